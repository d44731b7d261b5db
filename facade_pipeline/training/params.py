"""The parameters of the ``train_gs`` stage: one frozen dataclass read from ``[train_gs]``.

Schedules are fractions of ``iterations`` so that a short CI run keeps the shape of the paper's schedule;
intervals (densification, opacity reset, checkpoints) are in iterations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal, assert_never

from facade_pipeline.config import AnyInt, Count, Fraction, NonNeg, PosInt, Positive, Range
from facade_pipeline.errors import ConfigError
from facade_pipeline.shading.reflection import EnvMap, ReflectionMLP, ReflectionModel, SHOnly
from facade_pipeline.training.exposure import ExposureParams


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates (2DGS defaults; ``position_*`` are multiplied by the scene extent)."""

    position_init: Positive
    position_final: Positive
    sh_dc: Positive
    sh_rest: Positive
    opacity: Positive
    scaling: Positive
    rotation: Positive
    reflectivity: Positive
    f0: Positive
    reflection_init: Positive
    """of the reflection MLP's weights, decayed exponentially to ..."""
    reflection_final: Positive
    envmap: Positive
    """of the environment map's texel logits (constant): each texel sees few pixels, like a splat colour"""
    proxy: Positive
    """of the reflection MLP's proxy feature maps (constant), for the same reason"""
    pose_rotation: Positive
    """of the per-view pose corrections' rotations (rad, constant)"""
    pose_translation: Positive
    """of their translations (m, constant)"""
    exposure: Positive
    """of the per-view log exposure gains (``exposure_refinement``, constant)"""


@dataclass(frozen=True)
class DensifyParams:
    """Densification and pruning as 2DGS does it (clone / split by view-space gradient, prune, reset)."""

    start_fraction: Fraction
    end_fraction: Fraction
    interval: Count
    """iterations between densification steps"""
    grad_threshold: Positive
    """mean view-space (NDC) positional gradient above which a splat is cloned or split"""
    percent_dense: Fraction
    """splats larger than this fraction of the scene extent are split, smaller ones cloned"""
    split_count: PosInt
    opacity_reset_interval: Count
    """iterations between opacity resets (0: never)"""
    opacity_reset_value: Fraction
    prune_opacity: Fraction
    prune_world_size_fraction: Positive
    """after the first opacity reset, splats larger than this fraction of the extent are pruned"""
    max_gaussians: PosInt
    """no densification beyond this many splats (bounds CPU time and memory)"""

    def __post_init__(self) -> None:
        if self.start_fraction > self.end_fraction:
            raise ConfigError(
                None,
                "'train_gs.densify.start_fraction' <= end_fraction",
                f"{self.start_fraction} > {self.end_fraction}",
            )


@dataclass(frozen=True)
class TrainParams:
    """``[train_gs]``: every number that changes the trained model."""

    iterations: PosInt
    seed: AnyInt
    near_m: Positive
    lowpass_sigma_px: Positive
    """sigma of the renderer's screen-space low-pass filter (``splatting.render_2dgs``), in training and in
    every later render of the model"""
    reflection_model: Literal["sh", "envmap", "mlp"]
    fourier_levels: PosInt
    mlp_depth: PosInt
    mlp_width: PosInt
    mlp_skip: bool
    mlp_proxy_channels: Count
    mlp_proxy_resolution_px: PosInt
    mlp_proxy_levels: PosInt
    mlp_proxy_radius_m: NonNeg
    mlp_proxy_surroundings: bool
    """reflected rays meet the surroundings of the coarse point cloud (``shading.surroundings``)"""
    mlp_proxy_cell_m: Positive
    mlp_proxy_reach_m: NonNeg
    mlp_self_hits: bool
    """give the MLP where each reflected ray meets the facade itself (``shading.self_hits``)"""
    mlp_self_hit_offset_m: Positive
    mlp_self_hit_max_m: NonNeg
    envmap_height_px: PosInt
    envmap_width_px: PosInt
    sh_degree: Annotated[int, Range(0, 3)]
    sh_degree_interval: Count
    refl_threshold: Fraction
    reflection_normal_grad: bool
    supersample: PosInt
    """sub-pixel samples per pixel side in every render (``ShadingOptions.supersample``)"""
    pose_refinement: bool
    exposure_estimate: bool
    """estimate an exposure gain per training view and colour channel from the facade's opaque parts
    before training (``training.exposure``), and train with it"""
    exposure_refinement: bool
    """learn an exposure gain per training view and colour channel (on top of the estimate, if any),
    relative to their mean"""
    mlp_max_pixels: Count
    patch_px: Count
    test_every: Count
    mask_by_facade: bool
    lambda_dssim: Fraction
    lambda_normal: NonNeg
    normal_start_fraction: Fraction
    lambda_normal_prior: NonNeg
    normal_prior_start_fraction: Fraction
    lambda_hf_start: NonNeg
    lambda_hf_end: NonNeg
    hf_tau_start: NonNeg
    hf_tau_end: NonNeg
    hf_steps: PosInt
    hf_start_fraction: Fraction
    hf_residual: Literal["mean", "sum"]
    hf_eps: Positive
    lambda_distortion: NonNeg
    distortion_start_fraction: Fraction
    init_max_points: Count
    init_mesh_samples: Count
    init_bounds_margin_m: NonNeg
    init_opacity: Fraction
    init_reflectivity: Fraction
    init_reflectivity_glass: Fraction
    init_f0: Fraction
    init_knn: PosInt
    divergence_extent_factor: Positive
    lr: LearningRates
    densify: DensifyParams
    exposure: ExposureParams

    def reflection(self) -> ReflectionModel:
        """The reflection model strategy these parameters select."""
        match self.reflection_model:
            case "sh":
                return SHOnly()
            case "envmap":
                return EnvMap(self.envmap_height_px, self.envmap_width_px)
            case "mlp":
                return ReflectionMLP(
                    self.fourier_levels,
                    self.mlp_depth,
                    self.mlp_width,
                    self.mlp_skip,
                    self.mlp_proxy_channels,
                    self.mlp_proxy_resolution_px,
                    self.mlp_proxy_levels,
                    self.mlp_proxy_radius_m,
                    self.mlp_proxy_surroundings,
                    self.mlp_proxy_cell_m,
                    self.mlp_proxy_reach_m,
                    self.init_bounds_margin_m,
                    self.mlp_self_hits,
                    self.mlp_self_hit_offset_m,
                    self.mlp_self_hit_max_m,
                )
            case _:
                assert_never(self.reflection_model)
