"""The 2D panel observations of the frontal views (``03_segment``, read by
``facade_pipeline.segmentation.result.ViewSegmentation``) reconciled with the panel mask.

The mask is authoritative: a panel whose quadrilateral disagrees with its mask region is refitted from
the region, a region with no panel becomes a panel, and a panel with no mask pixel is dropped. Pixels:
x right, y down, pixel centres at (i + 0.5, j + 0.5); corners bottom-left, bottom-right, top-right,
top-left seen from outside.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class Quad:
    """One panel in one view: ``corners_px`` [4, 2] in the unrectified frontal image, and ``complete``
    (False: cut by the border or occluded). ``source`` says where it came from: corners, mask refit, mask."""

    corners_px: np.ndarray
    complete: bool = True
    source: str = "corners"


def quad_mask(corners_px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """[H, W] bool: the pixels whose centre lies inside the polygon ``corners_px`` [K, 2] (even-odd rule,
    evaluated on the polygon's bounding box only)."""
    c = np.asarray(corners_px, dtype=np.float64)
    out = np.zeros(shape, bool)
    x0, y0 = np.clip(np.floor(c.min(axis=0)).astype(int), 0, [shape[1], shape[0]])
    x1, y1 = np.clip(np.ceil(c.max(axis=0)).astype(int) + 1, 0, [shape[1], shape[0]])
    if x1 <= x0 or y1 <= y0:
        return out
    ys, xs = np.mgrid[y0:y1, x0:x1] + 0.5
    inside = np.zeros(xs.shape, bool)
    for k in range(len(c)):
        (ax, ay), (bx, by) = c[k], c[(k + 1) % len(c)]
        crosses = (ay > ys) != (by > ys)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = ax + (ys - ay) * (bx - ax) / (by - ay)
        inside ^= crosses & (xs < x_at)
    out[y0:y1, x0:x1] = inside
    return out


def fit_quad(region: np.ndarray) -> np.ndarray:
    """The corners [4, 2] (BL, BR, TR, TL, px) of a roughly axis-aligned quadrilateral region [H, W] bool:
    its extreme pixels along the two diagonals, taken at their outer pixel corners."""
    ys, xs = np.nonzero(region)
    picks = [np.argmin(xs - ys), np.argmax(xs + ys), np.argmax(xs - ys), np.argmin(xs + ys)]
    outer = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    return np.array([[xs[i], ys[i]] for i in picks], dtype=np.float64) + outer


#: a mask region this many times larger than the panels it holds together has lost its frame bars
MERGED_AREA_FACTOR = 1.5


def reconcile_with_mask(
    quads: tuple[Quad, ...], mask: np.ndarray, min_region_px: int, refit_iou: float
) -> tuple[list[Quad], dict[str, int]]:
    """Make the view's panels agree with its authoritative ``mask`` [H, W] bool (8-connected regions of at
    least ``min_region_px`` px). Returns the panels and counts: dropped (no mask pixel), refit (IoU with its
    region below ``refit_iou``), added (region without panel) and merged: regions over several panels and
    much larger than they are together (frames painted over: the mask no longer says where panels are,
    and keeping the panels as they were would ignore it, so the caller reports it)."""
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    sizes = np.bincount(labels.ravel(), minlength=n)
    owners: dict[int, list[int]] = {}
    best: list[int] = []
    for i, q in enumerate(quads):
        inside = labels[quad_mask(q.corners_px, mask.shape)]
        counts = np.bincount(inside, minlength=n)
        counts[0] = 0
        best.append(int(counts.argmax()) if counts.max() > 0 else 0)
        if best[-1]:
            owners.setdefault(best[-1], []).append(i)
    out: list[Quad] = []
    stats = {"dropped": 0, "refit": 0, "added": 0, "merged": 0}
    for lab, idx in owners.items():
        if len(idx) > 1:
            union = np.zeros(mask.shape, dtype=bool)
            for i in idx:
                union |= quad_mask(quads[i].corners_px, mask.shape)
            stats["merged"] += int(sizes[lab] > MERGED_AREA_FACTOR * union.sum())
    for i, q in enumerate(quads):
        lab = best[i]
        if lab == 0:
            stats["dropped"] += 1
            continue
        region = labels == lab
        poly = quad_mask(q.corners_px, mask.shape)
        iou = (region & poly).sum() / max(1, (region | poly).sum())
        if iou < refit_iou and len(owners[lab]) == 1 and sizes[lab] >= min_region_px:
            out.append(Quad(fit_quad(region), q.complete, "mask_refit"))
            stats["refit"] += 1
        else:
            out.append(q)
    for lab in range(1, n):
        if lab not in owners and sizes[lab] >= min_region_px:
            region = labels == lab
            ys, xs = np.nonzero(region)
            border = (
                xs.min() == 0
                or ys.min() == 0
                or xs.max() == mask.shape[1] - 1
                or ys.max() == mask.shape[0] - 1
            )
            out.append(Quad(fit_quad(region), not border, "mask"))
            stats["added"] += 1
    return out, stats
