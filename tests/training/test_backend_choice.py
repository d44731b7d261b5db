"""Which rasterizer a training run renders with: every shipped building trains through gsplat on CUDA,
and "auto" never trains with the torch backend on CUDA where gsplat is installed (the choice is pure, so
these run without CUDA)."""

from __future__ import annotations

import pytest
import torch

from facade_pipeline.config import available_buildings, load_building_config
from facade_pipeline.errors import ConfigError
from facade_pipeline.training.params import TrainParams
from facade_pipeline.training.render import training_backend, training_rasterizer


@pytest.mark.parametrize("budget", ["cpu", "gpu"])
@pytest.mark.parametrize("building", available_buildings())
def test_every_shipped_building_trains_through_gsplat_on_cuda(building, budget, monkeypatch):
    monkeypatch.setenv("FACADE_BUDGET", budget)
    cfg = load_building_config(building)
    p = cfg.section("train_gs", TrainParams)
    chosen = training_backend(cfg.run.raster_backend, "cuda", p.lowpass_sigma_px, gsplat_installed=True)
    assert chosen == "gsplat"


def test_auto_refuses_a_low_pass_gsplat_lacks_on_cuda():
    """A sigma gsplat does not have is one line naming the key under "auto" on CUDA, not a silent switch to
    the torch backend; asked for by name, or on the CPU, or without gsplat, the choice is the one asked."""
    with pytest.raises(ConfigError, match=r"train_gs\.lowpass_sigma_px = 0\.7071 .* found 0\.5: set 0\.7071"):
        training_backend("auto", "cuda", 0.5, gsplat_installed=True)
    assert training_backend("auto", "cuda", 0.7071, gsplat_installed=True) == "gsplat"
    assert training_backend("torch", "cuda", 0.5, gsplat_installed=True) == "torch"
    assert training_backend("gsplat", "cuda", 0.7071, gsplat_installed=True) == "gsplat"
    assert training_backend("auto", "cpu", 0.5, gsplat_installed=True) == "auto"
    assert training_backend("auto", "cuda", 0.5, gsplat_installed=False) == "auto"


def test_training_rasterizer_refuses_on_a_cuda_device(monkeypatch):
    """train_gs, bench_train and accuracy_vs_time build their rasterizer through ``training_rasterizer``,
    which asks ``training_backend`` with the device's type (no CUDA tensor is made to ask)."""
    from facade_pipeline.splatting import gsplat_backend

    monkeypatch.setattr(gsplat_backend, "available", lambda: True)
    with pytest.raises(ConfigError, match="lowpass_sigma_px"):
        training_rasterizer("auto", 0.5, torch.device("cuda"))
    assert callable(training_rasterizer("auto", 0.5, torch.device("cpu")))
