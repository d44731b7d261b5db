"""Reflection models: how the specular colour R of Eq. 7 is obtained. A strategy dataclass picks one:

- ``SHOnly``: no reflection term (vanilla 2DGS: I = D); the baseline the paper calls 2DGS.
- ``EnvMap``: R looked up in a learnable environment map by the reflection direction alone, the infinitely
  distant light of GaussianShader and Ref-Gaussian (cannot represent near-field parallax).
- ``ReflectionMLP``: the paper's network (section 3.2.2, Fig. 7): R = MLP(gamma(X_r), gamma(w_r)), optionally
  also fed features read where the reflected ray meets a proxy of the surroundings (``shading.proxy``).

The dataclasses are read from ``[train_gs.reflection]``: ``model`` picks the strategy, ``[...mlp]``,
``[...proxy]`` and ``[...envmap]`` fill ``ReflectionMLP``, ``EnvironmentProxy`` and ``EnvMap``;
``ReflectionParams.strategy`` is the one builder.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import Any, assert_never

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from facade_pipeline.errors import InputError
from facade_pipeline.shading.fourier import fourier_dim, fourier_features
from facade_pipeline.shading.params import (
    EnvironmentProxy,
    EnvMap,
    ReflectionMLP,
    ReflectionModel,
    SHOnly,
)
from facade_pipeline.shading.proxy import ProxyFeatures, proxy_reach_m
from facade_pipeline.shading.surroundings import Surroundings
from facade_pipeline.training.params import facade_size

#: Standard deviation of the proxy feature maps' initial values.
PROXY_INIT_STD = 0.1

#: On CUDA the reflection MLP's matrix products run in this type (autocast: its parameters, its inputs, the
#: proxy's features and R stay float32, and the backward's products follow the forward's). In float32 they
#: are the largest share of a GPU step's device time, on no tensor core (benchmarks/RESULTS.md, "The GPU
#: check"). bfloat16 keeps float32's exponent range, so no activation or gradient over- or underflows, and
#: its 8-bit mantissa rounds a layer's output by about one 8-bit photo step. None: float32. The CPU always
#: computes in float32.
CUDA_MATMUL_DTYPE: torch.dtype | None = torch.bfloat16


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
    features with gamma(w_r), (skip) gamma(X_r) again and (proxy) the environment proxy's features at the
    reflected ray's hit; ReLU hidden layers; sigmoid RGB out."""

    def __init__(
        self,
        cfg: ReflectionMLP,
        bounds: tuple[Tensor, Tensor] | None = None,
        points: np.ndarray | None = None,
    ):
        """``bounds``: the facade's [lo, hi] (m) that X_r is normalised by; needed with proxy features.
        ``points``: the coarse point cloud [N, 3] (m) the proxy's surroundings are binned from (None: left
        empty for a saved state to fill)."""
        super().__init__()
        if cfg.depth < 2 or cfg.width < 1:
            raise ValueError(f"reflection MLP needs depth >= 2 and width >= 1, got {cfg.depth}x{cfg.width}")
        self.cfg = cfg
        self.proxy: ProxyFeatures | None = None
        proxy = cfg.proxy
        if proxy is not None and proxy.channels > 0:
            if bounds is None:
                raise ValueError("a reflection MLP with proxy features needs the facade bounds")
            lo, hi = (b.detach().float() for b in bounds)
            self.register_buffer("bounds_lo", lo.clone(), persistent=False)
            self.register_buffer("bounds_hi", hi.clone(), persistent=False)
            cell_m = proxy.cell * facade_size((lo, hi))
            surroundings = Surroundings(lo, hi, proxy_reach_m(lo, hi), cell_m, points, cfg.proxy_margin_m)
            self.proxy = ProxyFeatures(
                surroundings, proxy.channels, proxy.resolution_px, proxy.levels, PROXY_INIT_STD
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
        )
        second = [nn.Linear(mid_in, cfg.width)]
        second += [nn.Linear(cfg.width, cfg.width) for _ in range(cfg.depth - self.n_first - 1)]
        self.first = nn.ModuleList(first)
        self.second = nn.ModuleList(second)
        self.out = nn.Linear(cfg.width, 3)
        self.cuda_matmul_dtype = CUDA_MATMUL_DTYPE
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
        feats = None
        if self.proxy is not None:
            x = self.bounds_lo + 0.5 * (x_norm + 1.0) * (self.bounds_hi - self.bounds_lo)
            feats = self.proxy(x, w_r)
        low = self.cuda_matmul_dtype is not None and x_norm.is_cuda
        with torch.autocast("cuda", dtype=self.cuda_matmul_dtype or torch.float32, enabled=low):
            h = gx
            for layer in self.first:
                h = F.relu(layer(h))
            mid = [h, gw, gx] if self.cfg.skip else [h, gw]
            h = torch.cat(mid if feats is None else [*mid, feats], dim=-1)
            for layer in self.second:
                h = F.relu(layer(h))
            logits = self.out(h)
        return torch.sigmoid(logits.float())


def build_reflection_module(
    model: ReflectionModel,
    device: torch.device | str,
    bounds: tuple[Tensor, Tensor] | None = None,
    points: np.ndarray | None = None,
) -> nn.Module | None:
    """The trainable module of a reflection model (None for ``SHOnly``), on ``device``, in float32.
    ``bounds``: the facade's [lo, hi] (m), which an MLP with proxy features is built around; ``points``:
    the coarse point cloud [N, 3] (m) an MLP's proxy surroundings are binned from (None: empty until a
    saved state is loaded)."""
    match model:
        case SHOnly():
            return None
        case EnvMap():
            return EnvMapModule(model).to(device)
        case ReflectionMLP():
            return ReflectionMLPModule(model, bounds, points).to(device)
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
    """What a ``reflection.pt`` holds (``evaluation.render_views.load_trained`` reads it back with
    ``strategy_from_record``): the strategy's name and fields, the facade bounds [lo, hi] (m) and the
    weights."""
    return {
        "model": model_name(strategy),
        "config": asdict(strategy),
        "bounds": [[float(c) for c in b] for b in bounds],
        "state_dict": {} if reflection is None else reflection.state_dict(),
    }


#: Fields of a saved MLP's record that options no longer offered used, with the value that means what the
#: code does now; a record with another value was trained with the option and cannot be rebuilt.
_RETIRED_MLP_FIELDS = {
    "proxy_radius_m": 0.0,
    "proxy_reach_m": 0.0,
    "proxy_surroundings": True,
    "self_hits": False,
    "self_hit_offset_m": None,
    "self_hit_max_m": None,
}
#: Proxy fields of a record written before the proxy had its own table, by their present name.
_FLAT_PROXY_FIELDS = {
    "proxy_channels": "channels",
    "proxy_resolution_px": "resolution_px",
    "proxy_levels": "levels",
    "proxy_cell_m": "cell_m",
}


def strategy_from_record(name: str, config: dict[str, Any], path: Path | None = None) -> ReflectionModel:
    """The reflection strategy named ``name`` (``sh``/``envmap``/``mlp``) with the fields a
    ``reflection_record`` saved, in its present form or in the flat form of earlier records (the proxy's
    fields as ``proxy_*``). A field that asks for an option no longer offered is an ``InputError``."""
    try:
        match name:
            case "sh":
                return SHOnly()
            case "envmap":
                return EnvMap(**config)
            case "mlp":
                return _mlp_from_record(dict(config), path)
    except TypeError as e:
        raise InputError(path, f"the fields of the {name!r} reflection model", str(e)) from None
    raise InputError(path, "a reflection model 'sh', 'envmap' or 'mlp'", repr(name))


def _mlp_from_record(config: dict[str, Any], path: Path | None) -> ReflectionMLP:
    channels = (config.get("proxy") or {}).get("channels", config.get("proxy_channels", 0))
    for key, kept in _RETIRED_MLP_FIELDS.items():
        value = config.pop(key, kept)
        # without proxy features the room and its surroundings were never built: any value did the same
        moot = key.startswith("proxy_") and not channels
        if kept is not None and value != kept and not moot:
            raise InputError(
                path,
                f"a reflection MLP this version builds ({key} = {kept!r})",
                f"{key} = {value!r}, an option no longer offered: retrain the model",
            )
    flat = {new: config.pop(old) for old, new in _FLAT_PROXY_FIELDS.items() if old in config}
    proxy = config.pop("proxy", None)
    if flat:
        proxy = flat
    if proxy is not None and "cell_m" in proxy:
        # the surface model's cell in metres, before it was a fraction of the facade's size
        if proxy.get("channels", 0):
            raise InputError(
                path,
                "a reflection MLP this version builds (the proxy's cell a fraction of the facade's size)",
                f"cell_m = {proxy['cell_m']!r}, a cell in metres: retrain the model",
            )
        proxy = {k: v for k, v in proxy.items() if k != "cell_m"}
    return ReflectionMLP(**config, proxy=None if proxy is None else EnvironmentProxy(**proxy))
