"""The environment proxy of the reflection MLP: where reflected rays land, its feature maps, hard cases."""

from __future__ import annotations

import math

import pytest
import torch

from facade_pipeline.shading.proxy import ProxyFeatures, ProxyGeometry
from facade_pipeline.shading.reflection import ReflectionMLP, ReflectionMLPModule, build_reflection_module

LO = torch.tensor([-10.0, -2.0, 0.0])
HI = torch.tensor([10.0, 2.0, 18.0])


def _geom(radius: float = 40.0) -> ProxyGeometry:
    return ProxyGeometry.around(LO, HI, radius)


def test_room_around_the_facade_bounds():
    g = ProxyGeometry.around(LO, HI)
    assert g.centre_xy == (0.0, 0.0) and g.ground_z == 0.0
    assert g.radius == pytest.approx(2.0 * math.hypot(10.0, 2.0))  # default: twice the half-diagonal
    with pytest.raises(ValueError, match="half-diagonal"):
        ProxyGeometry.around(LO, HI, 5.0)  # the facade would stick out of the room


def test_hits_against_hand_computed_points():
    g = _geom(40.0)
    x = torch.tensor(
        [[3.0, 1.0, 10.0], [0.0, 0.0, 10.0], [0.0, 0.0, 10.0], [0.0, 0.0, 10.0]], dtype=torch.float64
    )
    s = 1.0 / math.sqrt(2.0)
    w = torch.tensor([[0.0, 0.0, -1.0], [0.0, s, -s], [1.0, 0.0, 0.0], [0.0, s, s]], dtype=torch.float64)
    on_floor, floor_uv, wall_uv = g.hit(x, w)
    assert on_floor.tolist() == [True, True, False, False]
    # straight down from (3, 1, 10): the floor at (3, 1); 45 deg down along +y from 10 m: the floor at y = 10
    assert torch.allclose(floor_uv[0], torch.tensor([3.0, 1.0], dtype=torch.float64) / 40.0)
    assert torch.allclose(floor_uv[1], torch.tensor([0.0, 10.0], dtype=torch.float64) / 40.0)
    # horizontal along +x: the wall at azimuth 0, at 10 m up seen from the rim 40 m away
    elev = math.atan2(10.0, 40.0)
    assert torch.allclose(wall_uv[2], torch.tensor([0.0, 4 * elev / math.pi - 1], dtype=torch.float64))
    # 45 deg up along +y: the wall at azimuth pi/2, at 10 + 40 m up
    elev = math.atan2(50.0, 40.0)
    assert torch.allclose(wall_uv[3], torch.tensor([0.5, 4 * elev / math.pi - 1], dtype=torch.float64))


def test_rays_meeting_on_the_ground_read_the_same_texels():
    """The point of the proxy: two views mirrored off different facade points onto the same patch of ground
    get the same features, whatever their directions (parallax is right for what lies on the proxy)."""
    torch.manual_seed(0)
    feats = ProxyFeatures(_geom(40.0), channels=4, resolution=64, levels=2, init_std=1.0).double()
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
        [0.0, 0.0, 1.0],  # straight up: no wall hit at finite distance
        [0.0, 0.0, -1.0],  # straight down
        [1.0, 0.0, 0.0],  # horizontal: never meets the floor
        [0.0, 0.0, 0.0],  # no direction at all (a pixel with no surface)
        [1e-9, 0.0, -1.0],
        [1.0, 0.0, -1e-9],
    ],
)
def test_hard_rays_are_finite_in_value_and_gradient(w):
    feats = ProxyFeatures(_geom(40.0), channels=3, resolution=32, levels=2, init_std=1.0).double()
    x = torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 18.0], [9.9, 1.9, 5.0]], dtype=torch.float64)
    x.requires_grad_()
    wt = torch.tensor([w] * 3, dtype=torch.float64, requires_grad=True)
    out = feats(x, wt)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(x.grad).all() and torch.isfinite(wt.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in feats.parameters())


def test_gradients_match_finite_differences_away_from_edges():
    feats = ProxyFeatures(_geom(40.0), channels=2, resolution=16, levels=1, init_std=1.0).double()
    x = torch.tensor([[2.0, 0.5, 7.0], [-3.0, 1.0, 12.0]], dtype=torch.float64, requires_grad=True)
    w = torch.nn.functional.normalize(
        torch.tensor([[0.3, 0.8, -0.5], [-0.2, 0.7, 0.4]], dtype=torch.float64), dim=-1
    ).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: feats(a, b), (x, w))


def test_mlp_with_proxy_features_shapes_state_and_bounds():
    cfg = ReflectionMLP(
        fourier_levels=4, depth=4, width=16, proxy_channels=5, proxy_resolution_px=64, proxy_levels=2
    )
    with pytest.raises(ValueError, match="bounds"):
        ReflectionMLPModule(cfg)
    m = build_reflection_module(cfg, "cpu", (LO, HI))
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
