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
