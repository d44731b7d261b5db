"""The parameters of the ``train_gs`` stage: one frozen dataclass read from ``[train_gs]``.

Schedules are fractions of ``iterations`` so that a short CI run keeps the shape of the paper's schedule;
intervals (densification, opacity reset, checkpoints) are in iterations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, assert_never

from facade_pipeline.shading.reflection import EnvMap, ReflectionMLP, ReflectionModel, SHOnly
from facade_pipeline.training.exposure import ExposureParams


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates (2DGS defaults; ``position_*`` are multiplied by the scene extent)."""

    position_init: float
    position_final: float
    sh_dc: float
    sh_rest: float
    opacity: float
    scaling: float
    rotation: float
    reflectivity: float
    f0: float
    reflection_init: float
    """of the reflection MLP's weights, decayed exponentially to ..."""
    reflection_final: float
    envmap: float
    """of the environment map's texel logits (constant): each texel sees few pixels, like a splat colour"""
    proxy: float
    """of the reflection MLP's proxy feature maps (constant), for the same reason"""
    pose_rotation: float
    """of the per-view pose corrections' rotations (rad, constant)"""
    pose_translation: float
    """of their translations (m, constant)"""
    exposure: float
    """of the per-view log exposure gains (``exposure_refinement``, constant)"""


@dataclass(frozen=True)
class DensifyParams:
    """Densification and pruning as 2DGS does it (clone / split by view-space gradient, prune, reset)."""

    start_fraction: float
    end_fraction: float
    interval: int
    """iterations between densification steps"""
    grad_threshold: float
    """mean view-space (NDC) positional gradient above which a splat is cloned or split"""
    percent_dense: float
    """splats larger than this fraction of the scene extent are split, smaller ones cloned"""
    split_count: int
    opacity_reset_interval: int
    """iterations between opacity resets (0: never)"""
    opacity_reset_value: float
    prune_opacity: float
    prune_world_size_fraction: float
    """after the first opacity reset, splats larger than this fraction of the extent are pruned"""
    max_gaussians: int
    """no densification beyond this many splats (bounds CPU time and memory)"""


@dataclass(frozen=True)
class TrainParams:
    """``[train_gs]``: every number that changes the trained model."""

    iterations: int
    seed: int
    device: Literal["cpu", "cuda", "auto"]
    raster_backend: Literal["auto", "cpp", "torch", "gsplat"]
    near_m: float
    lowpass_sigma_px: float
    """sigma of the renderer's screen-space low-pass filter (``splatting.render_2dgs``), in training and in
    every later render of the model"""
    reflection_model: Literal["sh", "envmap", "mlp"]
    fourier_levels: int
    mlp_depth: int
    mlp_width: int
    mlp_skip: bool
    mlp_proxy_channels: int
    mlp_proxy_resolution_px: int
    mlp_proxy_levels: int
    mlp_proxy_radius_m: float
    mlp_proxy_surroundings: bool
    """reflected rays meet the surroundings of the coarse point cloud (``shading.surroundings``)"""
    mlp_proxy_cell_m: float
    mlp_proxy_reach_m: float
    mlp_self_hits: bool
    """give the MLP where each reflected ray meets the facade itself (``shading.self_hits``)"""
    mlp_self_hit_offset_m: float
    mlp_self_hit_max_m: float
    envmap_height_px: int
    envmap_width_px: int
    sh_degree: int
    sh_degree_interval: int
    refl_threshold: float
    reflection_normal_grad: bool
    supersample: int
    """sub-pixel samples per pixel side in every render (``ShadingOptions.supersample``)"""
    pose_refinement: bool
    exposure_estimate: bool
    """estimate an exposure gain per training view and colour channel from the facade's opaque parts
    before training (``training.exposure``), and train with it"""
    exposure_refinement: bool
    """learn an exposure gain per training view and colour channel (on top of the estimate, if any),
    relative to their mean"""
    mlp_max_pixels: int
    patch_px: int
    test_every: int
    mask_by_facade: bool
    lambda_dssim: float
    lambda_normal: float
    normal_start_fraction: float
    lambda_normal_prior: float
    normal_prior_start_fraction: float
    lambda_hf_start: float
    lambda_hf_end: float
    hf_tau_start: float
    hf_tau_end: float
    hf_steps: int
    hf_start_fraction: float
    hf_residual: Literal["mean", "sum"]
    hf_eps: float
    lambda_distortion: float
    distortion_start_fraction: float
    init_max_points: int
    init_mesh_samples: int
    init_bounds_margin_m: float
    init_opacity: float
    init_reflectivity: float
    init_reflectivity_glass: float
    init_f0: float
    init_knn: int
    checkpoint_every: int
    log_every: int
    divergence_extent_factor: float
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
