"""Units without glass told by what the other views' panes mirror (``segmentation.mirror``), on views drawn
by ray tracing a planar facade whose panes mirror a textured ground and sky and whose one unit without glass
opens onto a room."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.config import default_params
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.rectification.surface_map import Chart, ViewRectification
from facade_pipeline.segmentation.mirror import MirrorView, mirror_openings
from facade_pipeline.segmentation.params import SegmentParams

MAX_SCORE = default_params("segment_panels", SegmentParams).mirror_max_score  # the shipped default
PITCH, PANE = 1.0, 0.8  # m: a 4 x 3 grid of units, frames 0.2 m wide
COLS, ROWS = 4, 3
GROUND = -3.0  # m: the facade's foot, along up
ROOM = (1, 2)  # (row from the bottom, column): no glass, a room 1.5 m deep behind it
M_PER_PX = 0.02
# the wall: the plane y = 0 facing -y, up +z, right +x; the canvas covers it from s = 0, h = 3 m down
CHART = Chart(np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0]),
              0.0)


def _camera(centre: np.ndarray) -> PinholeCamera:
    R = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # x right, y down, z forward (+y, into the wall)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ centre
    return PinholeCamera(np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]), T, 320, 240)


def _ground(p: np.ndarray) -> np.ndarray:
    x, y = p[:, 0], p[:, 1]
    return np.stack([0.35 + 0.15 * np.sin(0.3 * x) * np.cos(0.2 * y), 0.4 + 0.12 * np.cos(0.2 * x + 0.1 * y),
                     0.3 + 0.1 * np.sin(0.15 * y - 0.2 * x)], axis=1)


def _sky(d: np.ndarray) -> np.ndarray:
    el, az = np.arcsin(np.clip(d[:, 2], -1, 1)), np.arctan2(d[:, 0], -d[:, 1])
    return np.stack([0.45 + 0.2 * np.sin(2 * az) * (1 - el), 0.55 + 0.1 * np.cos(3 * az), 0.8 - 0.2 * el],
                    axis=1)


def _room(p: np.ndarray) -> np.ndarray:
    x, z = p[:, 0], p[:, 2]
    stripes = (np.floor(x / 0.15) % 2)[:, None]
    shade = 0.8 + 0.2 * np.cos(3 * z)
    return np.where(stripes > 0, [[0.7, 0.25, 0.2]], [[0.2, 0.3, 0.15]]) * shade[:, None]


def _draw(centre: np.ndarray, gain: float) -> tuple[ViewRectification, np.ndarray, list[np.ndarray]]:
    """One view's rectified canvas (what each pixel's ray shows), its rectification and the panes' quads."""
    cam = _camera(centre)
    W, H = int(COLS * PITCH / M_PER_PX), int(ROWS * PITCH / M_PER_PX)
    rect = ViewRectification("plane", W, H, M_PER_PX, cam, CHART, 0.0, ROWS * PITCH)
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    s, h = (xs * M_PER_PX).ravel(), (ROWS * PITCH - ys * M_PER_PX).ravel()
    P = CHART.point(s, h)
    d = P - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = d - 2 * (d @ CHART.normal)[:, None] * CHART.normal
    t = np.where(r[:, 2] < 0, (GROUND - P[:, 2]) / np.minimum(r[:, 2], -1e-9), np.inf)
    hit = P + np.where(np.isfinite(t), t, 0)[:, None] * r
    mirrored = np.where(np.isfinite(t)[:, None], _ground(hit), _sky(r))
    col, row = np.floor(s / PITCH).astype(int), np.floor(h / PITCH).astype(int)
    u, v = s - col * PITCH, h - row * PITCH
    lo, hi = (PITCH - PANE) / 2, (PITCH + PANE) / 2
    pane = (u > lo) & (u < hi) & (v > lo) & (v < hi)
    room = pane & (row == ROOM[0]) & (col == ROOM[1])
    behind = P + ((1.5 - P[:, 1]) / d[:, 1])[:, None] * d  # the room's back wall, y = 1.5 m
    colour = np.where(pane[:, None], mirrored, 0.9)
    colour = np.where(room[:, None], _room(behind), colour)
    image = np.clip(np.rint(255 * gain * colour), 0, 255).astype(np.uint8).reshape(H, W, 3)
    quads = []
    for rr in range(ROWS):
        for cc in range(COLS):
            x0, x1 = (cc * PITCH + lo) / M_PER_PX, (cc * PITCH + hi) / M_PER_PX
            y0, y1 = (ROWS * PITCH - rr * PITCH - lo) / M_PER_PX, (ROWS * PITCH - rr * PITCH - hi) / M_PER_PX
            quads.append(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))  # bl, br, tr, tl
    return rect, image, quads


CENTRES = [np.array(c) for c in ((0.6, -6.0, 1.2), (1.8, -5.5, 2.0), (3.1, -6.5, 1.0), (2.4, -7.0, 2.6),
                                 (1.2, -6.2, 0.4), (3.6, -5.8, 1.8))]
GAINS = (1.0, 0.7, 1.3, 0.85, 1.1, 0.9)  # each view's exposure


def _views(n: int) -> tuple[list[MirrorView], list[np.ndarray]]:
    views = []
    for i, (c, g) in enumerate(zip(CENTRES[:n], GAINS[:n], strict=True)):
        rect, image, quads = _draw(c, g)
        views.append(MirrorView(f"v{i}", rect, image, quads))
    return views, [np.ones(len(v.quads), bool) for v in views]


def test_the_unit_without_glass_is_no_pane_in_any_view_and_every_pane_stays():
    views, complete = _views(6)
    flags, judged = mirror_openings(views, complete, (PITCH, PITCH), GROUND, MAX_SCORE)
    room = ROOM[0] * COLS + ROOM[1]
    for f in flags:
        assert f.tolist() == [i == room for i in range(ROWS * COLS)]
    assert len(judged["not_mirrored"]) == 1 and judged["units_scored"] == ROWS * COLS
    (unit,) = judged["not_mirrored"].values()
    assert unit["score"] > MAX_SCORE and len(unit["views"]) >= 4
    assert judged["highest_kept_score"] < MAX_SCORE


def test_a_unit_fewer_views_score_is_not_judged():
    views, complete = _views(2)
    flags, judged = mirror_openings(views, complete, (PITCH, PITCH), GROUND, MAX_SCORE)
    assert not any(f.any() for f in flags)
    assert judged == {"units_scored": 0, "highest_kept_score": None, "not_mirrored": {}}


@pytest.mark.parametrize("gain", [0.5, 1.6])
def test_a_view_exposed_otherwise_changes_nothing(gain: float):
    """Each pair of views' exposure is taken out: no decision rests on a brightness."""
    views, complete = _views(6)
    rect, image, quads = _draw(CENTRES[1], GAINS[1] * gain)
    views[1] = MirrorView("v1", rect, image, quads)
    base = mirror_openings(_views(6)[0], complete, (PITCH, PITCH), GROUND, MAX_SCORE)[0]
    flags = mirror_openings(views, complete, (PITCH, PITCH), GROUND, MAX_SCORE)[0]
    assert all((a == b).all() for a, b in zip(flags, base, strict=True))
