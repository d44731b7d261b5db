"""Line segments of a (rectified) frontal view and their grouping by orientation.

Segments come from OpenCV's LSD (``cv2.createLineSegmentDetector``) run on the image upsampled by an integer
factor (small views: LSD needs a few pixels of support on each side of an edge). Positions are returned in
the view's pixels with centres at (i + 0.5, j + 0.5). Orientation grouping takes the length-weighted
histogram of segment angles (mod 180 deg) and keeps two families: the near-vertical one (mullions) and the
near-horizontal one (transoms), each within ``tolerance_deg`` of its dominant angle.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class SegmentFamilies:
    """Segments [S, 4] (x1, y1, x2, y2 in px) with the indices of the two families and their angles (rad,
    0 = along +x, measured toward +y, mod pi)."""

    segments: np.ndarray
    vertical: np.ndarray  # [Sv] indices into segments
    horizontal: np.ndarray  # [Sh]
    angle_vertical: float
    angle_horizontal: float


def to_gray(image: np.ndarray) -> np.ndarray:
    """RGB uint8 [H, W, 3] -> luminance float32 [H, W] in [0, 1]."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0


def detect_segments(image: np.ndarray, upsample: int, min_length_px: float) -> np.ndarray:
    """LSD segments [S, 4] of an RGB image [H, W, 3], at least ``min_length_px`` long (view pixels)."""
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    big = (
        cv2.resize(gray, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_CUBIC)
        if upsample > 1
        else gray
    )
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    found = lsd.detect(big)[0]
    if found is None:
        return np.zeros((0, 4))
    seg = (found.reshape(-1, 4).astype(np.float64) + 0.5) / upsample  # OpenCV: centres at integers
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    return seg[length >= min_length_px]


def segment_angles(segments: np.ndarray) -> np.ndarray:
    """Angles [S] in [0, pi) of segments [S, 4]."""
    return np.mod(np.arctan2(segments[:, 3] - segments[:, 1], segments[:, 2] - segments[:, 0]), np.pi)


def _dominant(angles: np.ndarray, weights: np.ndarray, near: float, window: float) -> float:
    """Length-weighted circular mean (mod pi) of the angles within ``window`` of ``near``; ``near`` "
    "if none."""
    diff = np.angle(np.exp(2j * (angles - near))) / 2  # signed difference mod pi
    sel = np.abs(diff) <= window
    if not sel.any():
        return near
    return float(near + np.average(diff[sel], weights=weights[sel]))


def group_segments(segments: np.ndarray, tolerance_deg: float, search_deg: float) -> SegmentFamilies:
    """Split segments into the near-vertical and near-horizontal families (``search_deg`` around 90 and 0
    deg finds each dominant angle; ``tolerance_deg`` around it keeps a segment in the family)."""
    if len(segments) == 0:
        empty = np.zeros(0, int)
        return SegmentFamilies(segments, empty, empty, np.pi / 2, 0.0)
    ang = segment_angles(segments)
    length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    out = []
    for near in (np.pi / 2, 0.0):
        dom = _dominant(ang, length, near, np.radians(search_deg))
        diff = np.abs(np.angle(np.exp(2j * (ang - dom))) / 2)
        out.append((np.flatnonzero(diff <= np.radians(tolerance_deg)), dom))
    (v, av), (h, ah) = out
    return SegmentFamilies(segments, v, h, av, ah)


def support_profile(segments: np.ndarray, axis: int, size: int, step: float, sigma_px: float) -> np.ndarray:
    """Line support along one image axis: at positions ``k * step`` (px), k = 0 .. size / step, the summed
    length of the segments whose mean coordinate along ``axis`` (0: x, for vertical segments) is there,
    Gaussian-smoothed with ``sigma_px``."""
    pos = np.arange(int(size / step) + 1) * step
    if len(segments) == 0:
        return np.zeros_like(pos)
    centre = 0.5 * (segments[:, axis] + segments[:, axis + 2])
    length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    k = np.exp(-0.5 * ((pos[:, None] - centre[None]) / sigma_px) ** 2)
    return k @ length
