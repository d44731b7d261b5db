"""Hand-made hard scenes for the stability tests: a 4 m x 3 m facade in the plane y = 0 facing +y, seen
frontally, at a grazing angle and from behind, with pixels that no splat covers."""

from __future__ import annotations

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.training.data import InitGeometry, TrainData, TrainView


def _view(stem: str, eye, size: int = 24, seed: int = 0) -> TrainView:
    K = intrinsics(size * 1.2, size * 1.2, size / 2, size / 2)
    cam = PinholeCamera(K, look_at(np.array(eye, float), np.array([0.0, 0.0, 1.5])), size, size)
    rng = np.random.default_rng(seed)
    mask = np.zeros((size, size), bool)
    mask[:, : size * 3 // 4] = True  # a quarter of the image outside the facade
    prior = np.zeros((size, size, 3), np.float32)
    prior[..., 1] = 1.0
    return TrainView(
        stem, cam, rng.random((size, size, 3)).astype(np.float32), mask, mask.copy(), prior, mask.copy()
    )


def hard_scene() -> TrainData:
    views = (
        _view("test_frontal", [0.5, 8.0, 2.0], seed=1),  # index 0: held out
        _view("frontal", [0.0, 7.0, 1.5], seed=2),
        _view("grazing", [9.0, 0.25, 1.5], seed=3),  # 88 deg from the facade normal
        _view("behind", [0.3, -6.0, 1.6], seed=4),  # normals face away from this camera
        _view("sky", [0.0, 6.0, 12.0], seed=5),  # looks down: many pixels with no splat
    )
    rng = np.random.default_rng(0)
    pts = np.stack([rng.uniform(-2, 2, 300), rng.normal(0, 0.02, 300), rng.uniform(0, 3, 300)], 1)
    v = np.array([[-2, 0, 0], [2, 0, 0], [2, 0, 3], [-2, 0, 3]], float)
    init = InitGeometry(pts, rng.random((300, 3)), v, np.array([[0, 1, 2], [0, 2, 3]]))
    return TrainData(views, (1, 2, 3, 4), (0,), init)
