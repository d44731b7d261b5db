"""The one entry point of the 2DGS renderer: ``render_2dgs`` (paper section 2, Eq. 1-5; 2DGS semantics as
listed in shared/DESIGN.md "Reference 2DGS semantics")."""

from __future__ import annotations

import logging
from typing import assert_never

import torch

from facade_pipeline.splatting import cpu_kernel
from facade_pipeline.splatting.binning import bin_splats, pixel_support_bounds
from facade_pipeline.splatting.blend_torch import BlendSettings, blend_torch
from facade_pipeline.splatting.surfels import project_surfels
from facade_pipeline.splatting.types import (
    LOWPASS_SIGMA_PX,
    Backend,
    PixelWindow,
    SurfelRender,
    is_reference_lowpass,
    lowpass_inv_var,
)

log = logging.getLogger(__name__)

DEFAULT_NEAR = 0.2
"""Near plane (m) of the reference rasterizer."""
DEFAULT_FAR = 100.0
"""Far plane (m) of the NDC depth in the reference's distortion term."""
_WARNED: set[tuple] = set()
"""Fallbacks already warned about (a missing gsplat or C++ kernel, a low-pass sigma gsplat cannot render): a
renderer is called once per training step, so each fallback is logged once per process, not per call."""


def _warn_once(key: tuple, msg: str, *args) -> None:
    if key not in _WARNED:
        _WARNED.add(key)
        log.warning(msg, *args)


def _check_inputs(means, quats, scales, opacities, features, cam_from_world, K, width, height) -> None:
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {
        "means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 2)),
        "opacities": (opacities, (n,)), "cam_from_world": (cam_from_world, (4, 4)), "K": (K, (3, 3)),
    }  # fmt: skip
    for name, (t, shape) in expected.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)} (N = {n}), got {list(t.shape)}")
    if features.dim() != 2 or features.shape[0] != n:
        raise ValueError(f"features must have shape [N, F] with N = {n}, got {list(features.shape)}")
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    tensors = (means, quats, scales, opacities, features, cam_from_world, K)
    if len({t.dtype for t in tensors}) != 1 or not means.dtype.is_floating_point:
        raise ValueError(f"all tensors must share one floating dtype, got {[t.dtype for t in tensors]}")
    if len({t.device for t in tensors}) != 1:
        raise ValueError(f"all tensors must be on one device, got {[t.device for t in tensors]}")


def resolve_backend(backend: Backend, device: torch.device) -> Backend:
    """The concrete backend for ``backend`` on ``device`` ("auto" resolved, unavailable choices replaced by
    the torch reference with a logged warning, gsplat without CUDA refused)."""
    if backend == "auto":
        if device.type == "cuda" and torch.cuda.is_available():
            from facade_pipeline.splatting import gsplat_backend

            if gsplat_backend.available():
                return "gsplat"
            _warn_once(("no gsplat", str(device)),
                       "gsplat is not installed: rendering with the torch backend on %s", device)
            return "torch"
        return resolve_backend("cpp", device) if device.type == "cpu" else "torch"
    if backend == "cpp":
        if device.type != "cpu":
            raise ValueError(f"the cpp backend runs on CPU tensors only, got {device}")
        if cpu_kernel.load() is None:
            _warn_once(("no cpp",), "C++ kernel unavailable (%s): using the torch backend",
                       cpu_kernel.load_error())
            return "torch"
        return "cpp"
    if backend == "gsplat":
        if device.type != "cuda" or not torch.cuda.is_available():
            raise ValueError(f"the gsplat backend needs CUDA tensors and a CUDA device, got {device}")
        return "gsplat"
    if backend == "torch":
        return "torch"
    assert_never(backend)


def render_2dgs(
    means: torch.Tensor,  # [N, 3] splat centres, world frame (m)
    quats: torch.Tensor,  # [N, 4] rotations (w, x, y, z), normalised inside; columns t_u, t_v, normal
    scales: torch.Tensor,  # [N, 2] extents s_u, s_v along t_u, t_v (m), activated (>= 0)
    opacities: torch.Tensor,  # [N] in [0, 1], activated
    features: torch.Tensor,  # [N, F] any channels (RGB, reflectivity, F0, ...)
    cam_from_world: torch.Tensor,  # [4, 4] OpenCV axes
    K: torch.Tensor,  # [3, 3] pixels
    width: int,
    height: int,
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
    backend: Backend = "auto",
    crop: PixelWindow | None = None,
    lowpass_sigma_px: float = LOWPASS_SIGMA_PX,
) -> SurfelRender:
    """Render 2D Gaussian surfels into one pinhole view (paper Eq. 1-5), differentiably.

    Each splat is the disk p + s_u t_u u + s_v t_v v with Gaussian G = exp(-(u^2 + v^2) / 2) (Eq. 1-3); the
    pixel's ray meets it at (u, v) found from the ray transform (Eq. 4, see blend_torch); splats are blended
    front to back by centre depth (Eq. 5) with the reference 2DGS rules (low-pass fallback, alpha clamp and
    skip, early stop, near plane). Pixel centres are at (i + 0.5, j + 0.5). ``crop`` renders only that window
    of the ``width`` x ``height`` image (maps equal the same window of the full render). ``far`` only sets
    the NDC depth of the distortion term. ``lowpass_sigma_px`` is the sigma of the screen-space low-pass
    Gaussian every splat renders at least as wide as (2DGS: sqrt(2)/2 px); gsplat has only that one, so
    another sigma with ``backend="auto"`` renders CUDA tensors with the torch backend (logged), and with
    ``backend="gsplat"`` is refused. Returns maps of the window's size (types.SurfelRender).
    """
    _check_inputs(means, quats, scales, opacities, features, cam_from_world, K, width, height)
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    window = crop or PixelWindow(0, 0, width, height)
    window.check_inside(width, height)
    lowpass_inv_var(lowpass_sigma_px)  # ValueError on a bad sigma
    chosen = resolve_backend(backend, means.device)
    if chosen == "gsplat" and not is_reference_lowpass(lowpass_sigma_px):
        if backend == "gsplat":
            raise ValueError(
                f"the gsplat backend's low-pass filter is fixed at sigma {LOWPASS_SIGMA_PX:.4f} px (2DGS's), "
                f"got lowpass_sigma_px = {lowpass_sigma_px}: use that sigma or another backend"
            )
        _warn_once(("lowpass", lowpass_sigma_px), "gsplat has only the low-pass sigma %.4f px, %s px asked: "
                   "rendering with torch", LOWPASS_SIGMA_PX, lowpass_sigma_px)
        chosen = "torch"
    if chosen == "gsplat":
        from facade_pipeline.splatting import gsplat_backend

        return gsplat_backend.render(means, quats, scales, opacities, features, cam_from_world, K, window,
                                     near, far)
    proj = project_surfels(means, quats, scales, cam_from_world, K)
    if chosen == "cpp":
        bins = cpu_kernel.bin_splats_cpp(proj.ray_transform, opacities, proj.depth, window, near,
                                         lowpass_sigma_px=lowpass_sigma_px)
    else:
        bounds = pixel_support_bounds(proj.ray_transform, opacities, near, lowpass_sigma_px)
        bins = bin_splats(bounds, proj.depth, window)
    args = (proj.ray_transform, opacities, features, proj.normal_world, bins)
    if chosen == "cpp":
        maps = cpu_kernel.blend_cpp(*args, near=near, far=far, lowpass_sigma_px=lowpass_sigma_px)
    elif chosen == "torch":
        maps = blend_torch(*args, BlendSettings(near=near, far=far, lowpass_sigma_px=lowpass_sigma_px))
    else:
        raise AssertionError(chosen)
    feats, transmittance, depth_sum, normal, median, distortion = maps
    alpha = 1 - transmittance
    has = alpha > 0
    depth_expected = torch.where(has, depth_sum / torch.where(has, alpha, torch.ones_like(alpha)), 0.0)
    return SurfelRender(features=feats, alpha=alpha, depth_expected=depth_expected, depth_median=median,
                        normal=normal, distortion=distortion)
