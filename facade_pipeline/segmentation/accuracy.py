"""Accuracy of a segmentation against a synthetic building's truth (tests and benchmarks only: no stage
reads gt/). Pure functions over arrays and the true panels (``SyntheticTruth.panels``), local frame.

- corners: each predicted corner that is a true corner (not on the image border, where cut panels are
  closed) against the nearest true panel corner projected into the view (Eq. 6) through the view's true
  camera (gt/frontal/sparse/0: with "pose_noise" the imported camera is off by the noise), in pixels;
- count: true panels visible in the view = connected components (4-connected) of the true glass mask with
  at least ``min_area_px`` pixels, against the panels in the corners file;
- mask IoU per predicted panel against the true panel it overlaps most: the true panel's outline (its
  four edges along the true surface, projected through the true camera) rasterised at pixel centres. The
  segmentation's masks are panel quads through the glass corners, so glass hidden behind a proud frame
  counts as panel; the IoU against the visible glass (connected components of gt's glass mask) is reported
  beside it.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.rectification.surface_map import ViewRectification
from facade_pipeline.segmentation.result import SegmentedPanel, ViewSegmentation, panel_labels
from facade_pipeline.synthetic.truth import SyntheticTruth


def true_corners_px(panels: list[dict], camera: PinholeCamera) -> np.ndarray:
    """[T, 2] pixel positions of every true panel corner in front of ``camera``."""
    c = np.array([p["corners"] for p in panels], dtype=np.float64).reshape(-1, 3)
    uv, z = camera.project(c)
    return uv[z > 0]


def true_edges_px(
    panels: list[dict], camera: PinholeCamera, surface_point, samples: int = 9
) -> list[np.ndarray]:
    """Each true panel edge as [samples, 2] pixel positions along the true surface (``surface_point(a, b,
    t) -> [n, 3]`` interpolates between corners a and b on the facade, curved where it is)."""
    out = []
    for p in panels:
        c = np.asarray(p["corners"], dtype=np.float64)
        for i in range(4):
            pts = surface_point(c[i], c[(i + 1) % 4], np.linspace(0.0, 1.0, samples))
            uv, z = camera.project(pts)
            if np.all(z > 0):
                out.append(uv)
    return out


def corner_errors(
    pred_panels: Sequence[SegmentedPanel],
    true_px: np.ndarray,
    width: int,
    height: int,
    border_tol_px: float = 0.01,
) -> np.ndarray:
    """Distances [C] (px) from each predicted corner off the image border to the nearest true corner."""
    c = np.array([q for p in pred_panels for q in p.corners_px], dtype=np.float64).reshape(-1, 2)
    off = (
        (c[:, 0] > border_tol_px)
        & (c[:, 0] < width - border_tol_px)
        & (c[:, 1] > border_tol_px)
        & (c[:, 1] < height - border_tol_px)
    )
    c = c[off]
    if len(c) == 0 or len(true_px) == 0:
        return np.zeros(0)
    return np.linalg.norm(c[:, None] - true_px[None], axis=2).min(axis=1)


def glass_components(glass: np.ndarray, min_area_px: int) -> tuple[np.ndarray, list[int]]:
    """Labels [H, W] of the 4-connected components of the true glass mask and the ids of those kept."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(glass.astype(np.uint8), connectivity=4)
    return labels, [k for k in range(1, n) if stats[k, cv2.CC_STAT_AREA] >= min_area_px]


def panel_ious(pred_labels: np.ndarray, glass: np.ndarray, min_area_px: int, n_panels: int) -> np.ndarray:
    """IoU [P] of each of the ``n_panels`` predicted panels (pred_labels == p) with the true glass component
    it overlaps most; 0 for a panel that covers no pixel centre (a cut panel's sliver along the border)."""
    labels, kept = glass_components(glass, min_area_px)
    out = []
    for p in range(n_panels):
        mine = pred_labels == p
        if not mine.any():
            out.append(0.0)
            continue
        ids, counts = np.unique(labels[mine], return_counts=True)
        counts = np.where(np.isin(ids, kept), counts, 0)
        g = labels == ids[np.argmax(counts)] if counts.max() > 0 else np.zeros_like(mine)
        out.append(float((mine & g).sum() / (mine | g).sum()))
    return np.array(out)


def true_panel_labels(
    panels: list[dict], parts: list[dict], camera: PinholeCamera, samples: int = 9
) -> np.ndarray:
    """Labels [H, W] of the true panels in ``camera`` (index into ``panels``, -1: none): pixel centres
    inside the projected outline, whose edges follow the true surface (``samples`` per edge)."""
    from skimage.measure import points_in_poly

    W, H = camera.width, camera.height
    ys, xs = np.mgrid[0:H, 0:W]
    centres = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1)
    out = np.full(H * W, -1, dtype=np.int32)
    by_index = {part["index"]: part for part in parts}
    for k, p in enumerate(panels):
        c = np.asarray(p["corners"], dtype=np.float64)
        along = surface_interpolator(by_index[p["part_index"]])
        t = np.linspace(0.0, 1.0, samples)[:-1]
        outline = np.concatenate([along(c[i], c[(i + 1) % 4], t) for i in range(4)])
        uv, z = camera.project(outline)
        if not np.all(z > 0):
            continue
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        if hi[0] < 0 or hi[1] < 0 or lo[0] > W or lo[1] > H:
            continue
        box = (centres[:, 0] >= lo[0]) & (centres[:, 0] <= hi[0]) & (centres[:, 1] >= lo[1]) & (
            centres[:, 1] <= hi[1]
        )
        idx = np.flatnonzero(box & (out < 0))
        out[idx[points_in_poly(centres[idx], uv)]] = k
    return out.reshape(H, W)


def panel_ious_vs_panels(pred_labels: np.ndarray, true_labels: np.ndarray, n_panels: int) -> np.ndarray:
    """IoU [P] of each of the ``n_panels`` predicted panels (pred_labels == p) with the true panel
    (true_labels) it overlaps most; 0 for a predicted panel over no true panel or no pixel centre."""
    out = []
    for p in range(n_panels):
        mine = pred_labels == p
        ids, counts = np.unique(true_labels[mine], return_counts=True)
        counts = np.where(ids >= 0, counts, 0)
        if not mine.any() or counts.max() == 0:
            out.append(0.0)
            continue
        t = true_labels == ids[np.argmax(counts)]
        out.append(float((mine & t).sum() / (mine | t).sum()))
    return np.array(out)


def line_deviation_px(points: np.ndarray) -> float:
    """Largest distance (px) of points [N, 2] from their total-least-squares line."""
    c = points - points.mean(axis=0)
    normal = np.linalg.svd(c, full_matrices=False)[2][-1]
    return float(np.abs(c @ normal).max())


def surface_interpolator(part: dict):
    """``f(a, b, t) -> [n, 3]``: points between corners a and b [3] on a part of gt/scene.json
    (``SyntheticTruth.scene_parts``), along the cylinder (about ``axis_point``/``axis_direction``) for
    cylindrical parts, straight for planar ones."""
    if part["kind"] != "cylindrical":
        return lambda a, b, t: a[None] + np.asarray(t)[:, None] * (b - a)[None]
    o, u = np.asarray(part["axis_point"], float), np.asarray(part["axis_direction"], float)

    def f(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
        ha, hb = (a - o) @ u, (b - o) @ u
        ra, rb = a - o - ha * u, b - o - hb * u
        e1 = ra / np.linalg.norm(ra)
        e2 = np.cross(u, e1)
        phi = np.arctan2(rb @ e2, rb @ e1)
        r = np.linalg.norm(ra) + np.asarray(t)[:, None] * (np.linalg.norm(rb) - np.linalg.norm(ra))
        ang = np.asarray(t)[:, None] * phi
        h = ha + np.asarray(t)[:, None] * (hb - ha)
        return o + h * u + r * (np.cos(ang) * e1 + np.sin(ang) * e2)

    return f


def evaluate_view(layout, view, truth: SyntheticTruth, min_area_px: int) -> dict:
    """Every accuracy figure of one frontal view from the stage outputs and the truth (module docstring),
    in the local frame."""
    W, H = view.camera.width, view.camera.height
    cam, panels, parts = truth.frontal_camera(view.stem), truth.panels(), truth.scene_parts()
    seg = ViewSegmentation.load(layout, view.stem, W, H)
    rect = ViewRectification.load(layout.path("rectify_mapping", stem=view.stem))
    glass = truth.mask("glass", view.stem)
    errors = corner_errors(seg.panels, true_corners_px(panels, cam), W, H)
    _, kept = glass_components(glass, min_area_px)
    pred = panel_labels([p.corners_rectified_px for p in seg.panels], rect, W, H) if seg.panels else None
    ious = panel_ious(pred, glass, min_area_px, len(seg.panels)) if seg.panels else np.zeros(0)
    truth_labels = true_panel_labels(panels, parts, cam)
    ious_panel = panel_ious_vs_panels(pred, truth_labels, len(seg.panels)) if seg.panels else np.zeros(0)
    complete = np.array([p.complete for p in seg.panels], bool)
    straight = []
    for part in parts:
        mine = [p for p in panels if p["part_index"] == part["index"]]
        for uv in true_edges_px(mine, cam, surface_interpolator(part)):
            if uv.min() >= 0 and uv[:, 0].max() <= W and uv[:, 1].max() <= H:
                r = rect.to_rectified(uv)
                r = r[np.isfinite(r).all(axis=1)]  # rays past the fitted surface's silhouette miss it
                if len(r) >= 3:
                    straight.append(line_deviation_px(r))
    return {
        "corner_errors_px": errors,
        "n_true": len(kept),
        "n_pred": len(seg.panels),
        "iou_complete": ious_panel[complete],
        "iou_cut": ious_panel[~complete],
        "iou_visible_glass_complete": ious[complete],
        "iou_visible_glass_cut": ious[~complete],
        "edge_straightness_px": np.array(straight),
        "rectify_residual_px": 0.0 if rect.polynomial is None else max(w.max_px for w in rect.polynomial),
        "kind": rect.kind,
    }


def truth_as_real(truth: SyntheticTruth, stem: str, samples: int = 9) -> tuple[np.ndarray, list]:
    """Frontal view ``stem``'s truth in the layout of real photos with truth (``real_truth``): its glass
    mask [H, W] bool and, per true panel in front of the camera, its outline along the true surface
    projected through the true camera, as pixel indices (``panes.json``'s convention: the centre of the
    top-left pixel is 0). A panel wholly inside the view has its four corners as outline, so that
    ``real_truth.whole_panes`` takes it; one cut by the border keeps its points along the surface, off the
    view where it leaves it."""
    cam, parts = truth.frontal_camera(stem), truth.scene_parts()
    by_index = {part["index"]: part for part in parts}
    outlines = []
    for p in truth.panels():
        c = np.asarray(p["corners"], dtype=np.float64)
        uv, z = cam.project(c)
        if not np.all(z > 0):
            continue
        if uv.min() > 0 and (uv[:, 0] < cam.width).all() and (uv[:, 1] < cam.height).all():
            outlines.append((uv - 0.5).tolist())
            continue
        along = surface_interpolator(by_index[p["part_index"]])
        t = np.linspace(0.0, 1.0, samples)[:-1]
        uv, z = cam.project(np.concatenate([along(c[i], c[(i + 1) % 4], t) for i in range(4)]))
        if np.all(z > 0):
            outlines.append((uv - 0.5).tolist())
    return truth.mask("glass", stem), outlines
