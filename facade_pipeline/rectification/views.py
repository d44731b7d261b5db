"""One frontal view of stage ``rectify``: the coarse points it sees, the surface fitted to them, and the
overlay that shows the view beside its rectified image. Local frame, metres; pixels of the view."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.rectification.cylinder import (
    SurfaceFit,
    SurfaceFitError,
    fit_surface,
    implausible,
)
from facade_pipeline.rectification.params import SurfaceFitParams
from facade_pipeline.rectification.surface_map import ViewRectification


def view_points(
    points: np.ndarray,
    camera: PinholeCamera,
    hidden_by: MeshRaycaster | None = None,
    margin_m: float = np.inf,
) -> np.ndarray:
    """The points [N, 3] that project inside the image in front of the camera (Eq. 6). With ``hidden_by``,
    less those it hides: the line of sight meets the mesh more than ``margin_m`` before the point. A dense
    cloud holds the ground all around the facade; seen through the facade, it outnumbers the facade's own
    points and takes the plane fit (tests/rectification/test_rectify_hidden.py builds that case)."""
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


def fit_view(
    points: np.ndarray,
    cam: PinholeCamera,
    params: SurfaceFitParams,
    surface: str,
    occlusion_margin_m: float,
    unit_m: float,
    mesh: MeshRaycaster,
    source: Path,
) -> tuple[SurfaceFit | None, str]:
    """The surface a frontal view sees: a plane, or a plane or a cylinder when ``surface`` is "auto",
    fitted to the coarse ``points`` [N, 3] (file ``source``) that the view sees and ``mesh`` does not hide,
    and refused when it cannot be a facade (tilted, tight against the view's footprint, loose). Returns the
    fit, or None, and a status line that says why (``unit_m``: the frontal views' footprint, the unit of
    the fit's lengths)."""
    try:
        seen = view_points(points, cam, mesh, occlusion_margin_m)
        fit = fit_surface(seen, cam.center, params, unit_m, source, -cam.forward, curved=surface == "auto")
        depth = abs(float((fit.surface.origin - cam.center) @ cam.forward))
        why = implausible(fit, depth * cam.width / cam.K[0, 0], params)
        if why is not None:
            return None, f"no surface: implausible fit, {why}"
        return fit, "fitted"
    except SurfaceFitError as e:
        return None, f"no surface: {e}"


def overlay_image(
    image: np.ndarray, rectified: np.ndarray, rect: ViewRectification, scale: float
) -> np.ndarray:
    """Original (left) with the images of straight rectified grid lines, rectified image (right, at the
    original's height) with them."""
    H, W = image.shape[:2]
    size = (max(1, round(W * scale)), max(1, round(H * scale)))
    left = cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)
    k = size[1] / rect.height  # the rectified image drawn at the original's height
    right = cv2.resize(rectified, (max(1, round(rect.width * k)), size[1]), interpolation=cv2.INTER_AREA)
    for frac in np.linspace(0.1, 0.9, 5):
        for line in (
            np.stack([np.full(50, frac * rect.width), np.linspace(0, rect.height, 50)], 1),
            np.stack([np.linspace(0, rect.width, 50), np.full(50, frac * rect.height)], 1),
        ):
            cv2.polylines(right, [np.int32(line * k)], False, (255, 255, 0), 1)
            back = rect.to_original(line)
            back = back[np.isfinite(back).all(axis=1)]
            cv2.polylines(left, [np.int32(back * scale)], False, (255, 255, 0), 1)
    out = np.zeros((size[1], left.shape[1] + right.shape[1] + 4, 3), np.uint8)
    out[:, : left.shape[1]] = left
    out[:, left.shape[1] + 4 :] = right
    return out
