"""Masks: a pixel belongs to a panel when its centre lies inside the panel's quad, the way the views are
sampled (one ray through each pixel centre); a centre exactly on a quad's edge is decided by the half-open
rule (inside on the left and top edges, outside on the right and bottom ones), so that a panel whose edge
falls on pixel centres takes the same pixels as the truth does and two panels sharing an edge never share a
pixel."""

from __future__ import annotations

import numpy as np

#: a point further than this (px) outside a quad's bounding box is outside the quad, whatever the rounding of
#: its edge equations (an error of some 1e-10 px at image coordinates): only the points within it are tested
QUAD_BOX_MARGIN_PX = 1e-3


def inside_quads(quads: list[np.ndarray], xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Index [...] of the convex quad (corners [4, 2] each) containing each point (xs, ys), -1 for none.

    Half-open (module docstring): a point on an edge is inside when the point moved by an infinitesimal
    step along (+1, +eps) (right, then down) is; the step is taken exactly by a tie-break on the edge
    equations, not by moving the points."""
    out = np.full(np.shape(xs), -1, dtype=np.int32)
    flat = out.reshape(-1)
    xs_all = np.asarray(xs, dtype=np.float64).reshape(-1)
    ys_all = np.asarray(ys, dtype=np.float64).reshape(-1)
    for k, q in enumerate(quads):
        q = np.asarray(q, dtype=np.float64)
        if _signed_area(q) < 0:  # orient so that the inner side of every edge has cross > 0
            q = q[::-1]
        lo, hi = q.min(axis=0) - QUAD_BOX_MARGIN_PX, q.max(axis=0) + QUAD_BOX_MARGIN_PX
        near = np.flatnonzero((xs_all >= lo[0]) & (xs_all <= hi[0]) & (ys_all >= lo[1]) & (ys_all <= hi[1]))
        xs_k, ys_k = xs_all[near], ys_all[near]
        inside = np.ones(len(near), bool)
        for i in range(4):
            (x0, y0), (x1, y1) = q[i], q[(i + 1) % 4]
            ex, ey = x1 - x0, y1 - y0
            cross = ex * (ys_k - y0) - ey * (xs_k - x0)  # > 0: on the inner side of this edge
            # d(cross)/d(step): along +x it is -ey, then along +y it is ex; the first non-zero decides a tie
            tie = np.where(ey != 0, -ey > 0, ex > 0)
            inside &= (cross > 0) | ((cross == 0) & tie)
        hit = near[inside]
        flat[hit[flat[hit] < 0]] = k
    return out


def _signed_area(q: np.ndarray) -> float:
    """Shoelace area of a polygon [n, 2]; > 0 when its vertices turn with the edge equations above
    (cross > 0 on the inner side)."""
    x, y = q[:, 0], q[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
