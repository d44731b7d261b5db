"""Images a person looks at to check the 3D stages: the 3D panels projected over a frontal view
(``regularize_corners``) and shaded renders of the coarse and the corrected mesh (``correct_mesh``).

Small views are drawn at an integer upscale so that lines stay readable. Colours are RGB uint8.
"""

from __future__ import annotations

import cv2
import numpy as np

from facade_pipeline.bake.maps import bake_view
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.panels3d.model import PanelSet

QUAD_RGB = (230, 40, 40)  # segmented quads (03_segment)
PANEL_RGB = (40, 220, 60)  # 3D panels projected
LABEL_RGB = np.array([[200, 200, 200], [150, 120, 90], [90, 150, 230]], np.float32)  # other, frame, glass
SHIFT = 4  # cv2 fixed-point bits for sub-pixel polylines


def upscale_factor(width_px: int, min_width_px: int) -> int:
    """The integer factor that brings an image ``width_px`` wide to at least ``min_width_px`` (>= 1)."""
    return max(1, -(-int(min_width_px) // max(1, int(width_px))))


def scaled_camera(camera: PinholeCamera, factor: int) -> PinholeCamera:
    """``camera`` with ``factor`` times as many pixels each way (same view; pixel centres stay consistent:
    x_scaled = factor * x for continuous pixel coordinates)."""
    K = camera.K.copy()
    K[:2] *= factor
    return PinholeCamera(K, camera.cam_from_world, camera.width * factor, camera.height * factor)


def _polyline(img: np.ndarray, uv: np.ndarray, rgb: tuple[int, int, int], thickness: int) -> None:
    """Draw the closed polygon ``uv`` [M, 2] (continuous pixel coordinates) on ``img`` [H, W, 3]."""
    if not np.isfinite(uv).all():
        return
    pts = np.round((np.clip(uv, -1e5, 1e5) - 0.5) * (1 << SHIFT)).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(img, [pts], True, rgb, thickness, cv2.LINE_AA, SHIFT)


def panels_over_view(
    image: np.ndarray,
    camera: PinholeCamera,
    quads_px: list[np.ndarray],
    panels: PanelSet,
    factor: int,
    edge_samples: int = 16,
) -> np.ndarray:
    """The frontal ``image`` [H, W, 3] uint8 upscaled by ``factor`` with the segmented quads (Q arrays
    [4, 2] px, red) and the 3D ``panels`` projected through ``camera`` (green outlines, yellow corner dots;
    edges sampled on the part's surface so curved ones stay curved)."""
    img = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)
    img = np.ascontiguousarray(img[..., :3] if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2))
    for q in quads_px:
        _polyline(img, factor * np.asarray(q, np.float64), QUAD_RGB, 1)
    u = np.linspace(0.0, 1.0, edge_samples, endpoint=False)[:, None]
    for p in panels.panels:
        surface = panels.parts[p.part]
        szh = surface.coords(p.corners)
        outline = surface.points(np.concatenate([szh[k] + u * (szh[(k + 1) % 4] - szh[k]) for k in range(4)]))
        uv, z = camera.project(outline)
        if (z <= 0).any():
            continue
        _polyline(img, factor * uv, PANEL_RGB, 2)
        for c in factor * camera.project(p.corners)[0]:
            if np.isfinite(c).all() and np.abs(c).max() < 1e5:
                cv2.circle(img, tuple(int(x) for x in np.round(c - 0.5)), 3, (250, 230, 40), -1, cv2.LINE_AA)
    return img


def shaded_render(rc: MeshRaycaster, camera: PinholeCamera, labels: np.ndarray | None) -> np.ndarray:
    """[H, W, 3] uint8: the mesh seen by ``camera``, Lambert-shaded by a light at the camera raised and to
    the left, coloured by triangle ``labels`` [F] (other, frame, glass; all "other" when None); black where
    no triangle is hit."""
    baked = bake_view(rc, camera, 1 << 18, labels=labels)
    light_cam = np.array([-0.4, -0.5, -1.0])  # toward the light, camera axes (x right, y down, z forward)
    light = camera.world_from_cam[:3, :3] @ (light_cam / np.linalg.norm(light_cam))
    lambert = 0.25 + 0.75 * np.clip(baked.normal @ light.astype(np.float32), 0.0, 1.0)
    rgb = LABEL_RGB[baked.label] * lambert[..., None]
    rgb[~baked.valid] = 0.0
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def side_by_side(left: np.ndarray, right: np.ndarray, gap_px: int = 4) -> np.ndarray:
    """Two images [H, W, 3] next to each other with a white gap."""
    gap = np.full((left.shape[0], gap_px, 3), 255, np.uint8)
    return np.concatenate([left, gap, right], axis=1)
