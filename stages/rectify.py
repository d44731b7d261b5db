"""Stage ``rectify``: every frontal view becomes a metric, fronto-parallel image of its fitted facade
surface (paper, 3.1.1, extended from curved facades to all), so that segmentation works in metres.

For each frontal view of ``01_import``: crop the coarse point cloud to the points that project into the
image (Eq. 6) and that the coarse mesh does not hide from the camera, fit a plane or cylinder robustly
(``rectification.views``, ``rectification.cylinder``), and sample the surface on a regular (arc length,
height) grid of ``metres_per_px`` (``rectification.surface_map``: a homography for a plane, the unrolled
cylinder otherwise). A view whose points cannot define a surface, or whose fitted surface is implausible
(tilted, tight, loose, or a map that moves pixels further than the view's size), is left unrectified, with
the coarse mesh's scale at its centre; a view whose surface is nearly edge-on or whose rectified image would
be too large is skipped with a warning. Both are listed in the manifest with the reason. Writes into
``02_rectify/``: the rectified image (none for a skipped view), the mapping (both directions and the scale),
the fitted surface and an overlay.
"""

from __future__ import annotations

import functools
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
from tqdm import tqdm

from facade_pipeline.batch.fanout import map_views, shared
from facade_pipeline.config import Range, RunSettings
from facade_pipeline.errors import UpstreamMissingError
from facade_pipeline.io.atomic import write_json
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.rectification.params import RectifyParams, SurfaceFitParams
from facade_pipeline.scene import ImportedScene, View
from stages._runner import StageReport, main

if TYPE_CHECKING:  # names for annotations only: the functions that use them import them
    from facade_pipeline.geometry.raycast import MeshRaycaster

NAME = "rectify"
DOC = "fit a plane or cylinder to each frontal view's points and resample the view as a metric facade image"
UPSTREAM: tuple[str, ...] = ("import_photogrammetry",)
log = logging.getLogger("facade_pipeline.stages")


@dataclass(frozen=True)
class Params(RectifyParams):
    surface: Literal["auto", "planar"]
    """``auto`` fits a plane or a cylinder per view; ``planar`` declares the facade flat: planes only."""
    fit: SurfaceFitParams
    """The robust surface fit (``[rectify.fit]``)."""
    occlusion_margin: Annotated[float, Range(0.0, infinite=True)]
    """A coarse point whose line of sight meets the coarse mesh more than this (of the frontal views'
    footprint, ``surface_map.frontal_footprint_m``) before it is hidden and left out of the fit (the ground
    and surroundings behind the facade); inf: every point is kept."""


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    """scene.json, the coarse points and mesh and the frontal images of a completed import."""
    scene = ImportedScene.load(layout)
    files = [layout.import_scene, layout.import_coarse_points, layout.import_coarse_mesh]
    files += [layout.import_frontal_image(v.stem) for v in scene.frontal_views]
    for f in files:
        if not f.is_file():
            raise UpstreamMissingError(f, "a file written by import_photogrammetry", "no file")
    return files


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    return []  # per-view outputs are only known once the import ran; the manifest lists them


def rectify_one(
    layout: BuildingLayout,
    view: View,
    points: np.ndarray,
    params: Params,
    mesh: MeshRaycaster,
    overlay_scale: float,
    unit_m: float,
) -> tuple[list[Path], dict]:
    """Fit, rectify and write one view (``mesh``: the coarse mesh, which hides points and gives the scale
    of a view without a surface; ``unit_m``: the frontal views' footprint, the unit of the params'
    lengths); returns its outputs and its metrics."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.images import read_image, write_image
    from facade_pipeline.rectification.cylinder import implausible_displacement
    from facade_pipeline.rectification.surface_map import (
        Chart,
        ViewRectification,
        mesh_scale_m,
        rectify_view,
        warp_displacement_px,
        warp_image,
    )
    from facade_pipeline.rectification.views import fit_view, overlay_image

    t0 = time.perf_counter()
    source = layout.import_coarse_points
    margin = params.occlusion_margin * unit_m
    fit, status = (
        fit_view(points, view.camera, params.fit, params.surface, margin, unit_m, mesh, source)
        if np.isfinite(unit_m)
        else (None, "no surface: no frontal view's principal ray meets the coarse mesh (no footprint to "
              "measure the fit's lengths by)")
    )
    cam = view.camera
    rect, displacement = None, None
    if fit is not None:
        bounds = None
        if fit.part is not None:  # the canvas ends where the fitted part's points do, with the inlier band
            s, _ = Chart.of(fit.surface).coords(fit.part)
            margin = 3.0 * params.fit.inlier_scale * unit_m
            bounds = (float(s.min()) - margin, float(s.max()) + margin)
        rect = rectify_view(cam, fit.surface, params, bounds)
        if rect.kind != "skipped":  # edge-on or too large says more than the displacement it implies
            displacement = warp_displacement_px(cam, fit.surface)
            why = implausible_displacement(displacement, cam.width, cam.height, params.fit)
            if why is not None:
                fit, status, rect = None, f"no surface: implausible fit, {why}", None
    if rect is None:
        scale = mesh_scale_m(cam, lambda o, d: mesh.cast(o, d).t)
        rect = (
            ViewRectification.unrectified(cam, scale, status)
            if np.isfinite(scale)
            else ViewRectification.unrectified(
                cam, scale, f"{status}; the coarse mesh is not in the view", "skipped"
            )
        )
    if rect.kind == "skipped":
        log.warning("rectify: view %s skipped: %s", view.stem, rect.reason)
    outs = [layout.path("rectify_mapping", stem=view.stem), layout.path("rectify_surface", stem=view.stem)]
    rect.save(outs[0])
    write_json(outs[1], {"status": status, **({} if fit is None else fit.to_dict())})
    if rect.kind != "skipped":
        image = read_image(layout.import_frontal_image(view.stem))
        rectified = warp_image(image, rect)
        outs += [layout.path("rectify_image", stem=view.stem), layout.path("rectify_overlay", stem=view.stem)]
        write_image(outs[2], rectified)
        write_image(outs[3], overlay_image(image, rectified, rect, overlay_scale))
    poly = rect.polynomial
    metrics = {
        "kind": rect.kind,
        "fit": status,
        "reason": rect.reason,
        "radius_m": None if fit is None else _finite(fit.surface.radius_m),
        "fit_rms_m": None if fit is None else fit.rms_m,
        "metres_per_px": _finite(rect.metres_per_px),
        "size_px": [rect.width, rect.height],
        "polynomial_max_px": None if poly is None else max(poly[0].max_px, poly[1].max_px),
        "displacement_px": None if displacement is None else _finite(displacement),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return outs, metrics


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _coarse_geometry(points_path: Path, mesh_path: Path) -> tuple[np.ndarray, MeshRaycaster]:
    """The coarse points and a ray caster of the coarse mesh, which every view reads."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.geometry.raycast import MeshRaycaster
    from facade_pipeline.io.meshes import read_mesh, read_points

    points = np.asarray(read_points(points_path).points)
    coarse = read_mesh(mesh_path)
    return points, MeshRaycaster(np.asarray(coarse.vertices), np.asarray(coarse.triangles))


def _rectify_view(
    layout: BuildingLayout, params: Params, overlay_scale: float, unit_m: float, view: View
) -> tuple[list[Path], dict]:
    """``rectify_one`` in whichever process ``map_views`` runs it, the coarse geometry loaded once there."""
    points, mesh = shared(_coarse_geometry, layout.import_coarse_points, layout.import_coarse_mesh)
    return rectify_one(layout, view, points, params, mesh, overlay_scale, unit_m)


def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    scene = ImportedScene.load(layout)
    outputs: list[Path] = []
    per_view: dict[str, dict] = {}
    from facade_pipeline.rectification.surface_map import frontal_footprint_m

    views = scene.frontal_views
    _, mesh = shared(_coarse_geometry, layout.import_coarse_points, layout.import_coarse_mesh)
    unit = frontal_footprint_m([v.camera for v in views], lambda o, d: mesh.cast(o, d).t)
    one = functools.partial(_rectify_view, layout, params, settings.overlay_scale, unit)
    with tqdm(total=len(views), desc="rectify: frontal views", unit="img", file=sys.stderr) as bar:
        results = map_views(one, views, settings.view_workers, lambda _: bar.update())
    for view, (outs, metrics) in zip(views, results, strict=True):
        per_view[view.stem] = metrics
        outputs += outs
    kinds = [m["kind"] for m in per_view.values()]
    return StageReport(
        outputs,
        {
            "n_views": len(views),
            "footprint_unit_m": _finite(unit),
            **{f"n_{k}": kinds.count(k) for k in ("plane", "cylinder", "unrectified", "skipped")},
            "views_unrectified": {s: m["reason"] for s, m in per_view.items() if m["kind"] == "unrectified"},
            "views_skipped": {s: m["reason"] for s, m in per_view.items() if m["kind"] == "skipped"},
            "max_polynomial_residual_px": max(
                (m["polynomial_max_px"] or 0.0 for m in per_view.values()), default=0.0
            ),
            "seconds_per_view": round(sum(m["seconds"] for m in per_view.values()) / max(1, len(views)), 3),
            "views": per_view,
        },
    )


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
