"""Stage ``rectify``: unfold the curved facade in each frontal view into a planar-facade image (paper, 3.1.1).

For each frontal view of ``01_import``: crop the coarse point cloud to the points that project into the
image (Eq. 6) and that the coarse mesh does not hide from the camera, fit a cylinder robustly
(``geometry.cylinder``), and build degree-7 polynomial warps between the curved and the unfolded facade
(``geometry.rectification``). A flat patch (or ``surface = "planar"``) passes through with identity warps;
a view whose points cannot define a surface (too few, on one line) passes through too and is reported in
the manifest, not an error. Writes into ``02_rectify/``: the rectified image, the warps (forward and
inverse), the fitted surface and an overlay per view.
"""

from __future__ import annotations

import os

# The stage solves many small dense problems (625 x 36 SVDs); OpenBLAS threads only contend for the cores
# there (measured on 2 busy cores: 0.3 s per SVD with threads, 1 ms without). Set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Literal  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from facade_pipeline.errors import UpstreamMissingError  # noqa: E402
from facade_pipeline.geometry.camera import PinholeCamera  # noqa: E402
from facade_pipeline.geometry.cylinder import (  # noqa: E402
    SurfaceFit,
    SurfaceFitError,
    SurfaceFitParams,
    fit_surface,
)
from facade_pipeline.geometry.raycast import MeshRaycaster  # noqa: E402
from facade_pipeline.geometry.rectification import (  # noqa: E402
    RectifyParams,
    ViewRectification,
    rectify_view,
    warp_image,
)
from facade_pipeline.io.atomic import atomic_path, write_json  # noqa: E402
from facade_pipeline.io.images import read_image, write_image  # noqa: E402
from facade_pipeline.io.meshes import read_mesh, read_points  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.scene import ImportedScene, View  # noqa: E402
from stages._runner import StageReport, main  # noqa: E402

NAME = "rectify"
DOC = "fit a cylinder to each frontal view's points and warp curved facades into planar-facade images"
UPSTREAM: tuple[str, ...] = ("import_photogrammetry",)


@dataclass(frozen=True)
class Params:
    surface: Literal["auto", "planar"]
    """``auto`` fits a cylinder per view; ``planar`` declares the facade flat: identity warps, no fit."""
    fit: SurfaceFitParams
    """The robust cylinder fit (``[rectify.fit]``)."""
    warp: RectifyParams
    """Patch sampling and polynomial warps (``[rectify.warp]``)."""
    overlay_scale: int
    """The overlay is drawn this many times the image size (-)."""
    occlusion_margin_m: float
    """A coarse point whose line of sight meets the coarse mesh more than this (m) before it is hidden and
    left out of the fit (the ground and surroundings behind the facade); inf: every point is kept."""


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


def view_points(points: np.ndarray, camera: PinholeCamera, hidden_by: MeshRaycaster | None = None,
                margin_m: float = np.inf) -> np.ndarray:
    """The points [N, 3] that project inside the image in front of the camera (Eq. 6). With ``hidden_by``,
    less those it hides: the line of sight meets the mesh more than ``margin_m`` before the point. A dense
    cloud holds the ground all around the facade; seen through the facade, it outnumbers the facade's own
    points and takes the plane fit (benchmarks/RESULTS.md, session 21)."""
    uv, z = camera.project(points)
    x, y = uv[:, 0], uv[:, 1]
    inside = (z > 0) & (x >= 0) & (x <= camera.width) & (y >= 0) & (y <= camera.height)
    p = points[inside]
    if hidden_by is None or hidden_by.empty or not np.isfinite(margin_m) or len(p) == 0:
        return p
    d = p - camera.center
    dist = np.linalg.norm(d, axis=1)
    ok = dist > 0
    p, d, dist = p[ok], d[ok], dist[ok]
    t = hidden_by.cast(np.broadcast_to(camera.center, p.shape), d / dist[:, None]).t
    return p[~(t < dist - margin_m)]


def _fit(points: np.ndarray, view: View, params: Params, source: Path,
         mesh: MeshRaycaster | None) -> tuple[SurfaceFit | None, str]:
    if params.surface == "planar":
        return None, "declared planar"
    try:
        seen = view_points(points, view.camera, mesh, params.occlusion_margin_m)
        return fit_surface(seen, view.camera.center, params.fit, source, -view.camera.forward), "fitted"
    except SurfaceFitError as e:
        return None, f"no surface: {e}"


def _overlay(image: np.ndarray, rectified: np.ndarray, rect: ViewRectification, scale: int) -> np.ndarray:
    """Original (left) with the images of straight rectified grid lines, rectified image (right) with them."""
    H, W = image.shape[:2]
    left = cv2.resize(image, (W * scale, H * scale), interpolation=cv2.INTER_NEAREST)
    right = cv2.resize(rectified, (rect.width * scale, rect.height * scale), interpolation=cv2.INTER_NEAREST)
    for frac in np.linspace(0.1, 0.9, 5):
        for line in (np.stack([np.full(50, frac * rect.width), np.linspace(0, rect.height, 50)], 1),
                     np.stack([np.linspace(0, rect.width, 50), np.full(50, frac * rect.height)], 1)):
            cv2.polylines(right, [np.int32(line * scale)], False, (255, 255, 0), 1)
            cv2.polylines(left, [np.int32(rect.inverse(line) * scale)], False, (255, 255, 0), 1)
    out = np.zeros((max(left.shape[0], right.shape[0]), left.shape[1] + right.shape[1] + 4, 3), np.uint8)
    out[: left.shape[0], : left.shape[1]] = left
    out[: right.shape[0], left.shape[1] + 4:] = right
    return out


def rectify_one(layout: BuildingLayout, view: View, points: np.ndarray, params: Params,
                mesh: MeshRaycaster | None) -> tuple[list[Path], dict]:
    """Fit, warp and write one view (``mesh``: the coarse mesh, which hides points; None: no occlusion
    test); returns its outputs and its metrics."""
    t0 = time.perf_counter()
    fit, status = _fit(points, view, params, layout.import_coarse_points, mesh)
    src = layout.import_frontal_image(view.stem)
    cam = view.camera
    if fit is None:
        kind = "planar" if params.surface == "planar" else "no_surface"
        rect = ViewRectification.identity(cam.width, cam.height, kind)
    else:
        rect = rectify_view(cam, fit.surface, params.warp)
    image = read_image(src)
    out_img = layout.path("rectify_image", stem=view.stem)
    if rect.kind == "curved":
        rectified = warp_image(image, rect)
        write_image(out_img, rectified)
    else:  # identity: the image passes through byte for byte
        rectified = image
        with atomic_path(out_img) as tmp:
            shutil.copyfile(src, tmp)
    rect.save(layout.path("rectify_mapping", stem=view.stem))
    surface = {"status": status, **({} if fit is None else fit.to_dict())}
    write_json(layout.path("rectify_surface", stem=view.stem), surface)
    overlay = _overlay(image, rectified, rect, params.overlay_scale)
    write_image(layout.path("rectify_overlay", stem=view.stem), overlay)
    metrics = {"kind": rect.kind, "fit": status,
               "radius_m": None if fit is None else _finite(fit.surface.radius_m),
               "fit_rms_m": None if fit is None else fit.rms_m, "max_shift_px": rect.max_shift_px,
               "forward_rms_px": rect.forward.rms_px, "forward_max_px": rect.forward.max_px,
               "inverse_rms_px": rect.inverse.rms_px, "inverse_max_px": rect.inverse.max_px,
               "forward_condition": _finite(rect.forward.condition),
               "inverse_condition": _finite(rect.inverse.condition),
               "seconds": round(time.perf_counter() - t0, 3)}
    keys = ("rectify_mapping", "rectify_surface", "rectify_overlay")
    outs = [out_img] + [layout.path(k, stem=view.stem) for k in keys]
    return outs, metrics


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def run(layout: BuildingLayout, params: Params) -> StageReport:
    scene = ImportedScene.load(layout)
    points = np.asarray(read_points(layout.import_coarse_points).points)
    mesh = None
    if params.surface != "planar" and np.isfinite(params.occlusion_margin_m):
        coarse = read_mesh(layout.import_coarse_mesh)
        mesh = MeshRaycaster(np.asarray(coarse.vertices), np.asarray(coarse.triangles))
    outputs: list[Path] = []
    per_view: dict[str, dict] = {}
    views = scene.frontal_views
    for view in tqdm(views, desc="rectify: frontal views", unit="img", file=sys.stderr):
        outs, per_view[view.stem] = rectify_one(layout, view, points, params, mesh)
        outputs += outs
    kinds = [m["kind"] for m in per_view.values()]
    curved = [m for m in per_view.values() if m["kind"] == "curved"]
    return StageReport(outputs, {
        "n_views": len(views),
        "n_curved": kinds.count("curved"),
        "n_planar": kinds.count("planar"),
        "n_no_surface": kinds.count("no_surface"),
        "views_without_surface": [s for s, m in per_view.items() if m["kind"] == "no_surface"],
        "max_forward_residual_px": max((m["forward_max_px"] for m in curved), default=0.0),
        "max_inverse_residual_px": max((m["inverse_max_px"] for m in curved), default=0.0),
        "seconds_per_view": round(sum(m["seconds"] for m in per_view.values()) / max(1, len(views)), 3),
        "views": per_view,
    })


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
