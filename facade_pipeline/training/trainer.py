"""The trainer: ``build_trainer``, ``step``, ``evaluate``, ``save_checkpoint`` / ``load_checkpoint`` and
``train`` (the loop that ties them together with checkpoints and a progress callback).

Losses (Eq. 13): L = L_c + lambda_n L_n + lambda_np L_np + lambda_hf L_hf (+ lambda_d L_d), with L_c = 0.8 L1
+ 0.2 D-SSIM, the 2DGS normal consistency L_n, the normal prior L_np (Eq. 11) and the high-frequency loss
L_hf (Eq. 12), all over the facade mask. Every random draw comes from one ``torch.Generator`` that is saved
in checkpoints, so a resumed run equals an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import io
import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from facade_pipeline.errors import PipelineError
from facade_pipeline.evaluation import metrics
from facade_pipeline.evaluation.errors import EmptyMaskError
from facade_pipeline.io.atomic import write_bytes
from facade_pipeline.shading.reflection import build_reflection_module
from facade_pipeline.training import losses
from facade_pipeline.training.corrections import (
    AlignParams,
    ViewCorrections,
    align_view,
)
from facade_pipeline.training.data import TrainData, TrainView
from facade_pipeline.training.densify import (
    DensifyStats,
    accumulate,
    densify_and_prune,
    reset_opacity,
    view_space_grad,
)
from facade_pipeline.training.exposure import ExposureEstimate, estimate_exposures
from facade_pipeline.training.init import initial_model
from facade_pipeline.training.model import PARAM_NAMES, GaussianModel
from facade_pipeline.training.params import TrainParams
from facade_pipeline.training.render import (
    Camera,
    Rasterizer,
    Render,
    ShadingOptions,
    Window,
    random_subset,
    render_view,
)
from facade_pipeline.training.schedule import at_fraction, exp_decay, step_schedule

log = logging.getLogger(__name__)
CHECKPOINT_FORMAT = 2
EVAL_CHUNK = 65536
#: Pixels nearer than this to the edge of a view's glass mask are left out of ``psnr_glass_interior``.
INTERIOR_MARGIN_PX = 2


class TrainingDivergedError(PipelineError):
    """The optimisation produced NaN/Inf or splats flew off (an exploding learning rate, say)."""


@dataclass
class Trainer:
    """Everything that changes during training, and what it is trained on."""

    params: TrainParams
    data: TrainData
    device: torch.device
    rasterize: Rasterizer
    model: GaussianModel
    reflection: nn.Module | None
    opt: torch.optim.Adam
    opt_refl: torch.optim.Adam | None
    generator: torch.Generator
    stats: DensifyStats
    shading: ShadingOptions
    cameras: list[Camera]
    iteration: int = 0
    log: list[dict[str, Any]] = field(default_factory=list)
    corrections: ViewCorrections | None = None
    """per-view pose and exposure corrections (``pose_refinement``, ``exposure_refinement``), else None"""
    opt_corrections: torch.optim.Adam | None = None
    exposure: ExposureEstimate | None = None
    """per-view gains estimated from the photos before training (``exposure_estimate``), else None"""

    @property
    def extent(self) -> float:
        return self.data.extent


def resolve_device(choice: str) -> torch.device:
    """``cpu``, ``cuda`` (an error without CUDA) or ``auto`` (CUDA when available)."""
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if choice == "cuda" and not torch.cuda.is_available():
        raise PipelineError(None, 'a CUDA device (run.device = "cuda")', 'none; use "cpu" or "auto"')
    return torch.device(choice)


def _gaussian_optimizer(model: GaussianModel, p: TrainParams, extent: float) -> torch.optim.Adam:
    lr = p.lr
    rates = {
        "means": lr.position_init * extent,
        "quats": lr.rotation,
        "log_scales": lr.scaling,
        "opacity_logits": lr.opacity,
        "sh_dc": lr.sh_dc,
        "sh_rest": lr.sh_rest,
        "refl_logits": lr.reflectivity,
        "f0_logits": lr.f0,
    }
    groups = [{"params": [getattr(model, n)], "lr": rates[n], "name": n} for n in PARAM_NAMES]
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15)


def _build_parts(p: TrainParams, data: TrainData, device: torch.device, model: GaussianModel):
    lo, hi = data.bounds
    f32 = dict(dtype=torch.float32, device=device)
    if p.supersample < 1:
        raise PipelineError(None, "train_gs.supersample of at least 1", str(p.supersample))
    shading = ShadingOptions(
        p.refl_threshold,
        torch.as_tensor(lo, **f32),
        torch.as_tensor(hi, **f32),
        p.reflection_normal_grad,
        p.supersample,
    )
    with torch.random.fork_rng(devices=[]):  # the module's initial weights come from the seed alone
        torch.manual_seed(p.seed)
        reflection = build_reflection_module(
            p.reflection(),
            device,
            (shading.bounds_lo, shading.bounds_hi),
            reflection_mesh(data),
            data.init.points,
        )
    opt = _gaussian_optimizer(model, p, data.extent)
    opt_refl = None if reflection is None else _reflection_optimizer(p, reflection)
    cameras = [
        Camera(
            torch.as_tensor(v.camera.K, **f32),
            torch.as_tensor(v.camera.cam_from_world, **f32),
            v.camera.width,
            v.camera.height,
        )
        for v in data.views
    ]
    return reflection, opt, opt_refl, shading, cameras


def reflection_mesh(data: TrainData) -> tuple[Tensor, Tensor, Tensor | None]:
    """The corrected mesh an MLP with self hits casts against: vertices [V, 3] (m), triangles [T, 3] and
    glass labels [T] bool (None: unknown)."""
    m = data.init
    return (
        torch.as_tensor(m.mesh_vertices, dtype=torch.float32),
        torch.as_tensor(m.mesh_triangles, dtype=torch.int64),
        None if m.mesh_glass is None else torch.as_tensor(m.mesh_glass, dtype=torch.bool),
    )


def _build_corrections(
    p: TrainParams, n_views: int, device: torch.device
) -> tuple[ViewCorrections | None, torch.optim.Adam | None]:
    if not (p.pose_refinement or p.exposure_refinement):
        return None, None
    corr = ViewCorrections(n_views, device, pose=p.pose_refinement, exposure=p.exposure_refinement)
    return corr, corr.optimizer(p.lr.pose_rotation, p.lr.pose_translation, p.lr.exposure)


def _estimate_exposure(p: TrainParams, data: TrainData) -> ExposureEstimate | None:
    if not p.exposure_estimate:
        return None
    m = data.init
    est = estimate_exposures(
        data.views, m.mesh_vertices, m.mesh_triangles, m.mesh_glass, data.train_idx, p.exposure, p.seed
    )
    few = [data.views[i].stem for i in data.train_idx if est.samples[i] < p.exposure.min_samples]
    if few:
        shown = ", ".join(few[:5]) + (f" and {len(few) - 5} more" if len(few) > 5 else "")
        log.warning(
            "exposure estimate: %d of %d training views have fewer than %d usable samples of the facade's "
            "opaque parts (non-glass points of the corrected mesh inside their facade mask) (%s); their gain "
            "stays 1. Expected where the mesh covers little of a view; if their exposure differs, lower "
            "[train_gs.exposure] min_samples",
            len(few), len(data.train_idx), p.exposure.min_samples, shown,
        )  # fmt: skip
    return est


def exposure_gain(tr: Trainer, index: int) -> Tensor | None:
    """View ``index``'s exposure gain per colour channel [3]: the estimate (``exposure_estimate``) times
    the learnt correction (``exposure_refinement``), each relative to the training views' geometric mean,
    so that the splats keep the mean exposure and the gains have no common factor to trade with the
    colours; None for held-out views and when neither is on."""
    if index not in tr.data.train_idx:
        return None
    log_gain = None
    if tr.exposure is not None:
        log_gain = torch.as_tensor(tr.exposure.log_gain[index], device=tr.device)
    if tr.corrections is not None and tr.corrections.log_gain is not None:
        g = tr.corrections.log_gain
        learnt = g[index] - g[list(tr.data.train_idx)].mean(0)
        log_gain = learnt if log_gain is None else log_gain + learnt
    return None if log_gain is None else log_gain.exp()


@torch.no_grad()
def exposure_gains(tr: Trainer) -> dict[str, list[float]]:
    """Each training view's exposure gain per colour channel as trained (stem -> [r, g, b]); empty when
    training assumed one exposure for all views."""
    out = {}
    for i in tr.data.train_idx:
        gain = exposure_gain(tr, i)
        if gain is not None:
            out[tr.data.views[i].stem] = [round(float(x), 5) for x in gain]
    return out


def camera(tr: Trainer, index: int) -> Camera:
    """View ``index``'s camera as training sees it: with its pose correction when poses are refined."""
    cam = tr.cameras[index]
    if tr.corrections is None:
        return cam
    return Camera(cam.K, tr.corrections.cam_from_world(index, cam.cam_from_world), cam.width, cam.height)


def build_trainer(
    p: TrainParams, data: TrainData, rasterize: Rasterizer, device: torch.device | str = "cpu"
) -> Trainer:
    """A trainer at iteration 0: the initial Gaussians (section 3.2), the reflection module, optimisers."""
    if not data.train_idx:
        raise PipelineError(None, "at least one training view", "none")
    device = torch.device(device)
    model = initial_model(
        data.init,
        data.bounds,
        p.init_max_points,
        p.init_mesh_samples,
        p.init_bounds_margin_m,
        p.init_knn,
        p.init_opacity,
        p.init_reflectivity,
        p.init_reflectivity_glass,
        p.init_f0,
        p.sh_degree,
        p.seed,
        device,
    )
    reflection, opt, opt_refl, shading, cameras = _build_parts(p, data, device, model)
    gen = torch.Generator(device="cpu")
    gen.manual_seed(p.seed)
    corrections, opt_corrections = _build_corrections(p, len(data.views), device)
    return Trainer(
        p,
        data,
        device,
        rasterize,
        model,
        reflection,
        opt,
        opt_refl,
        gen,
        DensifyStats.zeros(model.n, device),
        shading,
        cameras,
        corrections=corrections,
        opt_corrections=opt_corrections,
        exposure=_estimate_exposure(p, data),
    )


def active_sh_degree(p: TrainParams, iteration: int) -> int:
    """The SH degree in use: one more band every ``sh_degree_interval`` iterations (3DGS), up to the max."""
    if p.sh_degree_interval <= 0:
        return p.sh_degree
    return min(p.sh_degree, iteration // p.sh_degree_interval)


def _randint(gen: torch.Generator, high: int) -> int:
    return int(torch.randint(high, (1,), generator=gen))


def _window(tr: Trainer, index: int) -> Window:
    """The whole image, or a random patch of ``patch_px`` centred on a random facade pixel (patches off the
    facade would teach nothing when the loss is masked by it)."""
    cam, p = tr.cameras[index], tr.params.patch_px
    if p <= 0 or (p >= cam.width and p >= cam.height):
        return (0, 0, cam.width, cam.height)
    pw, ph = min(p, cam.width), min(p, cam.height)
    mask = tr.data.views[index].facade_mask
    ys, xs = np.nonzero(mask) if tr.params.mask_by_facade else (np.zeros(0), np.zeros(0))
    if len(xs) == 0:
        return (
            _randint(tr.generator, cam.width - pw + 1),
            _randint(tr.generator, cam.height - ph + 1),
            pw,
            ph,
        )
    k = _randint(tr.generator, len(xs))
    x0 = int(np.clip(xs[k] - pw // 2, 0, cam.width - pw))
    y0 = int(np.clip(ys[k] - ph // 2, 0, cam.height - ph))
    return (x0, y0, pw, ph)


@dataclass
class ViewTensors:
    """A window of a view's data on the device."""

    image: Tensor  # [H, W, 3]
    mask: Tensor  # [H, W] bool: facade mask (all True when not masking)
    glass: Tensor  # [H, W] bool
    prior: Tensor  # [H, W, 3]
    prior_valid: Tensor  # [H, W] bool


def view_tensors(view: TrainView, window: Window, mask_by_facade: bool, device: torch.device) -> ViewTensors:
    x0, y0, w, h = window
    sl = (slice(y0, y0 + h), slice(x0, x0 + w))

    def t(a: np.ndarray, dtype=torch.float32) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(a[sl]), dtype=dtype, device=device)

    mask = (
        t(view.facade_mask, torch.bool)
        if mask_by_facade
        else torch.ones(h, w, dtype=torch.bool, device=device)
    )
    return ViewTensors(
        t(view.image),
        mask,
        t(view.glass_mask, torch.bool),
        t(view.normal_prior),
        t(view.normal_valid, torch.bool),
    )


def _set_learning_rates(tr: Trainer) -> None:
    p, it = tr.params, tr.iteration
    for g in tr.opt.param_groups:
        if g["name"] == "means":
            g["lr"] = exp_decay(
                p.lr.position_init * tr.extent, p.lr.position_final * tr.extent, it, p.iterations
            )
    if tr.opt_refl is not None:
        for g in tr.opt_refl.param_groups:
            g["lr"] = _reflection_lr(p, it, g["name"])


def _reflection_optimizer(p: TrainParams, module: nn.Module) -> torch.optim.Adam:
    """Adam over the reflection module, one group per rate: the proxy feature maps (``proxy``) apart from
    the network's weights (``reflection``)."""
    proxy = [prm for name, prm in module.named_parameters() if name.startswith("proxy.")]
    rest = [prm for name, prm in module.named_parameters() if not name.startswith("proxy.")]
    groups = [{"params": rest, "name": "reflection"}]
    if proxy:
        groups.append({"params": proxy, "name": "proxy"})
    for g in groups:
        g["lr"] = _reflection_lr(p, 0, g["name"])
    return torch.optim.Adam(groups)


def _reflection_lr(p: TrainParams, it: int, group: str) -> float:
    """A reflection parameter group's rate at iteration ``it``: the MLP's decays; the environment map's and
    the proxy feature maps' are fixed."""
    if group == "proxy":
        return p.lr.proxy
    if p.reflection_model == "envmap":
        return p.lr.envmap
    return exp_decay(p.lr.reflection_init, p.lr.reflection_final, it, p.iterations)


def compute_losses(p: TrainParams, r: Render, vt: ViewTensors, iteration: int) -> dict[str, Tensor]:
    """The terms of Eq. 13 for one rendered window and the weighted total (key ``loss``)."""
    zero = r.rgb.new_zeros(())
    loss_mask = vt.mask & ~r.skipped
    terms = {"color": losses.color_loss(r.rgb, vt.image, loss_mask, p.lambda_dssim)}
    total = terms["color"]
    if p.lambda_normal > 0 and iteration >= at_fraction(p.normal_start_fraction, p.iterations):
        terms["normal"] = losses.normal_consistency_loss(r.normal, losses.depth_normals(r.points), loss_mask)
        total = total + p.lambda_normal * terms["normal"]
    if p.lambda_normal_prior > 0 and iteration >= at_fraction(p.normal_prior_start_fraction, p.iterations):
        terms["normal_prior"] = losses.normal_prior_loss(r.normal, vt.prior, vt.prior_valid & vt.mask)
        total = total + p.lambda_normal_prior * terms["normal_prior"]
    if iteration >= at_fraction(p.hf_start_fraction, p.iterations):
        tau = step_schedule(
            p.hf_tau_start, p.hf_tau_end, p.hf_steps, p.hf_start_fraction, iteration, p.iterations
        )
        lam = step_schedule(
            p.lambda_hf_start, p.lambda_hf_end, p.hf_steps, p.hf_start_fraction, iteration, p.iterations
        )
        if lam > 0:
            terms["hf"] = losses.high_frequency_loss(r.rgb, vt.image, loss_mask, tau, p.hf_eps, p.hf_residual)
            total = total + lam * terms["hf"]
    if p.lambda_distortion > 0 and iteration >= at_fraction(p.distortion_start_fraction, p.iterations):
        terms["distortion"] = losses.masked_mean(r.distortion, vt.mask)
        total = total + p.lambda_distortion * terms["distortion"]
    terms["loss"] = total + zero
    return terms


def _check_finite(tr: Trainer, what: str, tensors: dict[str, Tensor | None]) -> None:
    for name, t in tensors.items():
        if t is not None and not bool(torch.isfinite(t).all()):
            raise TrainingDivergedError(
                None,
                f"finite {what} at iteration {tr.iteration + 1}",
                f"NaN or Inf in '{name}' (learning rates too high? lower train_gs.lr.*)",
            )


def _check_extent(tr: Trainer) -> None:
    lo, hi = tr.shading.bounds_lo, tr.shading.bounds_hi
    centre = 0.5 * (lo + hi)
    far = float((tr.model.means.detach() - centre).norm(dim=-1).max()) if tr.model.n else 0.0
    limit = tr.params.divergence_extent_factor * tr.extent
    if far > limit:
        raise TrainingDivergedError(
            None,
            f"splats within {limit:.1f} m of the facade at iteration {tr.iteration + 1}",
            f"a splat {far:.3g} m away (exploding position learning rate? lower train_gs.lr.position_init)",
        )


def render_window(
    tr: Trainer, index: int, window: Window, select=None, chunk: int = 0, cam: Camera | None = None
) -> tuple[Render, ViewTensors]:
    """Render a window of view ``index`` with the current model (from its corrected pose, if poses are
    refined, and with its exposure gain, if exposures are); returns it with the view's data there. ``cam``
    replaces the view's camera."""
    cam = camera(tr, index) if cam is None else cam
    vt = view_tensors(tr.data.views[index], window, tr.params.mask_by_facade, tr.device)
    r = render_view(
        tr.model,
        tr.reflection,
        cam,
        window,
        tr.rasterize,
        tr.params.near_m,
        active_sh_degree(tr.params, tr.iteration),
        tr.shading,
        spec_mask=vt.mask,
        select=select,
        chunk=chunk,
    )
    gain = exposure_gain(tr, index)
    if gain is not None:
        r = dataclasses.replace(r, rgb=r.rgb * gain.to(r.rgb.dtype))
    return r, vt


def step(tr: Trainer) -> dict[str, float]:
    """One optimisation step on a random training view (or patch). Returns the loss terms and the PSNR of
    the window over its loss mask. Raises ``TrainingDivergedError`` on NaN/Inf or runaway splats."""
    p = tr.params
    _set_learning_rates(tr)
    index = tr.data.train_idx[_randint(tr.generator, len(tr.data.train_idx))]
    cam = tr.cameras[index]  # the imported pose: the view-space gradients for densification
    window = _window(tr, index)
    r, vt = render_window(
        tr, index, window, select=lambda c: random_subset(c, p.mlp_max_pixels, tr.generator)
    )
    terms = compute_losses(p, r, vt, tr.iteration)
    _check_finite(tr, "loss terms", terms)
    terms["loss"].backward()
    grads = {n: t.grad for n, t in tr.model.params().items()}
    if tr.corrections is not None:
        grads |= {f"view_{n}": t.grad for n, t in tr.corrections.named_parameters()}
    _check_finite(tr, "gradients", grads)
    densify_end = at_fraction(p.densify.end_fraction, p.iterations)
    if tr.iteration < densify_end and tr.model.means.grad is not None:
        g, vis = view_space_grad(
            tr.model.means,
            tr.model.means.grad,
            cam.cam_from_world,
            cam.K,
            (cam.width, cam.height),
            window,
            p.near_m,
        )
        accumulate(tr.stats, g, vis)
    for opt in (tr.opt, tr.opt_refl, tr.opt_corrections):
        if opt is not None:
            opt.step()
            opt.zero_grad(set_to_none=True)
    _check_finite(tr, "parameters", {n: t for n, t in tr.model.params().items()})
    _check_extent(tr)
    tr.iteration += 1
    _densify_if_due(tr)
    out = {k: float(v.detach()) for k, v in terms.items()}
    out["psnr"] = losses.psnr(r.rgb.detach().clamp(0, 1), vt.image, vt.mask & ~r.skipped)
    return out


def _densify_if_due(tr: Trainer) -> None:
    p, d, it = tr.params, tr.params.densify, tr.iteration
    if not at_fraction(d.start_fraction, p.iterations) < it <= at_fraction(d.end_fraction, p.iterations):
        return
    if d.interval > 0 and it % d.interval == 0:
        prune_big = d.opacity_reset_interval > 0 and it > d.opacity_reset_interval
        counts = densify_and_prune(tr.model, tr.opt, tr.stats, d, tr.extent, prune_big, tr.generator)
        tr.stats = DensifyStats.zeros(tr.model.n, tr.device)
        log.debug("iteration %d: densified %s -> %d splats", it, counts, tr.model.n)
    if d.opacity_reset_interval > 0 and it % d.opacity_reset_interval == 0:
        reset_opacity(tr.model, tr.opt, d.opacity_reset_value)


@torch.no_grad()
def evaluate(
    tr: Trainer, indices: tuple[int, ...] | list[int], align: AlignParams | None = None
) -> dict[str, Any]:
    """Render whole views and measure them: PSNR and SSIM over the facade mask, PSNR over glass and over
    its interior (``INTERIOR_MARGIN_PX`` from the mask's edge: the frames' edges left out), and the
    rendered normals' angle error (deg) on glass against the view's normal prior. Means over the views
    (a view without glass pixels is left out of the glass means). With ``align`` (and steps), each view
    is first aligned to the frozen model (``corrections.align_view``, over its facade mask) and measured
    as aligned; each view's entry then says what the alignment changed."""
    per_view = []
    for i in indices:
        cam = camera(tr, i)
        fit = None
        if align is None or align.steps <= 0:
            r, vt = render_window(tr, i, (0, 0, cam.width, cam.height), chunk=EVAL_CHUNK)
        else:
            full = (0, 0, cam.width, cam.height)  # the view's data alone: the fit renders it
            vt = view_tensors(tr.data.views[i], full, tr.params.mask_by_facade, tr.device)
            fit = align_view(
                lambda M, i=i, cam=cam: _render_posed(tr, i, cam, M).rgb,
                cam.cam_from_world,
                vt.image,
                vt.mask,
                align,
                frozen=[*tr.model.params().values(), *_module_params(tr.reflection)],
            )
            r = _render_posed(tr, i, cam, fit.cam_from_world)
            r = dataclasses.replace(r, rgb=r.rgb * fit.gain)
        rgb = r.rgb.clamp(0, 1)
        glass = vt.glass & vt.mask
        n = torch.nn.functional.normalize(r.normal, dim=-1)
        cos = (n * vt.prior).sum(-1).clamp(-1, 1)
        ok = glass & vt.prior_valid
        ang = torch.rad2deg(torch.arccos(cos[ok])) if bool(ok.any()) else None
        row = {
            "view": tr.data.views[i].stem,
            "psnr": losses.psnr(rgb, vt.image, vt.mask),
            "ssim": _masked_ssim(rgb, vt.image, vt.mask),
            "psnr_glass": losses.psnr(rgb, vt.image, glass),
            "psnr_glass_interior": _psnr_or_none(rgb, vt.image, erode(glass, INTERIOR_MARGIN_PX)),
            "normal_error_glass_deg": None if ang is None else float(ang.mean()),
        }
        if fit is not None:
            row |= fit.summary()
        per_view.append(row)
    return {"views": per_view, **_means(per_view)}


def _render_posed(tr: Trainer, index: int, cam: Camera, cam_from_world: Tensor) -> Render:
    """View ``index`` whole, seen from ``cam_from_world`` instead of its pose."""
    posed = Camera(cam.K, cam_from_world, cam.width, cam.height)
    return render_window(tr, index, (0, 0, cam.width, cam.height), chunk=EVAL_CHUNK, cam=posed)[0]


def _module_params(module: nn.Module | None) -> list[Tensor]:
    return [] if module is None else list(module.parameters())


def _psnr_or_none(rgb: Tensor, image: Tensor, mask: Tensor) -> float | None:
    """PSNR over ``mask``, None where it is empty (JSON has no NaN)."""
    return losses.psnr(rgb, image, mask) if bool(mask.any()) else None


def erode(mask: Tensor, px: int) -> Tensor:  # [H, W] bool -> [H, W] bool
    """``mask`` without the pixels within ``px`` (Chebyshev distance) of a pixel outside it or of the
    image border."""
    if px <= 0:
        return mask
    k = 2 * px + 1
    outside = (~mask).float()[None, None]
    near = torch.nn.functional.max_pool2d(outside, k, stride=1, padding=px)[0, 0] > 0
    border = torch.ones_like(mask)
    border[px:-px, px:-px] = False
    return mask & ~near & ~border


def _masked_ssim(rgb: Tensor, image: Tensor, mask: Tensor) -> float | None:
    """SSIM over the facade mask exactly as the evaluate stage reports it (statistics renormalised over
    the mask, so nothing outside it counts); None for a view with no facade pixel."""
    try:
        return metrics.ssim(rgb.cpu().numpy(), image.cpu().numpy(), mask.cpu().numpy(), border="renormalize")
    except EmptyMaskError:
        return None


def _means(per_view: list[dict[str, Any]]) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for key in ("psnr", "ssim", "psnr_glass", "psnr_glass_interior", "normal_error_glass_deg"):
        vals = [v[key] for v in per_view if v[key] is not None and math.isfinite(v[key])]
        out[key] = float(np.mean(vals)) if vals else None
    return out


def save_checkpoint(tr: Trainer, path: str | Path, fingerprint: str) -> None:
    """Everything needed to continue exactly, written atomically."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "fingerprint": fingerprint,
        "iteration": tr.iteration,
        "model": tr.model.state(),
        "opt": tr.opt.state_dict(),
        "reflection": None if tr.reflection is None else tr.reflection.state_dict(),
        "opt_refl": None if tr.opt_refl is None else tr.opt_refl.state_dict(),
        "corrections": None if tr.corrections is None else tr.corrections.state_dict(),
        "opt_corrections": None if tr.opt_corrections is None else tr.opt_corrections.state_dict(),
        "generator": tr.generator.get_state(),
        "stats": {"grad_accum": tr.stats.grad_accum, "count": tr.stats.count},
        "log": tr.log,
    }
    save_torch(path, state)


def save_torch(path: str | Path, obj: Any) -> None:
    """``torch.save`` atomically and reproducibly (through memory: torch names the archive after the file,
    and the temporary name is random)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    write_bytes(path, buf.getvalue())


def load_checkpoint(
    path: str | Path,
    p: TrainParams,
    data: TrainData,
    rasterize: Rasterizer,
    device: torch.device | str,
    fingerprint: str,
) -> Trainer | None:
    """The trainer saved at ``path``, or None when there is none or it belongs to other parameters or
    inputs (its fingerprint differs) or an older format. A damaged file is moved aside to
    ``<name>.bad`` (kept for a person to look at) and training starts afresh."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise TypeError(f"a {type(state).__name__}, not a dict")
    except Exception as e:  # torch raises several types for truncated or foreign files
        bad = path.with_name(path.name + ".bad")
        os.replace(path, bad)
        log.warning(
            "%s: unreadable checkpoint (%s: %s), moved to %s; training starts from iteration 0",
            path, type(e).__name__, str(e).splitlines()[0] if str(e) else "", bad.name,
        )  # fmt: skip
        return None
    if state.get("format") != CHECKPOINT_FORMAT or state.get("fingerprint") != fingerprint:
        log.warning(
            "%s: checkpoint of iteration %s was made with other parameters, inputs or code; "
            "training starts from iteration 0",
            path, state.get("iteration", "?"),
        )  # fmt: skip
        return None
    device = torch.device(device)
    model = GaussianModel.from_state(state["model"], device)
    reflection, opt, opt_refl, shading, cameras = _build_parts(p, data, device, model)
    opt.load_state_dict(state["opt"])
    if reflection is not None:
        reflection.load_state_dict(state["reflection"])
        opt_refl.load_state_dict(state["opt_refl"])
    corrections, opt_corrections = _build_corrections(p, len(data.views), device)
    if corrections is not None:
        corrections.load_state_dict(state["corrections"])
        opt_corrections.load_state_dict(state["opt_corrections"])
    gen = torch.Generator(device="cpu")
    gen.set_state(state["generator"])
    stats = DensifyStats(state["stats"]["grad_accum"].to(device), state["stats"]["count"].to(device))
    return Trainer(
        p,
        data,
        device,
        rasterize,
        model,
        reflection,
        opt,
        opt_refl,
        gen,
        stats,
        shading,
        cameras,
        state["iteration"],
        list(state["log"]),
        corrections,
        opt_corrections,
        _estimate_exposure(p, data),
    )


ProgressCallback = Callable[[int, int, dict[str, float]], None]


def train(
    tr: Trainer,
    checkpoint: Path | None = None,
    fingerprint: str = "",
    progress: ProgressCallback | None = None,
    stop_at: int | None = None,
    *,
    log_every: int = 0,
    checkpoint_every: int = 0,
) -> Trainer:
    """Step until ``params.iterations`` (or ``stop_at``), logging every ``log_every`` iterations (0: never)
    and saving a checkpoint every ``checkpoint_every`` (0: only at the end) when ``checkpoint`` is given.
    Both are run settings (``[run]``): they change how a run goes, never what it trains."""
    p = tr.params
    end = p.iterations if stop_at is None else min(stop_at, p.iterations)
    start = tr.iteration
    while tr.iteration < end:
        out = step(tr)
        if log_every > 0 and (tr.iteration % log_every == 0 or tr.iteration == p.iterations):
            tr.log.append(
                {
                    "iteration": tr.iteration,
                    "n_gaussians": tr.model.n,
                    **{k: (round(v, 6) if math.isfinite(v) else None) for k, v in out.items()},
                }
            )
        if checkpoint is not None and checkpoint_every > 0 and tr.iteration % checkpoint_every == 0:
            save_checkpoint(tr, checkpoint, fingerprint)
        if progress is not None:
            progress(tr.iteration, p.iterations, {**out, "n": tr.model.n})
    saved = checkpoint_every > 0 and tr.iteration % checkpoint_every == 0
    if checkpoint is not None and tr.iteration > start and not saved:
        save_checkpoint(tr, checkpoint, fingerprint)
    return tr
