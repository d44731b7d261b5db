"""Per-view exposure gains estimated from the facade's opaque parts: the robust solve against known gains,
visibility, the masks, views without samples, and the whole estimate on synthetic64 against gains put
into its photos."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.training.data import TrainView
from facade_pipeline.training.exposure import (
    ExposureParams,
    estimate_exposures,
    observe,
    solve_log_gains,
    usable_mask,
)

PARAMS = ExposureParams(samples=4000, erode_px=1, occlusion_tolerance=0.005, min_samples=30, iterations=10)


def test_solve_recovers_known_gains_despite_outliers_and_gaps():
    """Radiance per point and channel, a log gain per view and channel; 10 % of observations replaced by
    junk (an occluder, a mislabelled triangle), 30 % missing: the gains come back to within 0.01, shifted
    to a geometric mean of 1 over the reference views."""
    rng = np.random.default_rng(0)
    n_views, n_points = 12, 3000
    radiance = rng.uniform(0.1, 0.6, (n_points, 3))
    g = rng.uniform(-0.3, 0.3, (n_views, 3))
    obs = radiance[None] * np.exp(g)[:, None, :]
    junk = rng.random(obs.shape[:2]) < 0.1
    obs[junk] = rng.uniform(0.05, 0.95, (int(junk.sum()), 3))
    obs[rng.random(obs.shape[:2]) < 0.3] = np.nan
    reference = list(range(1, n_views))
    est = solve_log_gains(obs.astype(np.float32), reference, 10, 30)
    want = g - g[reference].mean(axis=0)
    np.testing.assert_allclose(est.log_gain, want, atol=0.01)
    np.testing.assert_allclose(est.log_gain[reference].mean(axis=0), 0.0, atol=1e-6)


def test_solve_leaves_views_without_enough_samples_at_gain_one():
    rng = np.random.default_rng(1)
    obs = rng.uniform(0.2, 0.5, (1, 200, 3)) * np.array([1.0, 1.2, 0.8, 1.5])[:, None, None]
    obs[3, 5:] = np.nan  # 5 samples
    obs[2] = 0.995  # clipped: nothing usable
    est = solve_log_gains(obs.astype(np.float32), [0, 1, 2, 3], 10, 30)
    assert list(est.samples) == [200, 200, 0, 5]
    assert np.all(est.log_gain[2:] == 0.0)
    np.testing.assert_allclose(est.log_gain[1] - est.log_gain[0], np.log(1.2), atol=0.02)
    assert np.isfinite(est.log_gain).all()


def _quad(x0, x1, z0, z1, y):  # a rectangle in the plane y = const, facing -y
    v = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], float)
    return v, np.array([[0, 2, 1], [0, 3, 2]])


def _view(cam: PinholeCamera, image: np.ndarray, facade=None, glass=None) -> TrainView:
    h, w = cam.height, cam.width
    return TrainView(
        "v",
        cam,
        image.astype(np.float32),
        np.ones((h, w), bool) if facade is None else facade,
        np.zeros((h, w), bool) if glass is None else glass,
        np.zeros((h, w, 3), np.float32),
        np.zeros((h, w), bool),
    )


def test_observe_skips_occluded_points_and_masked_pixels():
    """A wall 10 m in front of the camera with a smaller plate 1 m in front of it: wall points behind the
    plate are not seen; points landing on glass pixels (or near them) do not count."""
    wall_v, wall_f = _quad(-5, 5, -5, 5, 10.0)
    plate_v, plate_f = _quad(-1, 1, -1, 1, 9.0)
    verts = np.vstack([wall_v, plate_v])
    tris = np.vstack([wall_f, plate_f + 4])
    K = intrinsics(40.0, 40.0, 32.0, 32.0)
    cam = PinholeCamera(K, look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])), 64, 64)
    img = np.full((64, 64, 3), 0.5)
    glass = np.zeros((64, 64), bool)
    glass[:, :16] = True  # the left strip is glass
    caster = MeshRaycaster(verts, tris)
    points = np.array([[0.0, 10.0, 0.0], [3.0, 10.0, 3.0], [0.0, 9.0, 0.5], [-4.9, 10.0, 0.0]])
    obs = observe([_view(cam, img, glass=glass)], points, caster, PARAMS)
    seen = np.isfinite(obs[0, :, 0])
    # behind the plate; in front of the wall; on the plate; on the glass strip
    assert list(seen) == [False, True, True, False]


def test_usable_mask_keeps_pixels_away_from_glass_and_the_facade_edge():
    facade = np.zeros((10, 10), bool)
    facade[1:9, 1:9] = True
    glass = np.zeros((10, 10), bool)
    glass[:, 5:] = True
    cam = PinholeCamera(intrinsics(10.0, 10.0, 5.0, 5.0), np.eye(4), 10, 10)
    m = usable_mask(_view(cam, np.zeros((10, 10, 3)), facade, glass), 1)
    assert m[2:8, 2:4].all() and m.sum() == 12


@pytest.mark.slow
def test_estimate_finds_gains_put_into_synthetic64s_photos(data64):
    """Each training photo of synthetic64 scaled by a known factor (0.7-1.3): the estimated gains move by
    those factors (relative to their mean) to within 0.02 in log, whatever synthetic64's own exposures."""
    rng = np.random.default_rng(3)
    k = rng.uniform(np.log(0.7), np.log(1.3), len(data64.views))
    scaled = tuple(
        dataclasses.replace(v, image=np.clip(v.image * np.exp(k[i]), 0, 1).astype(np.float32))
        for i, v in enumerate(data64.views)
    )
    init, ref = data64.init, list(data64.train_idx)
    params = dataclasses.replace(PARAMS, samples=40000, min_samples=10)  # small photos: thin frames
    args = (init.mesh_vertices, init.mesh_triangles, init.mesh_glass, ref, params, 0)
    before = estimate_exposures(data64.views, *args)
    after = estimate_exposures(scaled, *args)
    assert (before.samples[ref] >= 10).all() and (after.samples[ref] >= 10).all()
    moved = (after.log_gain - before.log_gain).mean(axis=1)
    np.testing.assert_allclose(moved[ref], k[ref] - k[ref].mean(), atol=0.02)
