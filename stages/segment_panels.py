"""Stage ``segment_panels``: glass panels of each frontal view by MAP estimation of the panel grid (paper,
3.1.2), on the metric rectified image (sizes in metres, turned into pixels with its scale), with the
corners mapped back to the original view through the rectification. The frame bars of every view are
found first; the building's frame depth and bar width per family (medians over the views: one facade's
frames share them) then correct each view's frame parallax and widen the bars a view found too thin. A
view whose grid is not the building's (none found, or a pitch or bar width beyond the building's median:
``segmentation.building``) is sought again at the building's pitch, and listed in the manifest
(``views_off_the_building_grid``) with the reason and the outcome.

Reads ``02_rectify`` (rectified image and warps per view) and ``01_import`` (the views' sizes, the original
images for the overlays). Writes the ``03_segment`` hand-off of data_layout.md ("Hand-off formats"):
``corners/{stem}.json``, the authoritative ``masks/{stem}.png`` (255 on panel glass) and
``overlays/{stem}.png``. A view with no facade in it, or one that rectify skipped, gets
``facade_found: false`` with the reason, an empty mask, and is listed in the manifest.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from facade_pipeline.batch.fanout import map_views, shared
from facade_pipeline.config import RunSettings
from facade_pipeline.errors import UpstreamMissingError
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.scene import ImportedScene, View
from facade_pipeline.segmentation.params import SegmentParams
from stages._runner import StageReport, main

if TYPE_CHECKING:  # names for annotations only: the functions that use them import them
    from facade_pipeline.geometry.raycast import MeshRaycaster
    from facade_pipeline.rectification.surface_map import ViewRectification
    from facade_pipeline.segmentation.frames import FrameBars
    from facade_pipeline.segmentation.openings import Panel
    from facade_pipeline.segmentation.panels import Segmentation
    from facade_pipeline.segmentation.parallax import ParallaxField
    from facade_pipeline.segmentation.result import SegmentedPanel

NAME = "segment_panels"
DOC = "find the glass panels of each frontal view (MAP panel grid): corners, panel mask, overlay"
UPSTREAM: tuple[str, ...] = ("rectify", "import_photogrammetry")
#: outputs a person may fix by hand (the README's route for a missed panel): an edit is not damage
EDITABLE: tuple[str, ...] = ("segment_mask",)


Params = SegmentParams


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    """The rectified images and mappings of a completed rectify run (a view rectify skipped has a mapping
    and no image), the frontal views and scene.json."""
    written = set(read_manifest(layout, "rectify").outputs)
    scene = ImportedScene.load(layout)
    files = [layout.import_scene, layout.import_coarse_mesh, layout.import_coarse_points]
    for v in scene.frontal_views:
        mapping = layout.path("rectify_mapping", stem=v.stem)
        image = layout.path("rectify_image", stem=v.stem)
        need = (
            [mapping]
            + ([image] if layout.relative(image) in written else [])
            + [layout.import_frontal_image(v.stem)]
        )
        for f in need:
            if f.parent.parent.name == "02_rectify" and layout.relative(f) not in written:
                raise UpstreamMissingError(
                    f,
                    "an output listed in the rectify manifest (run `doit rectify`)",
                    "a view that rectify did not write",
                )
            if not f.is_file():
                raise UpstreamMissingError(f, "a file written by an upstream stage", "no file")
            files.append(f)
    return files


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    return []  # per-view outputs are only known once the import ran; the manifest lists them


def _to_view(panel: Panel, rect: ViewRectification, width: int, height: int) -> SegmentedPanel:
    """The panel with its corners mapped back to the original view and kept inside it."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.segmentation.result import SegmentedPanel

    back = np.clip(rect.to_original(panel.corners), [0.0, 0.0], [float(width), float(height)])
    return SegmentedPanel(panel.row, panel.col, back, panel.corners, panel.complete)


def _overlay(image: np.ndarray, panels: list[Panel], rect: ViewRectification, scale: float) -> np.ndarray:
    """The view with each panel's outline (mapped back: curved where the facade is) and corners."""
    # imported here, not at the top: doit loads every stage module to build its task list
    import cv2

    H, W = image.shape[:2]
    size = (max(1, round(W * scale)), max(1, round(H * scale)))
    out = cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)
    t = np.linspace(0.0, 1.0, 12)[:, None]
    thick = max(1, round(min(size) / 300))
    for p in panels:
        c = p.corners
        outline = rect.to_original(np.concatenate([c[i] + t * (c[(i + 1) % 4] - c[i]) for i in range(4)]))
        outline = outline[np.isfinite(outline).all(axis=1)]
        if len(outline) < 2:
            continue
        colour = (0, 255, 0) if p.complete else (255, 160, 0)
        cv2.polylines(out, [np.int32(np.rint(outline * scale))], True, colour, thick, cv2.LINE_AA)
        centre = outline.mean(axis=0) * scale
        cv2.putText(
            out,
            f"{p.row},{p.col}",
            (int(centre[0]) - 8, int(centre[1]) + 4),
            cv2.FONT_HERSHEY_PLAIN,
            0.8 * thick,
            colour,
            thick,
            cv2.LINE_AA,
        )
    return out


#: grid step (px of the rectified image) on which a view's parallax coordinate is sampled: P changes
#: smoothly (a bar's pitch holds many steps), so bilinear reading between samples is far below a pixel
PARALLAX_STEP_PX = 8.0


def parallax_field(rect: ViewRectification, view: View) -> ParallaxField | None:
    """The parallax coordinate of the segmented image (``segmentation.parallax``): from the fitted surface
    for a rectified view (``surface_map.parallax_grid``), the distance from the principal point for a view
    that is not rectified; None where it is not finite."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.rectification.surface_map import parallax_grid
    from facade_pipeline.segmentation.parallax import ParallaxField

    if rect.chart is None:
        cx, cy = view.camera.K[:2, 2]
        return ParallaxField.about((float(cx), float(cy)), rect.width, rect.height)
    distance = abs(float(rect.chart.surface().signed_distance(view.camera.center[None])[0]))
    field = ParallaxField(*parallax_grid(rect, PARALLAX_STEP_PX), distance)
    return field if np.isfinite(field.p).all() else None


def survey_one(layout: BuildingLayout, view: View, params: Params) -> tuple[FrameBars | None, float]:
    """The frame bars the survey finds in one view (``frames.survey_frames``: sizes relative to the view,
    before the building's pitch is known; None for a view rectify skipped) and the seconds it took. Their
    pitches and bar widths give the building's pitch and widest bars, their parallax fits the frames' depth
    before the building's pitch is known."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.images import read_image
    from facade_pipeline.rectification.surface_map import ViewRectification, valid_region
    from facade_pipeline.segmentation.frames import survey_frames

    t0 = time.perf_counter()
    rect = ViewRectification.load(layout.path("rectify_mapping", stem=view.stem))
    if rect.kind == "skipped":
        return None, time.perf_counter() - t0
    image = read_image(layout.path("rectify_image", stem=view.stem))
    planar = rect.chart is not None and rect.chart.curvature_per_m == 0.0
    found = survey_frames(image, params, rect.metres_per_px, valid_region(rect), parallax_field(rect, view),
                          None, planar)
    return found, time.perf_counter() - t0


def find_one(
    layout: BuildingLayout, view: View, params: Params, mesh: MeshRaycaster, unit_m: float,
    pitch_m: dict[str, tuple[float, float]] | None = None, bar_max_m: dict[str, float] | None = None,
    predicted: bool = False, side_depth_m: dict[str, float] | None = None,
) -> tuple[ViewRectification, FrameBars | None, float]:
    """The rectification of one view and the frame bars in it (None for a view rectify skipped), and the
    seconds it took (``mesh``: the coarse mesh, which tells where the facade surface is; ``unit_m``: the
    building's pitch, ``building.survey_unit_m``; ``pitch_m``: the pitches sought and ``bar_max_m`` the
    widest bars, per family, ``predicted``: those pitches are the building's, and ``side_depth_m``: the
    frames' depth the surveys measured, ``frames.find_frames``)."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.images import read_image
    from facade_pipeline.rectification.surface_map import ViewRectification, facade_support, valid_region
    from facade_pipeline.segmentation.frames import find_frames

    t0 = time.perf_counter()
    rect = ViewRectification.load(layout.path("rectify_mapping", stem=view.stem))
    if rect.kind == "skipped":
        return rect, None, time.perf_counter() - t0
    valid = valid_region(rect)
    parallax = parallax_field(rect, view)
    image = read_image(layout.path("rectify_image", stem=view.stem))
    support = facade_support(rect, lambda o, d: mesh.cast(o, d).t, params.surface_tolerance * unit_m)
    planar = rect.chart is not None and rect.chart.curvature_per_m == 0.0
    found = find_frames(image, params, rect.metres_per_px, unit_m, valid, parallax, support, planar, pitch_m,
                        bar_max_m, predicted, side_depth_m)
    return rect, found, time.perf_counter() - t0


def with_building_grid(
    layout: BuildingLayout, views: list[View], found: list[tuple[ViewRectification, FrameBars | None, float]],
    params: Params, mesh: MeshRaycaster, width_m: dict[str, float], unit_m: float,
    bar_max_m: dict[str, float] | None = None, side_depth_m: dict[str, float] | None = None,
) -> tuple[list[tuple[ViewRectification, FrameBars | None, float]], dict[str, str]]:
    """``found`` with the building's grid tried on every view whose own grid is not it (none, or a pitch
    or bar width beyond the building's: ``building.disagreement``): sought again at the building's pitches
    (``building.pitch_range_m``), the view takes that grid where both families are found there, inside the
    range (``building.within``); failing that, a family off the building's pitch sought there alone, the
    other at any pitch, where it is found there and the other at all (``building.sought_again``); it keeps
    its own otherwise. Returns them and, per such view, why it disagreed and what the building's grid
    gave (``bar_max_m``: the widest bars sought, ``side_depth_m``: the surveys' frame depth, as
    ``find_one``)."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.segmentation.building import (
        building_pitch_m,
        disagreement,
        pitch_range_m,
        sought_again,
    )

    pitch = building_pitch_m([f for _, f, _ in found])
    wanted = pitch_range_m(pitch, params.grid)
    out, why = list(found), {}
    for i, (view, (rect, frames, seconds)) in enumerate(zip(views, found, strict=True)):
        reason = disagreement(frames, pitch, width_m, params.grid)
        if not reason:
            continue
        outcome = ""
        # a bar width of its own alone is the bars' business (``frames.widen_narrow_bars``), not the grid's
        if ("grid" in reason or "pitch" in reason) and len(wanted) == 2:
            spent = []

            def seek(ranges, view=view, spent=spent):
                _, again, more = find_one(layout, view, params, mesh, unit_m, ranges, bar_max_m, True,
                                            side_depth_m)
                spent.append(more)
                return again

            again, outcome = sought_again({} if frames is None else frames.pitches_m(), wanted, seek)
            if again is not None:
                out[i] = (rect, again, seconds + sum(spent))
        why[view.stem] = "; ".join(reason.values()) + outcome
    return out, why


def write_one(
    layout: BuildingLayout,
    view: View,
    rect: ViewRectification,
    seg: Segmentation | None,
    overlay_scale: float,
    not_mirrored: np.ndarray | None = None,
) -> tuple[list[Path], dict]:
    """Write one view's three outputs from its segmentation (``panels.segment_frames``; None for a view
    rectify skipped), without the panels of units
    no pane mirrors (``not_mirrored``, per panel: ``mirror_openings``); returns them and the view's
    metrics."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.images import read_image, write_image
    from facade_pipeline.segmentation.result import ViewSegmentation, panel_labels

    t0 = time.perf_counter()
    W, H = view.camera.width, view.camera.height
    panels, ok, metrics, reason = [], False, {}, rect.reason if rect.kind == "skipped" else ""
    dropped = 0
    if seg is not None:
        kept = list(seg.panels)
        if not_mirrored is not None and not_mirrored.any():
            kept = [p for p, off in zip(seg.panels, not_mirrored, strict=True) if not off]
            dropped = len(seg.panels) - len(kept)
        labels = panel_labels([p.corners for p in kept], rect, W, H)
        ok = seg.facade_found and bool((labels >= 0).any())
        panels, metrics = (kept if ok else []), seg.metrics
        reason = "" if ok else (seg.reason or "no panel inside the view")
    result = ViewSegmentation(
        view.stem,
        W,
        H,
        rect.rectified,
        ok,
        reason,
        tuple(_to_view(p, rect, W, H) for p in panels),
        labels >= 0 if ok else np.zeros((H, W), bool),
    )
    out = result.save(layout)
    out.append(layout.path("segment_overlay", stem=view.stem))
    original = read_image(layout.import_frontal_image(view.stem))
    write_image(out[-1], _overlay(original, panels, rect, overlay_scale))
    metrics = {
        "facade_found": ok,
        "reason": reason,
        "n_panels": len(panels),
        "n_complete": sum(p.complete for p in panels),
        "n_occluded": sum(p.reason == "occluded" for p in panels),
        "n_not_mirrored": dropped,
        "rectified": rect.rectified,
        **{k: round(v, 5) if isinstance(v, float) else v for k, v in metrics.items()},
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return out, metrics


def not_mirrored(
    layout: BuildingLayout,
    views: list[View],
    found: list[tuple[ViewRectification, FrameBars | None, float]],
    segs: list[Segmentation | None],
    params: Params,
    pitch_m: dict[str, float],
) -> tuple[list[np.ndarray | None], dict]:
    """Per view, which of its panels belong to a unit the other views' panes do not mirror
    (``mirror.mirror_openings``; None for a view that takes no part: not rectified onto a plane, or
    without panels), and the figures behind it. Off where fewer than ``mirror.MIN_VIEWS`` planar views
    have panels, or the building's pitch is not known in both families."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.images import read_image
    from facade_pipeline.io.meshes import read_points
    from facade_pipeline.segmentation.mirror import MIN_VIEWS, MirrorView, facade_foot, mirror_openings

    taking = [i for i, ((rect, _, _), seg) in enumerate(zip(found, segs, strict=True))
              if seg is not None and seg.facade_found and seg.panels and rect.chart is not None
              and rect.chart.curvature_per_m == 0.0]
    out: list[np.ndarray | None] = [None] * len(found)
    if len(taking) < MIN_VIEWS or not {"x", "y"} <= set(pitch_m):
        return out, {}
    mirrors, complete = [], []
    for i in taking:
        stem = views[i].stem
        image = read_image(layout.path("rectify_image", stem=stem))
        mirrors.append(MirrorView(stem, found[i][0], image, [p.corners for p in segs[i].panels]))
        complete.append(np.array([p.complete for p in segs[i].panels]))
    ground = facade_foot(read_points(layout.import_coarse_points).points, mirrors[0].rect.chart.up)
    flags, judged = mirror_openings(mirrors, complete, (pitch_m["x"], pitch_m["y"]), ground,
                                    params.mirror_max_score)
    for i, f in zip(taking, flags, strict=True):
        out[i] = f
    return out, judged


def _coarse_raycaster(mesh_path: Path) -> MeshRaycaster:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.geometry.raycast import MeshRaycaster
    from facade_pipeline.io.meshes import read_mesh

    coarse = read_mesh(mesh_path)
    return MeshRaycaster(np.asarray(coarse.vertices), np.asarray(coarse.triangles))


def _find_view(
    layout: BuildingLayout, params: Params, unit_m: float, bar_max_m: dict[str, float],
    side_depth_m: dict[str, float], view: View,
) -> tuple[ViewRectification, FrameBars | None, float]:
    """``find_one`` in whichever process ``map_views`` runs it, the coarse mesh loaded once there."""
    return find_one(layout, view, params, shared(_coarse_raycaster, layout.import_coarse_mesh), unit_m,
                    bar_max_m=bar_max_m, side_depth_m=side_depth_m)


def _survey_view(layout: BuildingLayout, params: Params, view: View) -> tuple[FrameBars | None, float]:
    """``survey_one`` in whichever process ``map_views`` runs it."""
    return survey_one(layout, view, params)


def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    from facade_pipeline.rectification.surface_map import ViewRectification
    from facade_pipeline.segmentation.building import (
        building_bar_width_m,
        building_frame_parallax_m,
        building_pitch_m,
        survey_unit_m,
        surveyed_bar_max_m,
    )
    from facade_pipeline.segmentation.panels import segment_frames

    views = ImportedScene.load(layout).frontal_views
    outputs: list[Path] = []
    per_view: dict[str, dict] = {}
    with tqdm(total=len(views), desc="segment_panels: survey", unit="img", file=sys.stderr) as bar:
        surveyed = map_views(functools.partial(_survey_view, layout, params), views, settings.view_workers,
                             lambda _: bar.update())
    unit = survey_unit_m([{} if f is None else f.pitches_m() for f, _ in surveyed])
    bar_max = {} if unit is None else surveyed_bar_max_m([{} if f is None else f.bar_widths_m()
                                                          for f, _ in surveyed], params.grid.max_bar * unit)
    # the frames' depth the surveys' own parallax fits show, for the side faces of the bars sought wider; a
    # family pooled over the views' bars (no view's own fit gave it) is sought as surveyed: the survey's few
    # bars a view pool into a looser depth, and a slope too steep widens every bar sought
    side_depth, pooled = building_frame_parallax_m([f for f, _ in surveyed], params.parallax_max_slope)
    side_depth = {n: d for n, d in side_depth.items() if n not in pooled}
    if unit is None:  # no view shows a grid at any pitch: each is written without panels, saying so
        found = [(ViewRectification.load(layout.path("rectify_mapping", stem=v.stem)), None, s)
                 for v, (_, s) in zip(views, surveyed, strict=True)]
    else:
        with tqdm(total=len(views), desc="segment_panels: frame bars", unit="img", file=sys.stderr) as bar:
            found = map_views(functools.partial(_find_view, layout, params, unit, bar_max, side_depth), views,
                              settings.view_workers, lambda _: bar.update())
        found = [(r, f, s + t) for (r, f, s), (_, t) in zip(found, surveyed, strict=True)]
    depth, sides = building_frame_parallax_m([f for _, f, _ in found], params.parallax_max_slope)
    width = building_bar_width_m([f for _, f, _ in found])
    # the views off the building's grid are sought again here, one after another (few, and they need the
    # building's figures, known only now)
    mesh = shared(_coarse_raycaster, layout.import_coarse_mesh)
    found, disagreeing = ((found, {}) if unit is None
                          else with_building_grid(layout, views, found, params, mesh, width, unit, bar_max,
                                                 side_depth))
    pitch = building_pitch_m([f for _, f, _ in found])
    segs, spent = [], []
    for _, frames, _ in found:  # every view's panels first: the mirror pass below judges them together
        t0 = time.perf_counter()
        segs.append(None if frames is None else segment_frames(frames, params, depth, width, sides, pitch))
        spent.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    off, judged = not_mirrored(layout, views, found, segs, params, pitch)
    judged["seconds"] = round(time.perf_counter() - t0, 3)
    for view, (rect, _, seconds), seg, o, more in zip(views, found, segs, off, spent, strict=True):
        outs, per_view[view.stem] = write_one(layout, view, rect, seg, settings.overlay_scale, o)
        if unit is None and rect.kind != "skipped":
            per_view[view.stem]["reason"] = "the survey found no regular frame grid in any view at any pitch"
        per_view[view.stem]["seconds"] = round(per_view[view.stem]["seconds"] + seconds + more, 3)
        outputs += outs
    return StageReport(
        outputs,
        {
            "n_views": len(views),
            "n_views_with_facade": sum(m["facade_found"] for m in per_view.values()),
            "views_without_facade": {s: m["reason"] for s, m in per_view.items() if not m["facade_found"]},
            "n_panels": sum(m["n_panels"] for m in per_view.values()),
            "n_complete_panels": sum(m["n_complete"] for m in per_view.values()),
            "pitch_unit_m": unit,
            "pitch_m": {name: round(p, 5) for name, p in pitch.items()},
            "frame_depth_m": {name: round(d, 4) for name, d in depth.items()},
            "frame_side_depths_m": {name: [round(d, 4) if np.isfinite(d) else None for d in s]
                                    for name, s in sides.items()},
            "bar_width_m": {name: round(w, 4) for name, w in width.items()},
            "surveyed_bar_max_m": {name: round(w, 4) for name, w in bar_max.items()},
            "views_off_the_building_grid": disagreeing,
            "mirror": judged,
            # the building's pass over all views counts in their mean as much as their own work does
            "seconds_per_view": round((sum(m["seconds"] for m in per_view.values()) + judged["seconds"])
                                      / max(1, len(views)), 3),
            "views": per_view,
        },
    )


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
