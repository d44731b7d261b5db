"""The training data bundle (one .npz with everything training needs) round-trips exactly, and trains
where the I/O stack cannot be imported."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

from facade_pipeline.training.data import ExposureEstimate, load_bundle, save_bundle
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
        for name in ("image", "facade_mask", "glass_mask", "normal_prior", "normal_valid"):
            x, y = getattr(a, name), getattr(b, name)
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
print(json.dumps({{"log": tr.log, "gains": exposure_gains(tr)}}))
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
