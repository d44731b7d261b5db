"""The parameters of the ``train_gs`` stage: one frozen dataclass read from ``[train_gs]``.

Schedules are fractions of ``iterations`` so that a short CI run keeps the shape of the paper's schedule;
intervals (densification, opacity reset, checkpoints) are in iterations.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Annotated, Any, TypeVar

import numpy as np

from facade_pipeline.config import AnyInt, Count, Fraction, NonNeg, PosInt, Positive, Range
from facade_pipeline.shading.params import ReflectionModel, ReflectionParams

T = TypeVar("T")


#: Numbers of the method that no building tuned, fixed here so that the config holds what a user tunes.
#: R is evaluated only on facade pixels whose rendered reflectivity exceeds this (0-1): below it the
#: specular term cannot show, and the MLP's cost goes to the pixels where it does.
REFL_THRESHOLD = 0.01
#: Lengths of training are measured from the scene: the facade's size is the diagonal of the corrected
#: mesh's bounds (``facade_size``). Coarse points farther than this fraction of it outside those bounds do
#: not become splats, and the reflection proxy's surroundings begin this far beyond them (about the fixed
#: 1 m it replaces on demo, whose facade is 62 m across its bounds).
INIT_BOUNDS_MARGIN = 1.0 / 60.0
#: Splat intersections nearer to the camera than this fraction of the facade's size are skipped (about the
#: reference 2DGS near plane, 0.2 m, on demo; a fixed 0.2 m clips a 1:25 model's wall, 0.21-0.35 m from
#: its cameras).
NEAR_FRACTION = 0.2 / 60.0
#: initial Fresnel F0 of every splat, all channels, learnt from there: coated facade glass reflects strongly
#: (0-1). Uncoated float glass's 0.04 trains gcw_dev's real glass 2 dB worse (benchmarks/RESULTS.md, Tried).
INIT_F0 = 0.5


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates of what 2DGS does not have, and its position rate at the start (times the
    scene extent); its other rates are constants of ``training.optimizers`` and ``training.schedule``."""

    position_init: Positive
    reflectivity: Positive
    reflection_init: Positive
    """of the reflection MLP's weights, decayed exponentially to ..."""
    proxy: Positive
    """of the reflection MLP's proxy feature maps (constant), for the same reason"""


@dataclass(frozen=True)
class DensifyParams:
    """Densification and pruning as 2DGS does it (clone / split by view-space gradient, prune, reset): what
    a budget sets; 2DGS's other numbers are constants of ``training.densify``."""

    interval: Count
    """iterations between densification steps"""
    grad_threshold: Positive
    """mean view-space (NDC) positional gradient above which a splat is cloned or split"""
    opacity_reset_interval: Count
    """iterations between opacity resets (0: never)"""
    max_gaussians: PosInt
    """no densification beyond this many splats (bounds CPU time and memory)"""


@dataclass(frozen=True)
class TrainParams:
    """``[train_gs]``: every number that changes the trained model."""

    iterations: PosInt
    seed: AnyInt
    lowpass_sigma_px: Positive
    """sigma of the renderer's screen-space low-pass filter (``splatting.render_2dgs``), in training and in
    every later render of the model"""
    reflection: ReflectionParams
    sh_degree: Annotated[int, Range(0, 3)]
    sh_degree_interval: Count
    reflection_normal_grad: bool
    supersample: PosInt
    """sub-pixel samples per pixel side in every render (``ShadingOptions.supersample``)"""
    pose_refinement: bool
    exposure_estimate: bool
    """estimate an exposure gain per training view and colour channel from the facade's opaque parts
    before training (``training.exposure``), and train with it"""
    mlp_max_pixels: Count
    max_view_pixels: Count
    """views of more pixels are trained, and measured, with f x f of their pixels averaged into one, f the
    smallest integer that brings them within this many (``data.pixel_budget_factor``; 0: as they are)"""
    patch_px: Count
    test_every: Count
    mask_by_facade: bool
    lambda_normal: NonNeg
    lambda_normal_prior: NonNeg
    lambda_opacity: NonNeg
    """weight of the opacity term (``losses.opacity_loss``): the facade's pixels pulled toward opaque"""
    lambda_hf_start: NonNeg
    lambda_hf_end: NonNeg
    hf_tau_start: NonNeg
    hf_tau_end: NonNeg
    hf_steps: PosInt
    init_max_points: Count
    init_mesh_samples: Count
    init_reflectivity: Fraction
    init_reflectivity_glass: Fraction
    lr: LearningRates
    densify: DensifyParams

    def reflection_strategy(self, bounds: tuple[Any, Any]) -> ReflectionModel:
        """The reflection model strategy these parameters select for a facade of ``bounds`` (lo, hi)."""
        return self.reflection.strategy(INIT_BOUNDS_MARGIN * facade_size(bounds))


def facade_size(bounds: tuple[Any, Any]) -> float:
    """The diagonal (m) of the facade's bounds (lo, hi: the corrected mesh's, arrays or tensors of 3): the
    length every length of training is relative to."""
    lo, hi = (np.asarray(b.detach().cpu() if hasattr(b, "detach") else b, np.float64) for b in bounds)
    return float(np.linalg.norm(hi - lo))


def near_plane(bounds: tuple[Any, Any]) -> float:
    """The near plane (m) of every render of a model of a facade of ``bounds`` (``NEAR_FRACTION``)."""
    return NEAR_FRACTION * facade_size(bounds)


def flat_params(params: dict[str, Any]) -> dict[str, Any]:
    """``train_gs`` parameters in ``to_dict`` form with the ``reflection`` table spelt in the flat keys that
    models saved before it carry (``reflection_model``, ``fourier_levels``, ``mlp_*``, ``envmap_*``): the
    one form in which the evaluation compares and labels trained variants of either age. Flat parameters
    come back as they are."""
    refl = params.get("reflection")
    if not isinstance(refl, dict):
        return params
    mlp, proxy, envmap = refl["mlp"], refl["proxy"], refl["envmap"]
    flat = {k: v for k, v in params.items() if k != "reflection"}
    return flat | {
        "reflection_model": refl["model"],
        "fourier_levels": mlp["fourier_levels"],
        "mlp_depth": mlp["depth"],
        "mlp_width": mlp["width"],
        "mlp_skip": mlp["skip"],
        "mlp_proxy_channels": proxy["channels"],
        "mlp_proxy_resolution_px": proxy["resolution_px"],
        "mlp_proxy_levels": proxy["levels"],
        "mlp_proxy_cell": proxy["cell"],
        "mlp_proxy_surroundings": True,  # the proxy's rays always meet the surroundings now
        "envmap_height_px": envmap["height_px"],
        "envmap_width_px": envmap["width_px"],
    }


def replace_keys(params: T, changes: dict[str, Any]) -> T:
    """``params`` (a frozen params dataclass) with ``changes`` applied, keyed as in the config: a field's
    name, dotted for a nested table (``reflection.mlp.depth``, ``densify.max_gaussians``). For variants
    built by key overrides (benchmarks, tests)."""
    nested: dict[str, dict[str, Any]] = {}
    direct: dict[str, Any] = {}
    for key, value in changes.items():
        head, dot, rest = key.partition(".")
        if dot:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[key] = value
    for head, sub in nested.items():
        direct[head] = replace_keys(getattr(params, head), sub)
    return dataclasses.replace(params, **direct)


@dataclass(frozen=True)
class AlignParams:
    """``[evaluate.align]``: how a measured view is aligned to the frozen model before it is measured."""

    steps: Count
    """Adam steps on the view's whole image (0: no alignment)"""
    lr_rotation: Positive
    """of the rotation correction (rad)"""
    lr_translation: Positive
    """of the translation correction (m)"""
    lr_exposure: Positive
    """of the log gain per colour channel (-)"""
    exposure: bool
    """fit the exposure gain as well as the pose"""
    max_pixels: Count = 0
    """the fit's image: the measured view with f x f pixels averaged into one, f the smallest integer that
    brings it within this many (``data.pixel_budget_factor``; 0: the measured view itself); the fitted pose
    is then measured at the view's size"""
