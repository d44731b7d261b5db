"""Load a trained model (the ``train_gs`` hand-off: Gaussians PLY + reflection weights) and render whole
views with it, on top of the training package's public API (``read_ply``/``model_from_ply``,
``build_reflection_module``, ``render_view``, ``splatting_rasterizer``).

Where a trained model lies and what produced it is ``training.trained.TrainedModelFiles`` (the pipeline's
``07_train/`` or a variant under ``variants/<name>/``); ``load_trained`` reads it into a ``TrainedModel``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.shading.reflection import (
    ReflectionModel,
    build_reflection_module,
    strategy_from_record,
)
from facade_pipeline.splatting.types import LOWPASS_SIGMA_PX
from facade_pipeline.training.corrections import Alignment, align_view
from facade_pipeline.training.data import block_reduce, pixel_budget_factor, scaled_camera
from facade_pipeline.training.model import GaussianModel
from facade_pipeline.training.params import REFL_THRESHOLD, AlignParams, near_plane
from facade_pipeline.training.ply import model_from_ply, read_ply
from facade_pipeline.training.render import (
    Camera,
    Render,
    ShadingOptions,
    render_view,
    splatting_rasterizer,
)
from facade_pipeline.training.schedule import active_sh_degree
from facade_pipeline.training.trained import TrainedModelFiles
from facade_pipeline.training.trainer import Trainer

#: reflective pixels shaded per call of the reflection module (bounds memory on large views)
RENDER_CHUNK = 65536


@dataclass
class TrainedModel:
    """A model ready to render: Gaussians, the reflection module (None for SH only) and shading options."""

    name: str
    model: GaussianModel
    reflection: nn.Module | None
    reflection_model: ReflectionModel
    shading: ShadingOptions
    sh_degree: int
    near_m: float
    backend: str
    lowpass_sigma_px: float
    """the renderer's low-pass sigma the model was trained with (px)"""
    device: torch.device
    mask_by_facade: bool
    """the specular term only on the facade mask, as training did"""


@dataclass(frozen=True)
class RenderedView:
    """One rendered view in numpy: colour [H, W, 3] in [0, 1], world normals [H, W, 3], opacity [H, W]."""

    rgb: np.ndarray
    normal: np.ndarray
    alpha: np.ndarray


def load_trained(
    variant: TrainedModelFiles, device: str | torch.device = "cpu", backend: str = "auto"
) -> TrainedModel:
    """Read a variant's PLY and reflection weights, to render with the rasterizer ``backend`` (a run
    setting, ``run.raster_backend``). A damaged file raises ``InputError`` naming it."""
    device = torch.device(device)
    model = model_from_ply(read_ply(variant.ply), device)
    try:
        refl = torch.load(variant.reflection, map_location="cpu", weights_only=True)
        name, config, bounds = refl["model"], refl["config"], refl["bounds"]
    except Exception as e:  # torch raises several types for truncated or foreign files
        found = f"an unreadable file ({type(e).__name__}: {e})"
        raise InputError(variant.reflection, "train_gs reflection weights", found) from None
    strategy = strategy_from_record(name, config, variant.reflection)
    lo, hi = (torch.as_tensor(np.asarray(b), dtype=torch.float32, device=device) for b in bounds)
    try:
        module = build_reflection_module(strategy, device, (lo, hi))
    except ValueError as e:
        raise InputError(variant.reflection, f"what a {strategy} is built from", str(e)) from None
    if module is not None:
        try:
            module.load_state_dict(refl["state_dict"])
        except RuntimeError as e:
            raise InputError(variant.reflection, f"weights of a {strategy}", str(e).splitlines()[0]) from None
        module.eval()
    p = variant.params
    refl_threshold = float(p.get("refl_threshold", REFL_THRESHOLD))  # a key when older models were saved
    shading = ShadingOptions(refl_threshold, lo, hi, supersample=int(p.get("supersample", 1)))
    lowpass = float(p.get("lowpass_sigma_px", LOWPASS_SIGMA_PX))  # models saved before the key: 2DGS's
    return TrainedModel(
        variant.name,
        model,
        module,
        strategy,
        shading,
        active_sh_degree(int(p["sh_degree"]), int(p["sh_degree_interval"]), int(p["iterations"])),
        float(p.get("near_m", near_plane(bounds))),  # a key when older models were saved
        backend,
        lowpass,
        device,
        bool(p.get("mask_by_facade", True)),
    )


def from_trainer(tr: Trainer, name: str, backend: str = "auto") -> TrainedModel:
    """A model being trained (``training.trainer.Trainer``), ready to render as if it had been saved."""
    p = tr.params
    return TrainedModel(
        name,
        tr.state.model,
        tr.state.reflection,
        p.reflection_strategy(tr.data.bounds),
        tr.shading,
        active_sh_degree(p.sh_degree, p.sh_degree_interval, tr.state.iteration),
        tr.near,
        backend,
        p.lowpass_sigma_px,
        tr.device,
        p.mask_by_facade,
    )


def _torch_camera(tm: TrainedModel, camera: PinholeCamera) -> Camera:
    f32 = {"dtype": torch.float32, "device": tm.device}
    return Camera(
        torch.as_tensor(camera.K, **f32),
        torch.as_tensor(camera.cam_from_world, **f32),
        camera.width,
        camera.height,
    )


def _spec_mask(tm: TrainedModel, facade_mask: np.ndarray | None) -> torch.Tensor | None:
    if facade_mask is None or not tm.mask_by_facade:
        return None
    return torch.as_tensor(np.asarray(facade_mask, bool), device=tm.device)


def _render(tm: TrainedModel, cam: Camera, spec: torch.Tensor | None) -> Render:
    return render_view(
        tm.model,
        tm.reflection,
        cam,
        (0, 0, cam.width, cam.height),
        splatting_rasterizer(tm.backend, tm.lowpass_sigma_px),
        tm.near_m,
        tm.sh_degree,
        tm.shading,
        spec_mask=spec,
        chunk=RENDER_CHUNK,
    )


@torch.no_grad()
def render_trained(tm: TrainedModel, camera: PinholeCamera, facade_mask: np.ndarray | None) -> RenderedView:
    """Render a whole view (Eq. 7-9). ``facade_mask`` [H, W] bool limits the specular term to the facade,
    as in training when ``mask_by_facade`` is set; None evaluates it wherever the reflectivity allows."""
    r = _render(tm, _torch_camera(tm, camera), _spec_mask(tm, facade_mask))
    return RenderedView(r.rgb.clamp(0, 1).cpu().numpy(), r.normal.cpu().numpy(), r.alpha.cpu().numpy())


@torch.no_grad()
def render_maps(tm: TrainedModel, camera: PinholeCamera, facade_mask: np.ndarray | None) -> Render:
    """The whole view with every map behind its colour (diffuse, specular, reflectivity, normals, depth):
    ``render_trained`` before it keeps the colour alone."""
    return _render(tm, _torch_camera(tm, camera), _spec_mask(tm, facade_mask))


@dataclass(frozen=True)
class AlignedView:
    """A view aligned to a model (``align_trained``): its fitted camera, the fit (gain per channel and what
    it changed), and the render from that camera with that gain."""

    camera: PinholeCamera
    alignment: Alignment
    render: RenderedView


def align_trained(
    tm: TrainedModel, camera: PinholeCamera, image: np.ndarray, facade_mask: np.ndarray, params: AlignParams
) -> AlignedView:
    """Fit the view's pose (and exposure gain) to ``image`` [H, W, 3] in [0, 1] over ``facade_mask`` with
    the model frozen (``training.corrections.align_view``; on the image reduced to ``params.max_pixels``),
    then render it so at its size."""
    f = pixel_budget_factor(camera.width, camera.height, params.max_pixels)
    fit_mask = block_reduce(np.asarray(facade_mask, np.float32), f) >= 0.5 if f > 1 else facade_mask
    cam = _torch_camera(tm, scaled_camera(camera, f))
    spec = _spec_mask(tm, fit_mask)
    frozen = [*tm.model.params().values(), *([] if tm.reflection is None else tm.reflection.parameters())]
    fit = align_view(
        lambda M: _render(tm, Camera(cam.K, M, cam.width, cam.height), spec).rgb,
        cam.cam_from_world,
        torch.as_tensor(block_reduce(image, f), dtype=torch.float32, device=tm.device),
        torch.as_tensor(np.asarray(fit_mask, bool), device=tm.device),
        params,
        frozen=frozen,
    )
    aligned = PinholeCamera(camera.K, fit.cam_from_world.double().cpu().numpy(), camera.width, camera.height)
    spec = _spec_mask(tm, facade_mask)
    with torch.no_grad():
        r = _render(tm, _torch_camera(tm, aligned), spec)
    # the gain scales the render before it is clipped to [0, 1], as an exposure scales light on a sensor
    rgb = (r.rgb * fit.gain).clamp(0, 1)
    maps = (t.cpu().numpy() for t in (rgb, r.normal, r.alpha))
    return AlignedView(aligned, fit, RenderedView(*maps))
