"""Geometry metrics against a synthetic truth (meshing/metrics.py and the closest-point query of
geometry/raycast.py they rest on): hand-computed cases and a brute-force point-triangle reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.meshing.metrics import corner_errors, sample_surface, surface_errors
from facade_pipeline.panels3d.model import Panel, PanelSet

SQUARE = (np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 2, 3]]))


def _closest_on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return a + t * (b - a)


def brute_force_distance(p: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Distance from point p [3] to a mesh, triangle by triangle: the foot of the perpendicular on the
    triangle's plane when it lies inside the triangle (all three edge tests agree), else the nearest point
    of its three edges."""
    best = math.inf
    for tri in triangles:
        a, b, c = vertices[tri]
        n = np.cross(b - a, c - a)
        n = n / np.linalg.norm(n)
        foot = p - ((p - a) @ n) * n
        signs = [np.cross(q1 - q0, foot - q0) @ n for q0, q1 in ((a, b), (b, c), (c, a))]
        if min(signs) >= 0 or max(signs) <= 0:
            best = min(best, float(np.linalg.norm(p - foot)))
        else:
            edges = [_closest_on_segment(p, q0, q1) for q0, q1 in ((a, b), (b, c), (c, a))]
            best = min(best, min(float(np.linalg.norm(p - e)) for e in edges))
    return best


def test_closest_hand_computed():
    pts = np.array([[0.5, 0.5, 0.3], [0.2, 0.7, -2.0], [2.0, 0.5, 0.0], [2.0, 2.0, 1.0], [0.5, 0.5, 0.0]])
    want = [0.3, 2.0, 1.0, math.sqrt(3.0), 0.0]
    closest, _, _ = MeshRaycaster(*SQUARE).closest(pts)
    np.testing.assert_allclose(np.linalg.norm(pts - closest, axis=1), want, atol=1e-6)  # float32 in open3d


def test_closest_matches_brute_force_on_a_tiny_mesh():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(6, 3))
    f = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [0, 4, 5]])
    pts = rng.normal(scale=2.0, size=(200, 3))
    closest, prim, _ = MeshRaycaster(v, f).closest(pts)
    got = np.linalg.norm(pts - closest, axis=1)
    want = [brute_force_distance(p, v, f) for p in pts]
    np.testing.assert_allclose(got, want, atol=2e-6)  # float32 in open3d
    assert set(prim.tolist()) <= set(range(len(f)))


def test_sample_surface_uniform_and_deterministic():
    pts, nrm = sample_surface(*SQUARE, 5000, np.random.default_rng(0))
    assert pts.shape == (5000, 3) and nrm.shape == (5000, 3)
    assert np.allclose(pts[:, 2], 0) and pts[:, :2].min() >= 0 and pts[:, :2].max() <= 1
    assert abs(pts[:, 0].mean() - 0.5) < 0.02 and abs(pts[:, 1].mean() - 0.5) < 0.02  # uniform by area
    assert np.allclose(nrm, [0, 0, 1])
    again, _ = sample_surface(*SQUARE, 5000, np.random.default_rng(0))
    np.testing.assert_array_equal(pts, again)


def _frames_beside() -> MeshRaycaster:
    """A frame strip far to the side of the glass square: never the nearer surface to the samples."""
    return MeshRaycaster(SQUARE[0] + [10.0, 0, 0], SQUARE[1])


def test_surface_errors_parallel_squares():
    shifted = SQUARE[0] + [0, 0, 0.25]
    out = surface_errors(shifted, SQUARE[1], MeshRaycaster(*SQUARE), _frames_beside(), 2000, 0.5, seed=1)
    assert out["glass_distance_mean_m"] == pytest.approx(0.25, abs=1e-6)
    assert out["glass_distance_p95_m"] == pytest.approx(0.25, abs=1e-6)
    assert out["glass_normal_error_mean_deg"] == pytest.approx(0.0, abs=1e-3)
    assert out["frame_distance_mean_m"] is None and out["samples_unmatched"] == 0


def test_surface_errors_statistics_and_normal_error_hand_computed():
    """A square tilted by 30 deg about x, rising from the glass: the distance of a sample at height y is
    y sin 30, so over uniform y in [0, 1] the mean is sin 30 / 2 and the 95th percentile 0.95 sin 30; the
    normal error is 30 deg everywhere. Samples beyond ``max_match_m`` are left out and counted."""
    s, c = math.sin(math.radians(30)), math.cos(math.radians(30))
    tilted = np.array([[0, 0, 0], [1, 0, 0], [1, c, s], [0, c, s]], float)
    glass, frames = MeshRaycaster(*SQUARE), _frames_beside()
    out = surface_errors(tilted, SQUARE[1], glass, frames, 20000, 10.0, seed=0)
    assert out["glass_distance_mean_m"] == pytest.approx(s / 2, abs=0.01)
    assert out["glass_distance_p95_m"] == pytest.approx(0.95 * s, abs=0.01)
    assert out["glass_normal_error_mean_deg"] == pytest.approx(30.0, abs=1e-3)
    assert out["glass_normal_error_p95_deg"] == pytest.approx(30.0, abs=1e-3)
    cut = surface_errors(tilted, SQUARE[1], glass, frames, 20000, 0.25, seed=0)
    assert cut["samples_unmatched"] == pytest.approx(20000 / 2, rel=0.05)  # y sin 30 > 0.25: half of y
    assert cut["glass_distance_mean_m"] == pytest.approx(0.125, abs=0.01)
    none = surface_errors(SQUARE[0] + [0, 0, 5.0], SQUARE[1], glass, frames, 100, 1.0)
    assert none["glass_distance_mean_m"] is None and none["samples_unmatched"] == 100  # None: JSON null


def test_surface_errors_splits_glass_and_frames_by_the_nearer_surface():
    frames = MeshRaycaster(SQUARE[0] + [1.0, 0, 0], SQUARE[1])  # frames beside the glass, same plane
    both = SQUARE[0] * [2.0, 1.0, 1.0] + [0, 0, 0.1]  # over glass and frames, 0.1 in front
    out = surface_errors(both, SQUARE[1], MeshRaycaster(*SQUARE), frames, 4000, 0.5, seed=2)
    assert out["glass_distance_mean_m"] == pytest.approx(0.1, abs=1e-5)
    assert out["frame_distance_mean_m"] == pytest.approx(0.1, abs=1e-5)
    assert out["samples_unmatched"] == 0


def _panel(corners: np.ndarray) -> Panel:
    return Panel(0, 0, 0, corners, np.array([0, 0, 1.0]), 0.0)


def test_corner_errors_hand_computed():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    true = np.stack([square, square + [3.0, 0, 0]])
    moved = true[1] + [[0.03, 0.04, 0.0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]  # one corner off by 0.05 m
    out = corner_errors(PanelSet((), (_panel(true[0]), _panel(moved))), true)
    assert out["corner_error_max_m"] == pytest.approx(0.05, abs=1e-12)
    assert out["corner_error_mean_m"] == pytest.approx(0.05 / 8, abs=1e-5)  # rounded to 5 decimals
    empty = {"corner_error_mean_m": None, "corner_error_max_m": None}
    assert corner_errors(PanelSet((), ()), true) == empty
    assert corner_errors(PanelSet((), (_panel(true[0]),)), np.zeros((0, 4, 3))) == empty


def test_surface_errors_leave_out_what_lies_on_the_body():
    """A mesh of the glass square 0.25 above it plus a roof square lying on the true body (beside the
    glass, 0.5 from it): without the body the roof's samples count as glass errors of 0.5 and more; with
    it they are left out and counted apart, and the glass error is the 0.25 offset alone."""
    glass = MeshRaycaster(*SQUARE)
    roof_v = SQUARE[0] + [1.5, 0.0, 0.0]
    body = MeshRaycaster(roof_v, SQUARE[1])
    v = np.concatenate([SQUARE[0] + [0, 0, 0.25], roof_v])
    f = np.concatenate([SQUARE[1], SQUARE[1] + 4])
    without = surface_errors(v, f, glass, _frames_beside(), 4000, 5.0, seed=2)
    assert without["glass_distance_p95_m"] > 0.5 and without["samples_off_facade"] == 0
    out = surface_errors(v, f, glass, _frames_beside(), 4000, 5.0, seed=2, other=body)
    assert out["glass_distance_mean_m"] == pytest.approx(0.25, abs=1e-6)
    assert out["samples_off_facade"] == pytest.approx(2000, rel=0.1) and out["samples_unmatched"] == 0
