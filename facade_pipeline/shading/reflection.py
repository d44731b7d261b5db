"""Reflection models: how the specular colour R of Eq. 7 is obtained. A strategy dataclass picks one:

- ``SHOnly``: no reflection term (vanilla 2DGS: I = D); the baseline the paper calls 2DGS.
- ``EnvMap``: R looked up in a learnable environment map by the reflection direction alone, the infinitely
  distant light of GaussianShader and Ref-Gaussian (cannot represent near-field parallax).
- ``ReflectionMLP``: the paper's network (section 3.2.2, Fig. 7): R = MLP(gamma(X_r), gamma(w_r)), optionally
  also fed features read where the reflected ray meets a proxy of the surroundings (``shading.proxy``)
  and where it meets the facade itself (``shading.self_hits``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, assert_never

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from facade_pipeline.shading.fourier import fourier_dim, fourier_features
from facade_pipeline.shading.proxy import ProxyFeatures, ProxyGeometry
from facade_pipeline.shading.self_hits import MESH_FIELDS, SELF_HIT_DIM, FacadeHits
from facade_pipeline.shading.surroundings import Surroundings

#: Standard deviation of the proxy feature maps' initial values.
PROXY_INIT_STD = 0.1


@dataclass(frozen=True)
class SHOnly:
    """No specular term: I = D."""


@dataclass(frozen=True)
class EnvMap:
    """A learnable equal-area (cylindrical) environment map, sigmoid-activated RGB."""

    height_px: int = 64
    """rows: the cosine of the polar angle (w_r.z from +1 at the top to -1 at the bottom)"""
    width_px: int = 128
    """columns: azimuth from -pi to pi"""


@dataclass(frozen=True)
class ReflectionMLP:
    """The paper's reflection MLP (Table 3 varies all four)."""

    fourier_levels: int = 12
    """L of Eq. 10, for both X_r and w_r"""
    depth: int = 8
    """hidden ReLU layers; the first depth // 2 see the encoded position alone"""
    width: int = 512
    """hidden units per layer"""
    skip: bool = True
    """re-inject gamma(X_r) at the middle layer beside gamma(w_r)"""
    proxy_channels: int = 0
    """feature channels read where the reflected ray meets the environment proxy (``shading.proxy``), given
    to the middle layer beside gamma(w_r); 0: none, the paper's network"""
    proxy_resolution_px: int = 512
    """texels across the proxy's finest floor map (and around its finest wall map)"""
    proxy_levels: int = 3
    """proxy feature maps per part, each a quarter of the resolution of the one before"""
    proxy_radius_m: float = 0.0
    """radius of the proxy around the facade (m); 0: twice the facade bounds' horizontal half-diagonal"""
    proxy_surroundings: bool = False
    """reflected rays meet the surroundings of the coarse point cloud (``shading.surroundings``: a surface
    model of its trees and buildings) and the ground instead of the room's wall and floor"""
    proxy_cell_m: float = 1.0
    """cell size of that surface model (m)"""
    proxy_reach_m: float = 0.0
    """how far from the facade's centre the surface model and the floor reach (m); 0: 1.5 x the room's
    radius"""
    proxy_margin_m: float = 1.0
    """coarse points farther than this outside the facade bounds (horizontally) make the surface model (m)"""
    self_hits: bool = False
    """cast each reflected ray against the corrected mesh and give the middle layer where it meets the
    facade itself (``shading.self_hits``); the proxy's features are zeroed on such rays"""
    self_hit_offset_m: float = 0.02
    """reflected rays start this far along w_r from X_r (m), off the surface they leave"""
    self_hit_max_m: float = 0.0
    """hits farther than this are misses (m); 0: every hit counts"""


ReflectionModel = SHOnly | EnvMap | ReflectionMLP


class EnvMapModule(nn.Module):
    """R(w_r) = sigmoid(bilinear lookup of a [3, H, W] texture at (azimuth, w_r.z))."""

    def __init__(self, cfg: EnvMap):
        super().__init__()
        if cfg.height_px < 2 or cfg.width_px < 2:
            raise ValueError(f"environment map must be at least 2x2 px, got {cfg.height_px}x{cfg.width_px}")
        self.logits = nn.Parameter(torch.zeros(1, 3, cfg.height_px, cfg.width_px))

    def forward(self, x_norm: Tensor, w_r: Tensor) -> Tensor:  # [P, 3], [P, 3] unit -> [P, 3]
        del x_norm  # an infinitely distant environment: the position does not matter
        x, y, z = w_r.unbind(-1)
        # atan2 has an unbounded gradient at x = y = 0 (straight up/down); nudge x there. Bounded, finite.
        pole = (x.abs() + y.abs()) < 1e-6
        x = torch.where(pole, torch.full_like(x, 1e-6), x)
        u = torch.atan2(y, x) / math.pi  # [-1, 1]
        v = -z.clamp(-1.0, 1.0)  # equal-area rows, +z on the top row
        grid = torch.stack([u, v], dim=-1).view(1, 1, -1, 2)
        out = F.grid_sample(self.logits, grid, mode="bilinear", padding_mode="border", align_corners=False)
        return torch.sigmoid(out.view(3, -1).T)


class ReflectionMLPModule(nn.Module):
    """The reflection MLP of Fig. 7: gamma(X_r) through the first half; at the middle layer concatenate the
    features with gamma(w_r), (skip) gamma(X_r) again, (self hits) where the reflected ray meets the facade
    and (proxy) the environment proxy's features at the reflected ray's hit; ReLU hidden layers; sigmoid
    RGB out."""

    def __init__(
        self,
        cfg: ReflectionMLP,
        bounds: tuple[Tensor, Tensor] | None = None,
        mesh: tuple[Tensor, Tensor, Tensor | None] | None = None,
        points: np.ndarray | None = None,
    ):
        """``bounds``: the facade's [lo, hi] (m) that X_r is normalised by; needed with proxy features or
        self hits. ``mesh``: the corrected mesh's vertices [V, 3] (m), triangles [T, 3] and glass labels
        [T] bool (None: unknown); needed with self hits. ``points``: the coarse point cloud [N, 3] (m) the
        proxy's surroundings are binned from (None: left empty for a saved state to fill)."""
        super().__init__()
        if cfg.depth < 2 or cfg.width < 1:
            raise ValueError(f"reflection MLP needs depth >= 2 and width >= 1, got {cfg.depth}x{cfg.width}")
        self.cfg = cfg
        self.proxy: ProxyFeatures | None = None
        self.self_hits: FacadeHits | None = None
        if cfg.proxy_channels > 0 or cfg.self_hits:
            if bounds is None:
                raise ValueError("a reflection MLP with proxy features or self hits needs the facade bounds")
            lo, hi = (b.detach().float() for b in bounds)
            self.register_buffer("bounds_lo", lo.clone(), persistent=False)
            self.register_buffer("bounds_hi", hi.clone(), persistent=False)
        if cfg.self_hits:
            if mesh is None:
                raise ValueError("a reflection MLP with self hits needs the corrected mesh")
            self.self_hits = FacadeHits(
                *mesh, offset_m=cfg.self_hit_offset_m, max_distance_m=cfg.self_hit_max_m
            )
        if cfg.proxy_channels > 0:
            geometry = ProxyGeometry.around(lo, hi, cfg.proxy_radius_m)
            surroundings = None
            if cfg.proxy_surroundings:
                reach = cfg.proxy_reach_m if cfg.proxy_reach_m > 0 else 1.5 * geometry.radius
                surroundings = Surroundings(lo, hi, reach, cfg.proxy_cell_m, points, cfg.proxy_margin_m)
            self.proxy = ProxyFeatures(
                geometry,
                cfg.proxy_channels,
                cfg.proxy_resolution_px,
                cfg.proxy_levels,
                PROXY_INIT_STD,
                surroundings,
            )
        enc = fourier_dim(cfg.fourier_levels)
        self.n_first = cfg.depth // 2
        first = [nn.Linear(enc, cfg.width)] + [
            nn.Linear(cfg.width, cfg.width) for _ in range(self.n_first - 1)
        ]
        mid_in = (
            cfg.width
            + enc
            + (enc if cfg.skip else 0)
            + (0 if self.proxy is None else self.proxy.out_dim)
            + (0 if self.self_hits is None else SELF_HIT_DIM)
        )
        second = [nn.Linear(mid_in, cfg.width)]
        second += [nn.Linear(cfg.width, cfg.width) for _ in range(cfg.depth - self.n_first - 1)]
        self.first = nn.ModuleList(first)
        self.second = nn.ModuleList(second)
        self.out = nn.Linear(cfg.width, 3)
        # He initialisation of the ReLU layers: with torch's default (variance 1/(3 fan_in)) the signal
        # shrinks about 3x per layer, so the 8-layer MLP starts as a constant R whose gradients vanish, and
        # Adam then drives the output bias into the sigmoid's flat end (R = 1 everywhere within 20 steps on
        # demo, measured), where it stays.
        for layer in (*self.first, *self.second):
            nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
            nn.init.zeros_(layer.bias)

    def forward(self, x_norm: Tensor, w_r: Tensor) -> Tensor:  # [P, 3] in [-1, 1], [P, 3] unit -> [P, 3]
        gx = fourier_features(x_norm, self.cfg.fourier_levels)  # [P, 6L]
        gw = fourier_features(w_r, self.cfg.fourier_levels)  # [P, 6L]
        h = gx
        for layer in self.first:
            h = F.relu(layer(h))
        mid = [h, gw, gx] if self.cfg.skip else [h, gw]
        if self.proxy is not None or self.self_hits is not None:
            x = self.bounds_lo + 0.5 * (x_norm + 1.0) * (self.bounds_hi - self.bounds_lo)
            hits = None if self.self_hits is None else self.self_hits(x, w_r)
            if self.proxy is not None:
                env = self.proxy(x, w_r)
                mid.append(env if hits is None else env * (1.0 - hits[:, :1]))
            if hits is not None:
                mid.append(hits)
        h = torch.cat(mid, dim=-1)
        for layer in self.second:
            h = F.relu(layer(h))
        return torch.sigmoid(self.out(h))


def build_reflection_module(
    model: ReflectionModel,
    device: torch.device | str,
    bounds: tuple[Tensor, Tensor] | None = None,
    mesh: tuple[Tensor, Tensor, Tensor | None] | None = None,
    points: np.ndarray | None = None,
) -> nn.Module | None:
    """The trainable module of a reflection model (None for ``SHOnly``), on ``device``, in float32.
    ``bounds``: the facade's [lo, hi] (m), which an MLP with proxy features or self hits is built around;
    ``mesh``: the corrected mesh (vertices [V, 3] m, triangles [T, 3], glass labels [T] or None) that an
    MLP with self hits casts its reflected rays against; ``points``: the coarse point cloud [N, 3] (m) an
    MLP's proxy surroundings are binned from (None: empty until a saved state is loaded)."""
    match model:
        case SHOnly():
            return None
        case EnvMap():
            return EnvMapModule(model).to(device)
        case ReflectionMLP():
            return ReflectionMLPModule(model, bounds, mesh, points).to(device)
        case _:
            assert_never(model)


def model_name(model: ReflectionModel) -> str:
    """The config name of a reflection model: ``sh``, ``envmap`` or ``mlp``."""
    match model:
        case SHOnly():
            return "sh"
        case EnvMap():
            return "envmap"
        case ReflectionMLP():
            return "mlp"
        case _:
            assert_never(model)


def reflection_record(
    strategy: ReflectionModel, bounds: tuple[Any, Any], reflection: nn.Module | None
) -> dict[str, Any]:
    """What a ``reflection.pt`` holds (``evaluation.render_views.load_trained`` reads it): the strategy's
    name and fields, the facade bounds [lo, hi] (m), the weights and, for an MLP with self hits, the mesh
    it casts against."""
    record: dict[str, Any] = {
        "model": model_name(strategy),
        "config": asdict(strategy),
        "bounds": [[float(c) for c in b] for b in bounds],
        "state_dict": {} if reflection is None else reflection.state_dict(),
    }
    hits = getattr(reflection, "self_hits", None)
    if hits is not None:
        record["mesh"] = {n: getattr(hits, n).cpu() for n in MESH_FIELDS}
    return record
