"""The training data bundle (one .npz with everything training needs) round-trips exactly, and trains
where the I/O stack cannot be imported; views reduced to a pixel budget; the lengths training derives from
the scene scale with it."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.shading.reflection import EnvironmentProxy, ReflectionMLP, build_reflection_module
from facade_pipeline.training.data import (
    ExposureEstimate,
    InitGeometry,
    TrainData,
    TrainView,
    downscale_view,
    load_bundle,
    pixel_budget_factor,
    save_bundle,
)
from facade_pipeline.training.params import INIT_BOUNDS_MARGIN, facade_size, near_plane
from tests.training.scenes import hard_scene

REPO = Path(__file__).resolve().parents[2]
RNG_GAINS = np.random.default_rng(0).normal(0, 0.1, (5, 3)).astype(np.float32)


def test_bundle_round_trip_is_exact(tmp_path):
    data = hard_scene()
    path = tmp_path / "data.npz"
    save_bundle(data, path)
    back = load_bundle(path)
    assert (back.train_idx, back.test_idx) == (data.train_idx, data.test_idx)
    assert len(back.views) == len(data.views)
    for a, b in zip(data.views, back.views, strict=True):
        assert a.stem == b.stem
        assert (a.camera.width, a.camera.height) == (b.camera.width, b.camera.height)
        assert np.array_equal(a.camera.K, b.camera.K)
        assert np.array_equal(a.camera.cam_from_world, b.camera.cam_from_world)
        for name in ("image", "facade_mask", "glass_mask", "normal_prior", "normal_valid", "clipped"):
            x, y = getattr(a, name), getattr(b, name)
            if x is None:
                assert y is None
                continue
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    for name in ("points", "colors", "mesh_vertices", "mesh_triangles"):
        assert np.array_equal(getattr(data.init, name), getattr(back.init, name)), name
    assert back.extent == data.extent
    assert not list(tmp_path.glob(".*")), "no temporary file left beside the bundle"


def test_bundle_carries_the_exposure_estimate(tmp_path):
    data = dataclasses.replace(hard_scene(), exposure=ExposureEstimate(RNG_GAINS, np.arange(5)))
    save_bundle(data, tmp_path / "data.npz")
    back = load_bundle(tmp_path / "data.npz").exposure
    assert np.array_equal(back.log_gain, RNG_GAINS) and np.array_equal(back.samples, np.arange(5))
    save_bundle(hard_scene(), tmp_path / "none.npz")
    assert load_bundle(tmp_path / "none.npz").exposure is None


#: What training from a bundle may not import: the I/O stack, which a GPU machine need not have.
IO_STACK = ("open3d", "pycolmap", "OpenEXR", "cv2", "pymeshlab")

_BLOCKED_RUN = """
import json, sys
for name in {blocked!r}:
    sys.modules[name] = None  # an import of it raises ImportError
from facade_pipeline.training.batches import exposure_gains
from facade_pipeline.training.data import load_bundle
from facade_pipeline.training.render import splatting_rasterizer
from facade_pipeline.training.trainer import build_trainer, train
from tests.training.conftest import small_params

p = small_params(iterations=3, proxy_channels=2, exposure_estimate=True)
tr = train(build_trainer(p, load_bundle({bundle!r}), splatting_rasterizer("auto")), log_every=1)
print(json.dumps({{"log": tr.state.log, "gains": exposure_gains(tr.gains, tr.data)}}))
"""


def test_training_from_a_bundle_needs_torch_alone(data64, tmp_path):
    """A bundle (with the exposure estimate the I/O stack made) trains a few steps, the environment proxy's
    surroundings included, in a process where the I/O stack cannot be imported (a process of its own, so
    that the block does not reach the other tests); the estimate's gains are the ones trained with."""
    gains = np.linspace(-0.2, 0.2, 3 * len(data64.views), dtype=np.float32).reshape(-1, 3)
    est = ExposureEstimate(gains, np.full(len(data64.views), 100))
    save_bundle(dataclasses.replace(data64, exposure=est), tmp_path / "data.npz")
    code = _BLOCKED_RUN.format(blocked=IO_STACK, bundle=str(tmp_path / "data.npz"))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert [rec["iteration"] for rec in out["log"]] == [1, 2, 3]
    assert all(math.isfinite(rec["loss"]) for rec in out["log"])
    for i in data64.train_idx:
        # the estimate as it was made: training applies it as it is
        np.testing.assert_allclose(out["gains"][data64.views[i].stem], np.exp(gains[i]), rtol=1e-5)


def test_pixel_budget_factor_is_the_smallest_that_fits():
    assert pixel_budget_factor(768, 1024, 0) == 1
    assert pixel_budget_factor(256, 192, 49152) == 1
    assert pixel_budget_factor(768, 1024, 49152) == 4  # 192 x 256
    assert pixel_budget_factor(768, 1024, 49151) == 5
    for w, h, budget in ((768, 1024, 10000), (101, 37, 500), (640, 480, 1)):
        f = pixel_budget_factor(w, h, budget)
        assert (w // f) * (h // f) <= budget or f == min(w, h)
        assert f == 1 or (w // (f - 1)) * (h // (f - 1)) > budget


def test_a_downscaled_view_sees_the_world_as_its_blocks_do():
    """A point's pixel in the scaled camera is its pixel in the photo divided by f, and each pixel of the
    downscaled view is the mean of its f x f photo pixels (masks: of the majority; clipping: of any)."""
    view = hard_scene().views[0]
    rng = np.random.default_rng(0)
    h, w = view.image.shape[:2]
    clipped = rng.random((h, w, 3)) > 0.97
    view = TrainView(view.stem, view.camera, view.image, view.facade_mask, view.glass_mask,
                     view.normal_prior, view.normal_valid, clipped)  # fmt: skip
    f = 3
    small = downscale_view(view, f)
    cam, sc = view.camera, small.camera
    assert (sc.width, sc.height) == (cam.width // f, cam.height // f)
    pts = cam.pixel_rays(np.array([3.2, 17.0]), np.array([5.5, 9.9]))
    world = pts[0] + 4.0 * pts[1]
    uv, _ = cam.project(world)
    uv_small, _ = sc.project(world)
    assert np.allclose(uv_small, uv / f)
    for y, x in ((0, 0), (2, 5), (sc.height - 1, sc.width - 1)):
        block = (slice(y * f, y * f + f), slice(x * f, x * f + f))
        assert np.allclose(small.image[y, x], view.image[block].reshape(-1, 3).mean(0), atol=1e-6)
        assert small.facade_mask[y, x] == (view.facade_mask[block].mean() >= 0.5)
        assert np.array_equal(small.clipped[y, x], view.clipped[block].reshape(-1, 3).any(0))
    n = np.linalg.norm(small.normal_prior[small.normal_valid], axis=-1)
    assert np.allclose(n, 1.0, atol=1e-5)


def test_the_extent_scales_with_the_scene():
    """Every length training derives from the scene (extent, near plane, the splats' bounds margin, the
    proxy's surface model of the surroundings) scales with it: the same scene at 1:25 has lengths 25 times
    smaller."""
    data = hard_scene()
    s = 1.0 / 25.0
    small = scaled_scene(data, s)
    assert np.isclose(small.extent, s * data.extent)
    assert np.isclose(near_plane(small.bounds), s * near_plane(data.bounds))
    assert np.isclose(facade_size(small.bounds), s * facade_size(data.bounds))
    # the reflection proxy's surface model of the surroundings: its cells and heights, 25 times smaller
    lo, hi = data.bounds
    size = facade_size(data.bounds)
    g = np.random.default_rng(0).uniform([0.5, -0.1, 0.05], [0.7, 0.1, 0.3], (500, 3))
    block = 0.5 * (lo + hi) * [1, 1, 0] + [0, 0, lo[2]] + size * g  # a building in front of the facade
    models = []
    for d, k in ((data, 1.0), (small, s)):
        b = d.bounds
        proxy = EnvironmentProxy(channels=1, resolution_px=16, levels=1)
        margin = INIT_BOUNDS_MARGIN * facade_size(b)
        cfg = ReflectionMLP(fourier_levels=2, depth=2, width=4, proxy=proxy, proxy_margin_m=margin)
        bt = tuple(torch.as_tensor(x, dtype=torch.float32) for x in b)
        models.append(build_reflection_module(cfg, "cpu", bt, block * k).proxy.surroundings)
    big, tiny = models
    assert np.isclose(tiny.cell_m, s * big.cell_m) and np.isclose(big.cell_m, size / 60.0)
    assert big.heights[1].max() > 0.2 * size  # the building is in the surface model
    assert torch.allclose(tiny.heights, s * big.heights, rtol=1e-4, atol=1e-6 * size)


def scaled_scene(data: TrainData, s: float) -> TrainData:
    """``data`` with every length multiplied by ``s`` (the world frame's origin fixed)."""
    views = []
    for v in data.views:
        T = np.array(v.camera.cam_from_world, float)
        T[:3, 3] *= s
        cam = PinholeCamera(v.camera.K, T, v.camera.width, v.camera.height)
        views.append(TrainView(v.stem, cam, v.image, v.facade_mask, v.glass_mask, v.normal_prior,
                               v.normal_valid, v.clipped))  # fmt: skip
    i = data.init
    init = InitGeometry(i.points * s, i.colors, i.mesh_vertices * s, i.mesh_triangles, i.mesh_glass)
    return TrainData(tuple(views), data.train_idx, data.test_idx, init)
