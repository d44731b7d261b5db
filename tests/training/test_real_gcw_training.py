"""Training on real photos (shared/real/gcw_dev): the building made by scripts/make_gcw_building.py, the DAG
run through bake_normals with configs/buildings/gcw_dev.toml, then a tiny training budget. The whole-view
PSNR (training.monitor) must rise: its last check above its first and none more than 1 dB below the best
before it. The photos' clipping and the pixel budget are checked on the loaded views. Skipped where
shared/ is absent."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.training.data import CLIP_LEVEL
from facade_pipeline.training.params import replace_keys
from facade_pipeline.training.render import splatting_rasterizer
from facade_pipeline.training.trainer import build_trainer, train
from tests.conftest import GCW_SRC

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not (GCW_SRC / "cameras.json").is_file(),
                                                   reason=f"no real photos at {GCW_SRC}")]


def test_views_are_loaded_at_the_pixel_budget_with_their_clipping(gcw_train_data):
    _, p, data = gcw_train_data
    for v in data.views:
        assert v.camera.width * v.camera.height <= p.max_view_pixels
        assert v.clipped is not None and v.clipped.shape == v.image.shape
        # a block holding a clipped photo pixel is marked; a block of pure white can hold nothing else
        assert v.clipped[v.image >= CLIP_LEVEL].all()
    frac = np.mean([v.clipped.any(-1)[v.facade_mask].mean() for v in data.views])
    assert 0.1 < frac < 0.6  # the README's 21-34 % of the pixels clipped white, more after the blocks


def test_whole_view_psnr_rises_on_real_photos(gcw_train_data):
    _, p, data = gcw_train_data
    p = replace_keys(p, {"iterations": 60})
    tr = build_trainer(p, data, splatting_rasterizer("auto", p.lowpass_sigma_px))
    train(tr, log_every=10)
    vp = [r["view_psnr"] for r in tr.state.log]
    assert len(vp) == 6 and all(v is not None for v in vp)
    assert vp[-1] > vp[0] + 1.0, vp
    for k in range(1, len(vp)):
        assert vp[k] >= max(vp[:k]) - 1.0, vp
