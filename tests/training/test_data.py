"""The training data bundle (one .npz with everything training needs) round-trips exactly."""

from __future__ import annotations

import numpy as np

from facade_pipeline.training.data import load_bundle, save_bundle
from tests.training.scenes import hard_scene


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
