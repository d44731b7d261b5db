"""benchmarks/bench_view_prediction.py: a photo warped through the plane at the depth of what it shows
reproduces another view of it; at another depth it does not."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from facade_pipeline.evaluation.metrics import psnr
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.training.data import InitGeometry, TrainData, TrainView

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
W, H, F = 64, 48, 60.0


@pytest.fixture(scope="module")
def bench():
    import sys

    sys.path.insert(0, str(BENCH))
    try:
        path = BENCH / "bench_view_prediction.py"
        spec = importlib.util.spec_from_file_location("bench_view_prediction", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCH))
    return module


def camera(x: float, y: float) -> PinholeCamera:
    """Looking along +z from (x, y, -0.3): the glass (z = 0) 0.3 m ahead."""
    T = np.eye(4)
    T[:3, 3] = [-x, -y, 0.3]
    return PinholeCamera(np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]]), T, W, H)


def texture(p: np.ndarray) -> np.ndarray:  # [N, 2] on the plane (m) -> [N, 3] in [0, 1]
    u, v = p[:, 0], p[:, 1]
    rgb = [0.5 + 0.3 * np.sin(40 * u), 0.5 + 0.3 * np.cos(30 * v), 0.5 + 0.2 * np.sin(25 * (u + v))]
    return np.stack(rgb, 1)


def photo(cam: PinholeCamera, depth: float) -> np.ndarray:
    """What ``cam`` sees of the texture on the plane z = depth (inf: painted on the directions)."""
    ys, xs = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    o, d = cam.pixel_rays(xs, ys)
    p = d[:, :2] / d[:, 2:] if math.isinf(depth) else o[:, :2] + (depth - o[:, 2:]) / d[:, 2:] * d[:, :2]
    return texture(p).reshape(H, W, 3).astype(np.float32)


def scene(depth: float) -> TrainData:
    views = []
    for i, (x, y) in enumerate(((0.0, 0.0), (0.03, 0.01))):
        cam = camera(x, y)
        full = np.ones((H, W), bool)
        normals = np.broadcast_to(np.array([0, 0, -1.0], np.float32), (H, W, 3)).copy()
        views.append(TrainView(f"v{i}", cam, photo(cam, depth), full, full, normals, full))
    verts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    init = InitGeometry(np.zeros((0, 3)), np.zeros((0, 3)), verts, tris, np.ones(2, bool))
    return TrainData(tuple(views), (1,), (0,), init)


@pytest.mark.parametrize("depth", [0.0, 0.05, math.inf])
def test_a_photo_warped_at_the_depth_it_shows_is_the_other_view(bench, depth):
    data = scene(depth)
    plane = bench.glass_plane(data)
    assert np.allclose(plane[0], [0, 0, 1]) and abs(plane[1]) < 1e-12
    target = data.views[0]
    K = torch.as_tensor(target.camera.K, dtype=bench.DTYPE)
    T = torch.as_tensor(target.camera.cam_from_world, dtype=bench.DTYPE)
    scores = {}
    for d in (0.0, 0.05, math.inf):
        rgb, ok = bench.Warp(data, 1, plane, d)(K, T, (H, W))
        # the source's border is not the target's: compare where the source sees the pixel
        scores[d] = psnr(rgb.numpy(), target.image, ok.numpy())
    assert scores[depth] > 35.0, scores
    assert all(scores[depth] > s + 8.0 for d, s in scores.items() if d != depth), scores


def test_two_layers_take_the_glass_from_the_far_one(bench):
    data = scene(0.05)
    plane = bench.glass_plane(data)
    glass = np.zeros((H, W), bool)
    glass[:, : W // 2] = True
    target = data.views[0]
    K = torch.as_tensor(target.camera.K, dtype=bench.DTYPE)
    T = torch.as_tensor(target.camera.cam_from_world, dtype=bench.DTYPE)
    two = bench.predictor(data, [1], plane, (0.0, 0.05), glass)(K, T, (H, W))
    near = bench.predictor(data, [1], plane, 0.0, glass)(K, T, (H, W))
    far = bench.predictor(data, [1], plane, 0.05, glass)(K, T, (H, W))
    assert torch.equal(two[glass], far[glass]) and torch.equal(two[~glass], near[~glass])


#: the scene the panes mirror: a plane this far in front of the glass (behind the cameras)
MIRRORED_AT = 1.0
#: the true tilts (deg) of the two panes (x < 0, x > 0) from the glass plane z = 0
TILTS = np.array([[0.0, 0.0], [2.0, -1.5]])


def mirrored_photo(cam: PinholeCamera, panes) -> np.ndarray:
    """What ``cam`` sees of the texture on the plane z = -MIRRORED_AT in the two panes tilted by TILTS."""
    ys, xs = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    o, d = cam.pixel_rays(xs, ys)
    k = np.where(o[:, 0] - o[:, 2] / d[:, 2] * d[:, 0] < 0, 0, 1)  # the pane the ray meets at z = 0
    n = panes.normals(TILTS).numpy().astype(np.float64)[k]
    centre = panes.centre.numpy().astype(np.float64)[k]
    x = o + (((centre - o) * n).sum(1) / (d * n).sum(1))[:, None] * d
    r = d - 2 * (d * n).sum(1, keepdims=True) * n
    s = x + ((-MIRRORED_AT - x[:, 2]) / r[:, 2])[:, None] * r
    return texture(s[:, :2]).reshape(H, W, 3).astype(np.float32)


def mirror_scene(bench) -> TrainData:
    """Two views of two panes side by side (their own vertices: two panes), mirroring the textured plane."""
    verts = np.array(
        [[-1, -1, 0], [0, -1, 0], [0, 1, 0], [-1, 1, 0], [0, -1, 0], [1, -1, 0], [1, 1, 0], [0, 1, 0.0]]
    )
    tris = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    init = InitGeometry(np.zeros((0, 3)), np.zeros((0, 3)), verts, tris, np.ones(4, bool))
    full = np.ones((H, W), bool)
    normals = np.broadcast_to(np.array([0, 0, -1.0], np.float32), (H, W, 3)).copy()
    blank = TrainData(
        tuple(TrainView(f"v{i}", camera(0, 0), normals, full, full, normals, full) for i in range(2)),
        (0, 1),
        (),
        init,
    )
    panes = bench.Panes(blank, bench.glass_plane(blank))
    views = []
    for i, (x, y) in enumerate(((0.0, 0.0), (0.03, 0.01))):
        cam = camera(x, y)
        views.append(TrainView(f"v{i}", cam, mirrored_photo(cam, panes), full, full, normals, full))
    return TrainData(tuple(views), (0, 1), (), init)


def test_a_photo_mirrored_in_each_pane_at_its_tilt_is_the_other_view(bench):
    data = mirror_scene(bench)
    plane = bench.glass_plane(data)
    panes = bench.Panes(data, plane)
    assert panes.count == 2 and np.allclose(panes.own_tilt, 0, atol=1e-9)
    target = data.views[0]
    K = torch.as_tensor(target.camera.K, dtype=bench.DTYPE)
    T = torch.as_tensor(target.camera.cam_from_world, dtype=bench.DTYPE)
    warp = bench.MirrorWarp(data, 1, panes, plane, MIRRORED_AT)
    scores = {}
    for name, tilt in (("true", TILTS), ("one plane", np.zeros_like(TILTS))):
        rgb, ok = warp(panes.normals(tilt), K, T, (H, W))
        # where the source sees the scene point
        scores[name] = psnr(rgb.numpy(), target.image, ok.numpy())
    assert scores["true"] > 30.0 and scores["true"] > scores["one plane"] + 8.0, scores


def test_the_tilts_fitted_on_the_training_views_are_the_panes(bench):
    data = mirror_scene(bench)
    plane = bench.glass_plane(data)
    panes = bench.Panes(data, plane)
    tilt, untilted, fitted = bench.fit_tilts(data, panes, plane, MIRRORED_AT, log=lambda *_, **__: None)
    # a tilt common to both panes barely changes two nearby views' images (only the mirrored scene's depth):
    # what the views decide is the panes' tilt against each other, to the fine grid's step
    assert np.abs((tilt[1] - tilt[0]) - (TILTS[1] - TILTS[0])).max() <= 0.25, tilt
    assert fitted > untilted + 4.0, (untilted, fitted)
