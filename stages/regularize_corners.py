"""Stage ``regularize_corners``: 3D glass panel models from the panels segmented in the frontal views (the
paper, end of section 3.1.2).

Reads the frontal views' panel corners and authoritative panel masks (``03_segment``), the imported
scene, coarse mesh and coarse points (``01_import``); writes ``04_regularize/panels.json`` (a ``PanelSet``),
each frontal view's pose registered to those panels (``04_regularize/poses.json``, ``RegisteredPoses``:
``facade_pipeline.panels3d.poses``, which later stages read the cameras through) and per frontal view an
overlay (the segmented quads and the 3D panels projected over the view through its registered pose).
Quads cut by the image border ("complete": false) count with their corners away from the border.
Rejected rays (missed, grazing, ghost) and grid outliers are counted in the manifest; on synthetic
buildings the 3D corner error against gt/panels.json is added (gt is read for that metric only).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from facade_pipeline.config import RunSettings
from facade_pipeline.errors import InputError
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.panels3d.params import RegularizeConfig
from facade_pipeline.scene import ImportedScene
from stages import PIPELINE
from stages._runner import StageReport, main

#: panel-mask regions smaller than this (px) are specks (a hand edit's stray stroke), not panels: ignored
MASK_MIN_REGION_PX = 8
#: a panel whose quadrilateral overlaps its mask region with an IoU below this (0-1) is refitted from the
#: mask: the mask, which a person may have edited, wins where the two disagree
MASK_REFIT_IOU = 0.6
NAME = "regularize_corners"
DOC = "3D panel models: ray-cast segmented corners onto the coarse mesh, merge, regularise rows and columns"
# segment_panels writes the corners and masks; until it is part of the pipeline they are read as they are.
UPSTREAM: tuple[str, ...] = (("segment_panels",) if "segment_panels" in PIPELINE else ()) + (
    "import_photogrammetry",
)
OVERLAY_MIN_WIDTH_PX = 480  # small views are drawn upscaled to at least this width
Params = RegularizeConfig


def _segment_files(layout: BuildingLayout, scene: ImportedScene) -> list[tuple[Path, Path]]:
    """(corners JSON, mask PNG) of every frontal view, as listed by segment_panels' manifest if it runs."""
    pairs = [
        (layout.path("segment_corners", stem=v.stem), layout.path("segment_mask", stem=v.stem))
        for v in scene.frontal_views
    ]
    listed = set(read_manifest(layout, "segment_panels").outputs) if "segment_panels" in UPSTREAM else None
    for pair in pairs:
        for p in pair:
            if listed is not None and layout.relative(p) not in listed:
                raise InputError(
                    layout.manifest("segment_panels"),
                    f"{layout.relative(p)} among the outputs",
                    "it is not listed",
                )
            if not p.is_file():
                raise InputError(p, "a file of segment_panels (data_layout.md, Hand-off formats)", "no file")
    return pairs


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.images import image_size

    scene = ImportedScene.load(layout)
    files = [layout.import_scene, layout.import_coarse_mesh, layout.import_coarse_points]
    files += [layout.root / v.image for v in scene.frontal_views]
    for (corners, mask), view in zip(_segment_files(layout, scene), scene.frontal_views, strict=True):
        c = view.camera
        if image_size(mask) != (c.width, c.height):
            raise InputError(
                mask, f"a {c.width}x{c.height} mask (the frontal view)", "{}x{}".format(*image_size(mask))
            )
        files += [corners, mask]
    return files


def _observations(layout: BuildingLayout, scene: ImportedScene, params: Params):
    """The reconciled panel quads of every frontal view and the mask reconciliation counts."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.panels3d.observations import Quad, reconcile_with_mask
    from facade_pipeline.segmentation.result import ViewSegmentation

    quads, complete, view = [], [], []
    counts = {"dropped": 0, "refit": 0, "added": 0}
    views = scene.frontal_views
    _segment_files(layout, scene)  # listed by segment_panels' manifest and present, else it raises
    for i, v in enumerate(tqdm(views, desc="regularize: views", unit="view", file=sys.stderr)):
        seg = ViewSegmentation.load(layout, v.stem, v.camera.width, v.camera.height)
        observed = tuple(Quad(p.corners_px, p.complete) for p in seg.panels) if seg.facade_found else ()
        found, stats = reconcile_with_mask(
            observed, seg.mask, MASK_MIN_REGION_PX, MASK_REFIT_IOU
        )
        if stats["merged"]:
            raise InputError(
                layout.path("segment_mask", stem=v.stem),
                "one mask region per panel, the frame bars between panels black (a panel mask)",
                f"{stats['merged']} region(s) spanning several panels and much more than them (frames "
                "painted over): paint the bars between panels black, or delete the file to have it made anew",
            )
        for k in counts:
            counts[k] += stats[k]
        for q in found:
            quads.append(q.corners_px)
            complete.append(q.complete)
            view.append(i)
    return quads, complete, view, counts


def _registered_poses(scene: ImportedScene, quads: list, complete: list, view: list, panels):
    """Each frontal view's pose refined against the 3D panels on its matched true corners, or kept."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.panels3d.grid import BORDER_MARGIN_PX, true_corners
    from facade_pipeline.panels3d.poses import RegisteredPoses, match_corners, refine_pose

    cameras = [v.camera for v in scene.frontal_views]
    ok = true_corners(quads, np.asarray(complete, bool), view, cameras, BORDER_MARGIN_PX)
    out = []
    for i, v in enumerate(scene.frontal_views):
        mine = [q for q, k in enumerate(view) if k == i]
        px, world = match_corners([quads[q] for q in mine], ok[mine], panels, v.camera)
        out.append(refine_pose(v.camera, px, world, v.stem))
    return RegisteredPoses(tuple(out))


def _truth_metrics(layout: BuildingLayout, scene: ImportedScene, panels, poses) -> dict:
    """Corner error against gt/panels.json, and the frontal views' pose error against gt/frontal/sparse/0
    as imported and as registered, on synthetic buildings (metrics only)."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.meshing.metrics import corner_errors
    from facade_pipeline.synthetic.truth import SyntheticTruth

    if not SyntheticTruth.available(layout, "panels"):
        return {}
    truth = SyntheticTruth.load(layout, scene.georef_from_local)
    out = {**corner_errors(panels, truth.panel_corners()), "true_panels": len(truth.panel_corners())}
    if layout.gt("frontal_sparse_dir").is_dir() and poses.views:
        from facade_pipeline.panels3d.poses import pose_error

        registered = {p.stem: p.cam_from_world for p in poses.views}
        errs = [
            (pose_error(v.camera.cam_from_world, t), pose_error(registered[v.stem], t))
            for v in scene.frontal_views
            for t in [truth.frontal_camera(v.stem).cam_from_world]
        ]
        for k, name in enumerate(("rotation_deg", "centre_m")):
            out[f"pose_{name}_median_imported"] = round(float(np.median([e[0][k] for e in errs])), 6)
            out[f"pose_{name}_median"] = round(float(np.median([e[1][k] for e in errs])), 6)
    return {"truth": out}


def _overlays(layout: BuildingLayout, scene: ImportedScene, quads: list, view: list, panels) -> list[Path]:
    """Write one overlay per frontal view; returns their paths."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.images import read_image, write_image
    from facade_pipeline.meshing.overlay import panels_over_view, upscale_factor

    out = []
    for i, v in enumerate(scene.frontal_views):
        factor = upscale_factor(v.camera.width, OVERLAY_MIN_WIDTH_PX)
        mine = [q for q, k in zip(quads, view, strict=True) if k == i]
        img = panels_over_view(read_image(layout.root / v.image), v.camera, mine, panels, factor)
        out.append(layout.path("regularize_overlay", stem=v.stem))
        write_image(out[-1], img)
    return out


def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.geometry.raycast import MeshRaycaster
    from facade_pipeline.io.meshes import read_mesh, read_points
    from facade_pipeline.panels3d.grid import build_panel_set
    from facade_pipeline.panels3d.poses import registered_scene
    from facade_pipeline.segmentation.building import surveyed_pitch_m

    scene = ImportedScene.load(layout)
    mesh = read_mesh(layout.import_coarse_mesh)
    rc = MeshRaycaster(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    points = np.asarray(read_points(layout.import_coarse_points).points)
    quads, complete, view, counts = _observations(layout, scene, params)
    # the lengths' unit is needed only where there are panels to place
    pitch = surveyed_pitch_m(layout, needed=bool(quads))
    params = dataclasses.replace(params, unit_m=pitch if np.isfinite(pitch) else None)
    cameras = [v.camera for v in scene.frontal_views]
    panels, metrics = build_panel_set(quads, complete, view, cameras, rc, points, params)
    if cameras and not panels.panels and params.require_panels:
        raise InputError(
            layout.stage_dir("segment_panels"),
            f"glass panels in the {len(cameras)} frontal views",
            f"none ({len(quads)} quads segmented: {_why_none(layout, scene)}): check the frontal views' "
            "poses and [segment_panels.grid] sizes (fractions of the building's pitch), paint the masks by "
            "hand, or set [regularize_corners] require_panels = false to go on without mesh correction",
        )
    out = layout.path("regularize_panels")
    panels.save(out)
    poses = _registered_poses(scene, quads, complete, view, panels)
    poses.save(layout.path("regularize_poses"))
    # drawn through the registered poses, the cameras every later stage reads: a person checks those
    overlays = _overlays(layout, registered_scene(layout), quads, view, panels)
    metrics = {
        "n_frontal_views": len(cameras),
        **({} if panels.panels else {"note": _no_panels_note(len(cameras))}),
        "coarse_triangles_degenerate": rc.n_dropped,
        **{f"mask_panels_{k}": n for k, n in counts.items()},
        **metrics,
        "poses": poses.summary(),
        **_truth_metrics(layout, scene, panels, poses),
    }
    return StageReport([out, layout.path("regularize_poses"), *overlays], metrics)


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    return [layout.path("regularize_panels"), layout.path("regularize_poses")]


def _no_panels_note(n_frontal: int) -> str:
    if n_frontal == 0:
        return "no frontal views: no panels, no mesh correction"
    return "no panels found in the frontal views (require_panels = false): no mesh correction"


def _why_none(layout: BuildingLayout, scene: ImportedScene) -> str:
    """What segment_panels said about the views where it found no facade (its manifest), in a few words."""
    try:
        reasons = read_manifest(layout, "segment_panels").metrics.get("views_without_facade") or {}
    except InputError:
        reasons = {}
    if not reasons:
        return "no view's quads could be placed on the coarse mesh"
    first = "; ".join(f"{stem}: {why}" for stem, why in list(reasons.items())[:2])
    more = f" and {len(reasons) - 2} more" if len(reasons) > 2 else ""
    return f"{len(reasons)} of {len(scene.frontal_views)} views without a facade ({first}{more})"


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
