"""The reflection model strategies (``reflection`` explains each) and their parameters, read from
``[train_gs.reflection]``, apart from the torch modules that implement them, so that reading them costs no
heavy import: doit reads every stage's parameters to build its task list."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal, assert_never

from facade_pipeline.config import Count, NonNeg, PosInt, Positive


@dataclass(frozen=True)
class SHOnly:
    """No specular term: I = D."""


@dataclass(frozen=True)
class EnvMap:
    """A learnable equal-area (cylindrical) environment map, sigmoid-activated RGB
    (``[train_gs.reflection.envmap]``)."""

    height_px: PosInt = 64
    """rows: the cosine of the polar angle (w_r.z from +1 at the top to -1 at the bottom)"""
    width_px: PosInt = 128
    """columns: azimuth from -pi to pi"""


@dataclass(frozen=True)
class EnvironmentProxy:
    """Feature maps read where the reflected ray meets the surroundings (``shading.proxy``,
    ``[train_gs.reflection.proxy]``), given to the MLP's middle layer beside gamma(w_r)."""

    channels: Count = 0
    """feature channels; 0: none, the paper's network"""
    resolution_px: PosInt = 256
    """texels across the proxy's finest floor map (and around its finest wall map)"""
    levels: PosInt = 3
    """feature maps per part, each a quarter of the resolution of the one before"""
    cell: Positive = 1.0 / 60.0
    """cell size of the surroundings' surface model, a fraction of the facade's size (the diagonal of the
    corrected mesh's bounds, ``training.params.facade_size``): 1/60 is about 1 m on demo, 62 m across"""


@dataclass(frozen=True)
class ReflectionMLP:
    """The paper's reflection MLP (Table 3 varies the first four; ``[train_gs.reflection.mlp]``)."""

    fourier_levels: PosInt = 12
    """L of Eq. 10, for both X_r and w_r"""
    depth: PosInt = 8
    """hidden ReLU layers; the first depth // 2 see the encoded position alone"""
    width: PosInt = 512
    """hidden units per layer"""
    skip: bool = True
    """re-inject gamma(X_r) at the middle layer beside gamma(w_r)"""
    proxy: EnvironmentProxy | None = None
    """the environment proxy's features (None, or 0 channels: the paper's network);
    ``ReflectionParams.strategy`` fills it from [train_gs.reflection.proxy]"""
    proxy_margin_m: NonNeg = 1.0
    """coarse points farther than this outside the facade bounds (horizontally) make the proxy's surface
    model of the surroundings (m; ``training.params.INIT_BOUNDS_MARGIN_M``)"""


ReflectionModel = SHOnly | EnvMap | ReflectionMLP


@dataclass(frozen=True)
class ReflectionParams:
    """``[train_gs.reflection]``: the specular term R of Eq. 7 and the fields of each choice."""

    model: Literal["sh", "envmap", "mlp"]
    """"sh" (none, vanilla 2DGS), "envmap" (distant light) or "mlp" (the paper's)"""
    mlp: ReflectionMLP
    proxy: EnvironmentProxy
    envmap: EnvMap

    def strategy(self, margin_m: float) -> ReflectionModel:
        """The strategy ``model`` selects; an MLP gets the proxy and ``margin_m`` (the splats' bounds
        margin, m), around the facade bounds of which the proxy's surroundings are taken."""
        match self.model:
            case "sh":
                return SHOnly()
            case "envmap":
                return self.envmap
            case "mlp":
                return replace(self.mlp, proxy=self.proxy, proxy_margin_m=margin_m)
            case _:
                assert_never(self.model)
