"""Deferred shading (Eq. 7-10), SH colour and the reflection models: values, shapes, hard cases, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from facade_pipeline.shading import deferred
from facade_pipeline.shading.fourier import fourier_dim, fourier_features
from facade_pipeline.shading.reflection import (
    EnvMap,
    EnvMapModule,
    ReflectionMLP,
    ReflectionMLPModule,
    SHOnly,
    build_reflection_module,
    model_name,
)
from facade_pipeline.shading.sh import eval_sh, num_sh_coeffs, rgb_to_sh_dc, sh_basis

#: tolerances by dtype (float32 products of a few terms; float64 for gradchecks)
TOL = {torch.float32: 1e-5, torch.float64: 1e-10}


def _unit(n: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1)


def test_fourier_features_values_and_shape():
    p = torch.tensor([[0.25, -0.5, 1.0]], dtype=torch.float64)
    g = fourier_features(p, 3)
    assert g.shape == (1, fourier_dim(3)) == (1, 18)
    # frequency-major: [sin(pi p), cos(pi p), sin(2 pi p), cos(2 pi p), ...]
    expected = []
    for k in range(3):
        expected += [np.sin(2**k * np.pi * p[0].numpy()), np.cos(2**k * np.pi * p[0].numpy())]
    assert np.allclose(g[0].numpy(), np.concatenate(expected), atol=TOL[torch.float64])
    with pytest.raises(ValueError):
        fourier_features(p, 0)


def test_schlick_fresnel_limits_and_clamp():
    f0 = torch.tensor([[0.04, 0.5, 1.0]])
    assert torch.allclose(deferred.schlick_fresnel(f0, torch.tensor([1.0])), f0)  # normal incidence: F0
    assert torch.allclose(deferred.schlick_fresnel(f0, torch.tensor([0.0])), torch.ones(1, 3))  # grazing: 1
    # a normal facing away (cos < 0) is clamped to grazing, never beyond 1
    w_o = torch.tensor([[0.0, 0.0, 1.0]])
    n_away = torch.tensor([[0.0, 0.6, -0.8]])
    c = deferred.cos_theta(n_away, w_o)
    assert float(c) == 0.0
    assert torch.all(deferred.schlick_fresnel(f0, c) <= 1.0)
    half = deferred.schlick_fresnel(torch.zeros(1, 3), torch.tensor([0.5]))
    assert torch.allclose(half, torch.full((1, 3), 0.5**5))


def test_reflect_is_the_mirror_about_the_normal():
    w_o, n = _unit(64, 1), _unit(64, 2)
    n = torch.where(((w_o * n).sum(-1, keepdim=True) < 0), -n, n)
    w_r = deferred.reflect(w_o, n)
    assert torch.allclose(w_r.norm(dim=-1), torch.ones(64, dtype=torch.float64))
    assert torch.allclose((w_r * n).sum(-1), (w_o * n).sum(-1))  # equal angles with n
    # w_o + w_r lies along n (same plane, mirrored)
    assert torch.allclose(
        torch.cross(w_o + w_r, n, dim=-1), torch.zeros(64, 3, dtype=torch.float64), atol=1e-12
    )
    # Eq. 9 as the paper writes it with the incident direction w_i = -w_o gives the same vector
    w_i = -w_o
    paper = w_i - 2 * (w_i * n).sum(-1, keepdim=True) * n
    assert torch.allclose(w_r, paper)


def test_zero_normal_gives_finite_values_and_gradients():
    n = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)  # pixels with alpha 0
    w_o = _unit(4, 3)
    nu = deferred.safe_normalize(n)
    w_r = deferred.reflect(w_o, nu)
    F = deferred.schlick_fresnel(torch.full((4, 3), 0.04, dtype=torch.float64), deferred.cos_theta(nu, w_o))
    assert torch.allclose(w_r, -w_o)  # no surface: the viewing ray continues
    (w_r.sum() + F.sum()).backward()
    assert torch.isfinite(n.grad).all()


def test_composite_extremes():
    D, F, R = torch.rand(5, 3), torch.rand(5, 3), torch.rand(5, 3)
    assert torch.allclose(deferred.composite(D, torch.zeros(5), F, R), D)
    assert torch.allclose(deferred.composite(D, torch.ones(5), F, R), F * R)


def test_pixel_rays_hit_the_pixel_at_the_given_depth():
    from facade_pipeline.geometry.camera import intrinsics, look_at

    K = intrinsics(50.0, 55.0, 32.0, 30.0)
    T = look_at(np.array([3.0, -10.0, 4.0]), np.array([0.0, 0.0, 3.0]))
    centre, rays = deferred.pixel_rays(torch.tensor(K), torch.tensor(T), (4, 6, 8, 5))
    X = deferred.surface_points(centre, rays, torch.full((5, 8), 7.0, dtype=torch.float64))
    pc = X.reshape(-1, 3).numpy() @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(pc[:, 2], 7.0)
    uv = (pc @ K.T)[:, :2] / pc[:, 2:]
    ys, xs = np.mgrid[6:11, 4:12] + 0.5
    assert np.allclose(uv, np.stack([xs.ravel(), ys.ravel()], 1))


def test_shading_gradcheck_float64():
    f0 = torch.rand(6, 3, dtype=torch.float64, requires_grad=True)
    n = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    w_o = _unit(6, 4)

    def f(f0, n):
        nu = deferred.safe_normalize(n)
        return deferred.schlick_fresnel(f0, deferred.cos_theta(nu, w_o)) * deferred.reflect(w_o, nu)

    assert torch.autograd.gradcheck(f, (f0, n))


def test_normalize_to_bounds_clamps():
    lo, hi = torch.tensor([0.0, -1.0, 0.0]), torch.tensor([10.0, 1.0, 5.0])
    x = torch.tensor([[5.0, 0.0, 2.5], [0.0, -1.0, 0.0], [100.0, 0.0, -7.0]])
    out = deferred.normalize_to_bounds(x, lo, hi)
    assert torch.allclose(out, torch.tensor([[0.0, 0.0, 0.0], [-1.0, -1.0, -1.0], [1.0, 0.0, -1.0]]))


def test_sh_basis_is_orthonormal_on_the_sphere():
    d = _unit(200_000, 5)
    Y = sh_basis(3, d)  # [P, 16]
    gram = (Y.T @ Y) / d.shape[0] * 4 * math.pi  # Monte Carlo integral of Y_i Y_j over the sphere
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.03)  # MC error ~ 1/sqrt(P)


def test_eval_sh_constant_colour_and_gradcheck():
    rgb = torch.tensor([[0.2, 0.5, 0.9]], dtype=torch.float64)
    coeffs = torch.zeros(1, num_sh_coeffs(3), 3, dtype=torch.float64)
    coeffs[:, 0] = rgb_to_sh_dc(rgb)
    for d in _unit(5, 6):
        assert torch.allclose(eval_sh(3, coeffs, d[None]), rgb)
    c = torch.randn(4, 16, 3, dtype=torch.float64, requires_grad=True)
    dirs = _unit(4, 7).requires_grad_()
    assert torch.autograd.gradcheck(lambda c, d: eval_sh(3, c, d), (c, dirs))
    with pytest.raises(ValueError):
        eval_sh(3, torch.zeros(1, 4, 3), _unit(1))


def test_reflection_mlp_full_size_architecture():
    """The paper's network (8 x 512, L = 12, skip): layer sizes and parameter count, on a few pixels."""
    cfg = ReflectionMLP()
    m = ReflectionMLPModule(cfg)
    enc = 6 * 12
    assert [layer.in_features for layer in m.first] == [enc, 512, 512, 512]
    assert [layer.in_features for layer in m.second] == [512 + 2 * enc, 512, 512, 512]
    n_params = sum(p.numel() for p in m.parameters())
    assert n_params == (enc * 512 + 512) + 3 * (512 * 512 + 512) + ((512 + 2 * enc) * 512 + 512) + 3 * (
        512 * 512 + 512
    ) + (512 * 3 + 3)
    x, w = torch.rand(16, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(16, 3), dim=-1)
    out = m(x, w)
    assert out.shape == (16, 3) and torch.all((out > 0) & (out < 1))
    out.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in m.parameters())


def test_reflection_mlp_variants_and_position_only_first_half():
    no_skip = ReflectionMLPModule(ReflectionMLP(fourier_levels=4, depth=6, width=32, skip=False))
    assert len(no_skip.first) == 3 and no_skip.second[0].in_features == 32 + 24
    m = ReflectionMLPModule(ReflectionMLP(fourier_levels=4, depth=4, width=16, skip=True))
    x = torch.rand(8, 3)
    w1 = torch.nn.functional.normalize(torch.randn(8, 3), dim=-1)
    w2 = torch.nn.functional.normalize(torch.randn(8, 3), dim=-1)
    # the first half sees the position alone: the middle layer's input starts with the same features for
    # two directions, then holds gamma(w_r) and (skip) gamma(X_r)
    seen = []
    hook = m.second[0].register_forward_hook(lambda mod, inp, out: seen.append(inp[0].detach()))
    m(x, w1), m(x, w2)
    hook.remove()
    assert torch.equal(seen[0][:, :16], seen[1][:, :16])
    assert torch.equal(seen[0][:, 16:40], fourier_features(w1, 4))
    assert torch.equal(seen[0][:, 40:], fourier_features(x, 4))
    assert not torch.allclose(m(x, w1), m(x, w2))  # the direction matters downstream
    with pytest.raises(ValueError):
        ReflectionMLPModule(ReflectionMLP(depth=1))


def test_envmap_lookup_by_direction_only():
    m = EnvMapModule(EnvMap(height_px=8, width_px=16))
    with torch.no_grad():
        m.logits.zero_()
        m.logits[0, 0, 0, :] = 5.0  # top row red: straight up
        m.logits[0, 2, -1, :] = 5.0  # bottom row blue: straight down
    up = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    x1, x2 = torch.zeros(2, 3), torch.ones(2, 3)
    out = m(x1, up)
    assert out[0, 0] > 0.99 and out[1, 2] > 0.99
    assert torch.equal(out, m(x2, up))  # position is ignored: an infinitely distant environment
    w = up.clone().requires_grad_()
    m(x1, w).sum().backward()
    assert torch.isfinite(w.grad).all()  # the poles are finite


def test_strategies_build_closed_set():
    assert build_reflection_module(SHOnly(), "cpu") is None
    assert isinstance(build_reflection_module(EnvMap(4, 8), "cpu"), EnvMapModule)
    assert isinstance(build_reflection_module(ReflectionMLP(2, 2, 4, True), "cpu"), ReflectionMLPModule)
    assert [model_name(m) for m in (SHOnly(), EnvMap(), ReflectionMLP())] == ["sh", "envmap", "mlp"]
