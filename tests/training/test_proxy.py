"""The environment proxy of the reflection MLP: its reach, its feature maps read where reflected rays meet
the surroundings, hard cases, and the MLP built with it."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from facade_pipeline.shading.proxy import REACH_FACTOR, ProxyFeatures, proxy_reach_m
from facade_pipeline.shading.reflection import (
    EnvironmentProxy,
    ReflectionMLP,
    ReflectionMLPModule,
    build_reflection_module,
)
from facade_pipeline.shading.surroundings import Surroundings

pytest.importorskip("open3d")

LO = torch.tensor([-10.0, -2.0, 0.0])
HI = torch.tensor([10.0, 2.0, 18.0])


def _features(channels: int, resolution: int, levels: int) -> ProxyFeatures:
    """Feature maps over bare ground (no points: nothing stands around the facade)."""
    ground = Surroundings(LO, HI, reach_m=proxy_reach_m(LO, HI), cell_m=1.0)
    return ProxyFeatures(ground, channels, resolution, levels, init_std=1.0).double()


def test_reach_is_derived_from_the_facade_bounds():
    assert proxy_reach_m(LO, HI) == pytest.approx(REACH_FACTOR * math.hypot(10.0, 2.0))


def test_rays_meeting_on_the_ground_read_the_same_texels():
    """The point of the proxy: two views mirrored off different facade points onto the same patch of ground
    get the same features, whatever their directions (parallax is right for what lies on the proxy)."""
    torch.manual_seed(0)
    feats = _features(channels=4, resolution=64, levels=2)
    target = torch.tensor([5.0, 12.0, 0.0], dtype=torch.float64)
    x = torch.tensor([[-8.0, 0.5, 3.0], [6.0, -1.0, 15.0], [0.0, 2.0, 9.0]], dtype=torch.float64)
    w = torch.nn.functional.normalize(target - x, dim=-1)
    out = feats(x, w)
    assert torch.allclose(out[0], out[1]) and torch.allclose(out[0], out[2])
    assert out[:, -1].tolist() == [1.0, 1.0, 1.0]  # the floor flag
    assert torch.count_nonzero(out[:, 4:8]) == 0  # no wall features on a floor hit
    # a different spot of ground reads different features
    w2 = torch.nn.functional.normalize(
        target + torch.tensor([6.0, 0.0, 0.0], dtype=torch.float64) - x[:1], dim=-1
    )
    assert not torch.allclose(feats(x[:1], w2), out[:1])


@pytest.mark.parametrize(
    "w",
    [
        [0.0, 0.0, 1.0],  # straight up: the sky
        [0.0, 0.0, -1.0],  # straight down
        [1.0, 0.0, 0.0],  # horizontal: never meets the floor
        [0.0, 0.0, 0.0],  # no direction at all (a pixel with no surface)
        [1e-9, 0.0, -1.0],
        [1.0, 0.0, -1e-9],
    ],
)
def test_hard_rays_are_finite_in_value_and_gradient(w):
    feats = _features(channels=3, resolution=32, levels=2)
    x = torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 18.0], [9.9, 1.9, 5.0]], dtype=torch.float64)
    wt = torch.tensor([w] * 3, dtype=torch.float64)
    out = feats(x, wt)
    out.sum().backward()
    assert torch.isfinite(out).all()
    assert all(torch.isfinite(p.grad).all() for p in feats.parameters())


def test_mlp_with_proxy_features_shapes_state_and_bounds():
    proxy = EnvironmentProxy(channels=5, resolution_px=64, levels=2)
    cfg = ReflectionMLP(fourier_levels=4, depth=4, width=16, proxy=proxy)
    with pytest.raises(ValueError, match="bounds"):
        ReflectionMLPModule(cfg)
    m = build_reflection_module(cfg, "cpu", (LO, HI), points=np.zeros((0, 3)))
    assert m.second[0].in_features == 16 + 24 + 24 + 11  # h, gamma(w), gamma(x), 2 x 5 features + flag
    x = torch.rand(32, 3) * 2 - 1
    w = torch.nn.functional.normalize(torch.randn(32, 3), dim=-1)
    out = m(x, w)
    assert out.shape == (32, 3) and torch.all((out > 0) & (out < 1))
    # the bounds are rebuilt from the saved config, not stored: a state dict loads into a fresh module
    state = m.state_dict()
    assert not any("bounds" in k for k in state)
    m2 = build_reflection_module(cfg, "cpu", (LO, HI))
    m2.load_state_dict(state)
    assert torch.equal(m2(x, w), out)
    # the paper's network has no proxy parameters at all
    paper = ReflectionMLPModule(ReflectionMLP(fourier_levels=4, depth=4, width=16))
    assert paper.proxy is None and not any(k.startswith("proxy") for k in paper.state_dict())


def test_a_saved_record_of_either_form_rebuilds_its_strategy(tmp_path):
    """``reflection.pt`` records keep their own form: the present one (the proxy as a table), the flat one of
    models saved before it, and an error naming the field for one trained with an option no longer offered."""
    from facade_pipeline.errors import InputError
    from facade_pipeline.shading.reflection import EnvMap, reflection_record, strategy_from_record

    proxy = EnvironmentProxy(channels=5, resolution_px=64, levels=2, cell=0.03)
    cfg = ReflectionMLP(fourier_levels=4, depth=4, width=16, proxy=proxy, proxy_margin_m=0.5)
    record = reflection_record(cfg, (LO.tolist(), HI.tolist()), None)
    assert strategy_from_record(record["model"], record["config"]) == cfg
    flat = {"fourier_levels": 4, "depth": 4, "width": 16, "skip": True, "proxy_channels": 5,
            "proxy_resolution_px": 64, "proxy_levels": 2, "proxy_radius_m": 0.0, "proxy_surroundings": True,
            "proxy_reach_m": 0.0, "proxy_margin_m": 0.5, "self_hits": False,
            "self_hit_offset_m": 0.02, "self_hit_max_m": 0.0}  # fmt: skip
    assert strategy_from_record("mlp", flat) == replace(cfg, proxy=replace(proxy, cell=1.0 / 60.0))
    # without proxy features the room's fields (and the cell of the surroundings) never mattered
    paper = {**flat, "proxy_channels": 0, "proxy_surroundings": False, "proxy_cell_m": 2.0}
    assert strategy_from_record("mlp", paper).proxy.channels == 0
    with pytest.raises(InputError, match="cell_m = 2.0, a cell in metres: retrain"):
        strategy_from_record("mlp", {**flat, "proxy_cell_m": 2.0}, tmp_path / "reflection.pt")
    assert strategy_from_record("envmap", {"height_px": 8, "width_px": 16}) == EnvMap(8, 16)
    path = tmp_path / "reflection.pt"
    for field, value in (("self_hits", True), ("proxy_surroundings", False), ("proxy_reach_m", 40.0)):
        with pytest.raises(InputError) as e:
            strategy_from_record("mlp", {**flat, field: value}, path)
        assert field in str(e.value) and "retrain" in str(e.value) and str(path) in str(e.value)
    with pytest.raises(InputError, match="'sh', 'envmap' or 'mlp'"):
        strategy_from_record("room", {}, path)
