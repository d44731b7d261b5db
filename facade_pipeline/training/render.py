"""One view through the model: per-splat colour terms -> rasterized maps -> deferred shading (Eq. 7-9).

The rasterizer is injected (``Rasterizer``): the real one is ``facade_pipeline.splatting`` through
``splatting_rasterizer``; tests pass a dense reference. It is called with crop windows so training can work
on patches.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import torch
from torch import Tensor, nn

from facade_pipeline.errors import ConfigError
from facade_pipeline.shading import deferred
from facade_pipeline.shading.sh import eval_sh
from facade_pipeline.splatting.types import LOWPASS_SIGMA_PX, is_reference_lowpass
from facade_pipeline.training.compiling import torch_compiled
from facade_pipeline.training.model import GaussianModel

Window = tuple[int, int, int, int]  # (x0, y0, width, height) in pixels of the full image


@dataclass
class RasterOutput:
    """What the shading needs from a rasterizer, over a window of H x W pixels."""

    features: Tensor  # [H, W, F] alpha-blended features (background 0)
    alpha: Tensor  # [H, W]
    depth: Tensor  # [H, W] depth along the camera z axis where the surface is (0 where alpha is 0)
    normal: Tensor  # [H, W, 3] alpha-blended world normal, facing the camera (0 where alpha is 0)
    distortion: Tensor  # [H, W] 2DGS depth distortion


class Rasterizer(Protocol):
    def __call__(
        self,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        features: Tensor,
        cam_from_world: Tensor,
        K: Tensor,
        width: int,
        height: int,
        near: float,
        window: Window,
    ) -> RasterOutput: ...


@dataclass(frozen=True)
class Camera:
    """A view's camera as tensors on the training device."""

    K: Tensor  # [3, 3]
    cam_from_world: Tensor  # [4, 4]
    width: int
    height: int

    @property
    def centre(self) -> Tensor:  # [3]
        R, t = self.cam_from_world[:3, :3], self.cam_from_world[:3, 3]
        return -(R.T @ t)


@dataclass(frozen=True)
class ShadingOptions:
    refl_threshold: float
    """R is evaluated only where the rendered reflectivity exceeds this"""
    bounds_lo: Tensor  # [3] facade bounds, for normalising X_r to [-1, 1]
    bounds_hi: Tensor  # [3]
    normal_grad: bool = True
    """the specular term's gradient reaches the rendered normal (through w_r and F); False: the normal is
    a constant there and only the colour's other terms and the normal losses move it"""
    supersample: int = 1
    """sub-pixel samples per pixel side: each pixel is the mean of supersample^2 shaded samples on a
    regular grid, as a camera pixel integrates over its area (1: one sample at the pixel centre)"""
    compiled: bool = False
    """the per-splat colours and the shading after the rasterizer run as ``torch.compile``'s fused kernels
    (``[run] compile``): the same maps to float rounding, R evaluated at every pixel and kept where chosen"""


@dataclass
class Render:
    """A shaded window: the image and the maps the losses and the evaluation need."""

    rgb: Tensor  # [H, W, 3] Eq. 7
    diffuse: Tensor  # [H, W, 3] D
    refl: Tensor  # [H, W]
    fresnel: Tensor  # [H, W, 3] F (Eq. 8)
    specular: Tensor  # [H, W, 3] R (0 where not evaluated)
    spec_pixels: Tensor  # [H, W] bool: where R was evaluated
    skipped: Tensor  # [H, W] bool: reflective pixels left out of this iteration's subsample
    normal: Tensor  # [H, W, 3]
    depth: Tensor  # [H, W]
    alpha: Tensor  # [H, W]
    distortion: Tensor  # [H, W]
    points: Tensor  # [H, W, 3] X_r
    n_features: int = 7


def splatting_rasterizer(backend: str, lowpass_sigma_px: float = LOWPASS_SIGMA_PX) -> Rasterizer:
    """The pipeline's rasterizer (``facade_pipeline.splatting.render_2dgs``) with the given backend and
    low-pass sigma (px), as a ``Rasterizer``. Its expected depth (alpha-normalised, camera z) is the depth
    used for X_r."""
    from facade_pipeline.splatting import PixelWindow, render_2dgs

    def rasterize(
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        features: Tensor,
        cam_from_world: Tensor,
        K: Tensor,
        width: int,
        height: int,
        near: float,
        window: Window,
    ) -> RasterOutput:
        out = render_2dgs(
            means,
            quats,
            scales,
            opacities,
            features,
            cam_from_world,
            K,
            width,
            height,
            near=near,
            backend=backend,
            crop=PixelWindow(*window),
            lowpass_sigma_px=lowpass_sigma_px,
        )
        return RasterOutput(out.features, out.alpha, out.depth_expected, out.normal, out.distortion)

    return rasterize


def training_backend(backend: str, device_type: str, lowpass_sigma_px: float, gsplat_installed: bool) -> str:
    """The backend ``[run] raster_backend`` trains with on a ``device_type`` device. On CUDA "auto" is gsplat
    where it is installed; gsplat has 2DGS's low-pass sigma built in, and rendering another one with the
    exact torch backend instead is 30-170 times slower (benchmarks/RESULTS.md, GPU), so "auto" refuses it
    rather than training at CPU speed on a GPU: the torch backend is there for it by name. Without gsplat
    "auto" stays the torch backend, which ``render_2dgs`` warns about. Pure: the choice is tested without
    CUDA."""
    if device_type != "cuda" or backend != "auto" or not gsplat_installed:
        return backend
    if not is_reference_lowpass(lowpass_sigma_px):
        raise ConfigError(
            None,
            f"train_gs.lowpass_sigma_px = {LOWPASS_SIGMA_PX:.4f} (the only sigma gsplat renders) on CUDA "
            'with [run] raster_backend = "auto"',
            f'{lowpass_sigma_px}: set 0.7071, or raster_backend = "torch" to train with the exact torch '
            "backend (30-170 times slower)",
        )
    return "gsplat"


def training_rasterizer(backend: str, lowpass_sigma_px: float, device: torch.device) -> Rasterizer:
    """The rasterizer a training run on ``device`` renders with (``training_backend``'s choice)."""
    from facade_pipeline.splatting import gsplat_backend

    chosen = training_backend(backend, device.type, lowpass_sigma_px, gsplat_backend.available())
    return splatting_rasterizer(chosen, lowpass_sigma_px)


def splat_features(model: GaussianModel, centre: Tensor, sh_degree: int) -> Tensor:  # -> [N, 7]
    """Per-splat channels blended by the rasterizer: D (SH evaluated toward the camera), r, F0."""
    dirs = deferred.safe_normalize(model.means - centre)
    diffuse = eval_sh(sh_degree, model.sh_coeffs(), dirs)
    return torch.cat([diffuse, model.reflectivity().unsqueeze(-1), model.f0()], dim=-1)


def render_view(
    model: GaussianModel,
    reflection: nn.Module | None,
    camera: Camera,
    window: Window,
    rasterize: Rasterizer,
    near: float,
    sh_degree: int,
    shading: ShadingOptions,
    spec_mask: Tensor | None = None,  # [H, W] bool: where R may be evaluated (the facade mask)
    select: Callable[[Tensor], Tensor] | None = None,  # [P] bool candidates -> [P] bool chosen
    chunk: int = 0,
) -> Render:
    """Render ``window`` of a view and shade it (Eq. 7-9). ``reflection`` None means no specular term.
    ``select`` subsamples the reflective pixels (CPU training); ``chunk`` > 0 evaluates R in chunks.
    With ``shading.supersample`` s > 1 every map is the mean over s x s sub-pixel samples (``select``
    then picks sub-pixel samples, and a pixel is ``skipped`` when any of its samples is)."""
    if (s := shading.supersample) > 1:
        fine, fine_window, fine_mask = _sub_pixel_view(camera, window, spec_mask, s)
        one = replace(shading, supersample=1)
        r = render_view(model, reflection, fine, fine_window, rasterize, near, sh_degree, one, fine_mask,
                        select, chunk)  # fmt: skip
        return _block_mean(r, s)
    centre = camera.centre
    features_of = torch_compiled(splat_features, True) if shading.compiled else splat_features
    feats = features_of(model, centre, sh_degree)
    ras = rasterize(
        model.means,
        model.unit_quats(),
        model.scales(),
        model.opacities(),
        feats,
        camera.cam_from_world,
        camera.K,
        camera.width,
        camera.height,
        near,
        window,
    )
    candidates = ras.features[..., 3].detach() > shading.refl_threshold
    if spec_mask is not None:
        candidates = candidates & spec_mask
    if reflection is None:
        candidates = torch.zeros_like(candidates)
    chosen = candidates if select is None else select(candidates)
    if reflection is not None and gathers_chosen(ras.features.device) and not shading.compiled:
        maps = _shade_gathered(ras, camera, window, centre, chosen, reflection, shading, chunk)
    else:
        shade = torch_compiled(_shade_everywhere, None) if shading.compiled else _shade_everywhere
        maps = shade(
            ras.features,
            ras.normal,
            ras.depth,
            camera.K,
            camera.cam_from_world,
            centre,
            window,
            chosen,
            reflection,
            shading.normal_grad,
            shading.bounds_lo,
            shading.bounds_hi,
            chunk,
        )
    rgb, diffuse, refl, fresnel, specular, points = maps
    return Render(
        rgb,
        diffuse,
        refl,
        fresnel,
        specular,
        chosen,
        candidates & ~chosen,
        ras.normal,
        ras.depth,
        ras.alpha,
        ras.distortion,
        points,
    )


Maps = tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]  # rgb, diffuse, refl, fresnel, specular, points


def _geometry(
    features: Tensor,
    normal: Tensor,
    depth: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    centre: Tensor,
    window: Window,
    normal_grad: bool,
):
    """The rasterized maps split (D, r) with the Fresnel term F (Eq. 8), each pixel's surface point X_r,
    its direction to the camera and its unit normal (a constant where ``normal_grad`` is False)."""
    diffuse, refl, f0 = features[..., :3], features[..., 3], features[..., 4:7]
    _, rays = deferred.pixel_rays(K, cam_from_world, window)
    points = deferred.surface_points(centre, rays, depth)
    w_o = deferred.directions_to_camera(rays)
    n_unit = deferred.safe_normalize(normal)
    if not normal_grad:
        n_unit = n_unit.detach()
    fresnel = deferred.schlick_fresnel(f0, deferred.cos_theta(n_unit, w_o))
    return diffuse, refl, fresnel, points, w_o, n_unit


def _shade_gathered(
    ras: RasterOutput,
    camera: Camera,
    window: Window,
    centre: Tensor,
    chosen: Tensor,
    reflection: nn.Module,
    shading: ShadingOptions,
    chunk: int,
) -> Maps:
    """Eq. 7-9 with R evaluated at the chosen pixels only (gathered: reads how many there are)."""
    diffuse, refl, fresnel, points, w_o, n_unit = _geometry(
        ras.features,
        ras.normal,
        ras.depth,
        camera.K,
        camera.cam_from_world,
        centre,
        window,
        shading.normal_grad,
    )
    specular = torch.zeros_like(diffuse)
    if bool(chosen.any()):
        w_r = deferred.reflect(w_o[chosen], n_unit[chosen])
        x = deferred.normalize_to_bounds(points[chosen], shading.bounds_lo, shading.bounds_hi)
        specular = specular.index_put((chosen,), _eval_chunked(reflection, x, w_r, chunk))
    return deferred.composite(diffuse, refl, fresnel, specular), diffuse, refl, fresnel, specular, points


def _shade_everywhere(
    features: Tensor,
    normal: Tensor,
    depth: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    centre: Tensor,
    window: Window,
    chosen: Tensor,
    reflection: nn.Module | None,
    normal_grad: bool,
    bounds_lo: Tensor,
    bounds_hi: Tensor,
    chunk: int,
) -> Maps:
    """Eq. 7-9 with R at every pixel, kept where chosen (the others get neither R nor a gradient, and finite
    inputs, so that no NaN reaches the gradients through them): shapes that do not depend on the values, so
    that nothing waits for the device and ``torch.compile`` can fuse it. Tensors and flags only."""
    diffuse, refl, fresnel, points, w_o, n_unit = _geometry(
        features, normal, depth, K, cam_from_world, centre, window, normal_grad
    )
    specular = torch.zeros_like(diffuse)
    if reflection is None:
        return diffuse, diffuse, refl, fresnel, specular, points
    c = chosen.unsqueeze(-1)
    w_r = torch.where(c, deferred.reflect(w_o, n_unit), w_o)
    x = deferred.normalize_to_bounds(torch.where(c, points, 0.0), bounds_lo, bounds_hi)
    all_r = _eval_chunked(reflection, x.reshape(-1, 3), w_r.reshape(-1, 3), chunk).view_as(diffuse)
    specular = torch.where(c, all_r, specular)
    return deferred.composite(diffuse, refl, fresnel, specular), diffuse, refl, fresnel, specular, points


def gathers_chosen(device: torch.device) -> bool:
    """Whether R is evaluated at the chosen pixels only (gathered), else at every pixel and masked. Gathering
    reads how many pixels are chosen: free on the CPU, where it saves evaluating R at the others; on a GPU
    a wait for the device in every step, where evaluating R everywhere costs less."""
    return device.type == "cpu"


def _sub_pixel_view(
    camera: Camera, window: Window, spec_mask: Tensor | None, s: int
) -> tuple[Camera, Window, Tensor | None]:
    """The camera, window and mask of s x s samples per pixel: a camera with s times the resolution,
    whose pixel centre j + 0.5 lands at (j + 0.5) / s of a pixel."""
    K = camera.K.clone()
    K[:2] = K[:2] * s
    x0, y0, w, h = window
    mask = None if spec_mask is None else spec_mask.repeat_interleave(s, 0).repeat_interleave(s, 1)
    fine = Camera(K, camera.cam_from_world, camera.width * s, camera.height * s)
    return fine, (x0 * s, y0 * s, w * s, h * s), mask


def _block_mean(r: Render, s: int) -> Render:
    """A render of s x s samples per pixel, each map averaged over its s x s blocks (masks: any sample)."""
    h, w = r.rgb.shape[0] // s, r.rgb.shape[1] // s

    def mean(t: Tensor) -> Tensor:  # [H s, W s, ...] -> [H, W, ...]
        return t.reshape(h, s, w, s, *t.shape[2:]).mean(dim=(1, 3))

    def any_(t: Tensor) -> Tensor:
        return t.reshape(h, s, w, s).any(dim=3).any(dim=1)

    return Render(
        mean(r.rgb),
        mean(r.diffuse),
        mean(r.refl),
        mean(r.fresnel),
        mean(r.specular),
        any_(r.spec_pixels),
        any_(r.skipped),
        mean(r.normal),
        mean(r.depth),
        mean(r.alpha),
        mean(r.distortion),
        mean(r.points),
        r.n_features,
    )


def _eval_chunked(module: nn.Module, x: Tensor, w: Tensor, chunk: int) -> Tensor:  # [P, 3], [P, 3] -> [P, 3]
    if chunk <= 0 or x.shape[0] <= chunk:
        return module(x, w)
    return torch.cat([module(x[i : i + chunk], w[i : i + chunk]) for i in range(0, x.shape[0], chunk)])


def random_subset(candidates: Tensor, max_count: int, generator: torch.Generator) -> Tensor:  # [H, W] bool
    """At most ``max_count`` of the True pixels of ``candidates``, uniformly at random (0: all of them). A
    cap reads the candidates' count from the device (a wait on a GPU, where whole images leave it at 0)."""
    if max_count <= 0:
        return candidates
    idx = candidates.flatten().nonzero().squeeze(-1)
    if max_count <= 0 or idx.numel() <= max_count:
        return candidates
    perm = torch.randperm(idx.numel(), generator=generator, device="cpu")[:max_count].to(idx.device)
    out = torch.zeros(candidates.numel(), dtype=torch.bool, device=candidates.device)
    out[idx[perm]] = True
    return out.view_as(candidates)
