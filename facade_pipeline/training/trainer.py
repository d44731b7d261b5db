"""The training loop: the ``Trainer`` (a run: its parameters, its data on the device and its ``TrainState``,
everything a step changes), ``build_trainer`` (at iteration 0) and ``load_checkpoint`` (from a checkpoint),
``step`` (one optimisation step: draw a window, render it, the losses, update, check for divergence,
densify when due) and ``train`` (steps with checkpoints and a progress callback).

What a step uses lives beside it: the window and data of a view (``training.batches``), the losses
(``training.losses``, Eq. 13), the optimisers and their rates (``training.optimizers``,
``training.schedule``) and the checkpoint file (``training.checkpoints``). Every random draw comes from one
``torch.Generator`` that is saved in checkpoints, so a resumed run equals an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from facade_pipeline.errors import PipelineError
from facade_pipeline.shading.reflection import build_reflection_module
from facade_pipeline.shading.surroundings import surroundings_points
from facade_pipeline.training.batches import (
    ViewTensors,
    camera,
    exposure_gain,
    random_int,
    random_window,
    view_tensors,
    views_on_device,
)
from facade_pipeline.training.checkpoints import TrainState, read_checkpoint, save_checkpoint
from facade_pipeline.training.compiling import torch_compiled
from facade_pipeline.training.corrections import ViewCorrections
from facade_pipeline.training.data import ExposureEstimate, TrainData
from facade_pipeline.training.densify import (
    OPACITY_RESET_VALUE,
    DensifyStats,
    accumulate,
    densify_and_prune,
    densify_window,
    last_opacity_reset,
    reset_opacity,
    view_space_grad,
)
from facade_pipeline.training.init import INIT_KNN, INIT_OPACITY, initial_model
from facade_pipeline.training.losses import compute_losses, psnr_tensor, recorded
from facade_pipeline.training.model import GaussianModel
from facade_pipeline.training.monitor import monitored
from facade_pipeline.training.optimizers import gaussian_optimizer, reflection_optimizer, set_learning_rates
from facade_pipeline.training.params import (
    INIT_BOUNDS_MARGIN,
    INIT_F0,
    REFL_THRESHOLD,
    TrainParams,
    facade_size,
    near_plane,
)
from facade_pipeline.training.render import (
    Camera,
    Rasterizer,
    Render,
    ShadingOptions,
    Window,
    random_subset,
    render_view,
)
from facade_pipeline.training.schedule import active_sh_degree

log = logging.getLogger(__name__)
#: A splat this many scene extents from the facade means the run diverged: a sanity bound, far beyond any
#: real splat (the surroundings are within a few extents).
DIVERGENCE_EXTENT_FACTOR = 100.0
#: Adam rates of the per-view pose corrections (``pose_refinement``, constant): rotation (rad) and
#: translation (times the scene extent, so that a 1:25 model's poses move as the building's). demo's steps
#: (1e-5 rad, 3e-4 m at its 70 m extent): rates 10x and 23x these, large enough to undo gcw_dev's motion-
#: capture error within 300 steps, cost demo 2.3 dB on held-out glass as imported (benchmarks/RESULTS.md,
#: "Pose refinement's rates on demo").
LR_POSE_ROTATION = 1e-5
LR_POSE_TRANSLATION = 4.3e-6


class TrainingDivergedError(PipelineError):
    """The optimisation produced NaN/Inf or splats flew off (an exploding learning rate, say)."""


@dataclass
class Trainer:
    """A training run: its parameters (``params``, the one config), what it trains on (``data``, with what
    a step reads of it moved to ``device`` once: ``views``, ``cameras``, ``gains``, ``shading``), its
    rasterizer, and ``state``, everything a step changes (what a checkpoint holds). Made one way:
    ``build_trainer`` at iteration 0, ``load_checkpoint`` from a checkpoint, both through ``_assemble``."""

    params: TrainParams
    data: TrainData
    device: torch.device
    rasterize: Rasterizer
    state: TrainState
    shading: ShadingOptions
    cameras: list[Camera]
    """every view's imported camera on the device"""
    views: tuple[ViewTensors, ...] = field(repr=False)
    """every view's data on the device (``batches.views_on_device``)"""
    exposure: ExposureEstimate | None
    """per-view gains estimated from the photos before training (``exposure_estimate``), else None"""
    gains: Tensor | None = field(repr=False)
    """[V, 3] the exposure gains on the device (``exposure``), else None"""

    @property
    def extent(self) -> float:
        return self.data.extent

    @property
    def near(self) -> float:
        return near_plane(self.data.bounds)


def resolve_device(choice: str) -> torch.device:
    """``cpu``, ``cuda`` (an error without CUDA) or ``auto`` (CUDA when available)."""
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if choice == "cuda" and not torch.cuda.is_available():
        raise PipelineError(None, 'a CUDA device (run.device = "cuda")', 'none; use "cpu" or "auto"')
    return torch.device(choice)


def _build_corrections(
    p: TrainParams, n_views: int, extent: float, device: torch.device
) -> tuple[ViewCorrections | None, torch.optim.Adam | None]:
    if not p.pose_refinement:
        return None, None
    corr = ViewCorrections(n_views, device, pose=True)
    return corr, corr.optimizer(LR_POSE_ROTATION, LR_POSE_TRANSLATION * extent, lr_exposure=0.0)


def _exposure(p: TrainParams, data: TrainData) -> ExposureEstimate | None:
    if not p.exposure_estimate:
        return None
    if data.exposure is None:
        raise PipelineError(
            None,
            "the views' exposure estimate in the training data (train_gs.exposure_estimate = true)",
            "none: build the data with training.exposure.with_exposure_estimate (a bundle written without "
            "it: write it again) or set exposure_estimate = false",
        )
    return data.exposure


def _assemble(
    p: TrainParams,
    data: TrainData,
    rasterize: Rasterizer,
    device: torch.device,
    model: GaussianModel,
    saved: dict[str, Any] | None = None,
    compile: bool = False,
) -> Trainer:
    """The one way a trainer is made: around ``model``, every other part new at iteration 0, or, given
    ``saved`` (a checkpoint's state, ``checkpoints.read_checkpoint``), as it was saved. ``compile``: a
    step's shading, losses and densification statistics through ``torch.compile`` (``[run] compile``)."""
    lo, hi = data.bounds
    f32 = dict(dtype=torch.float32, device=device)
    if p.supersample < 1:
        raise PipelineError(None, "train_gs.supersample of at least 1", str(p.supersample))
    shading = ShadingOptions(
        REFL_THRESHOLD,
        torch.as_tensor(lo, **f32),
        torch.as_tensor(hi, **f32),
        p.reflection_normal_grad,
        p.supersample,
        compile,
    )
    init = data.init
    # the proxy's surroundings from the coarse points, the reflections' virtual points mirrored back
    margin = INIT_BOUNDS_MARGIN * facade_size(data.bounds)
    points, _ = surroundings_points(init.points, init.mesh_vertices, init.mesh_triangles, init.mesh_glass,
                                    [v.camera for v in data.views], margin)
    with torch.random.fork_rng(devices=[]):  # the module's initial weights come from the seed alone
        torch.manual_seed(p.seed)
        reflection = build_reflection_module(
            p.reflection_strategy(data.bounds),
            device,
            (shading.bounds_lo, shading.bounds_hi),
            points,
        )
    opt = gaussian_optimizer(model, p, data.extent)
    opt_refl = None if reflection is None else reflection_optimizer(p, reflection)
    cameras = [
        Camera(
            torch.as_tensor(v.camera.K, **f32),
            torch.as_tensor(v.camera.cam_from_world, **f32),
            v.camera.width,
            v.camera.height,
        )
        for v in data.views
    ]
    corrections, opt_corrections = _build_corrections(p, len(data.views), data.extent, device)
    generator = torch.Generator(device="cpu")
    if saved is None:
        generator.manual_seed(p.seed)
        stats, iteration, log_ = DensifyStats.zeros(model.n, device), 0, []
    else:
        opt.load_state_dict(saved["opt"])
        if reflection is not None:
            reflection.load_state_dict(saved["reflection"])
            opt_refl.load_state_dict(saved["opt_refl"])
        if corrections is not None:
            corrections.load_state_dict(saved["corrections"])
            opt_corrections.load_state_dict(saved["opt_corrections"])
        generator.set_state(saved["generator"])
        stats = DensifyStats(saved["stats"]["grad_accum"].to(device), saved["stats"]["count"].to(device))
        iteration, log_ = saved["iteration"], list(saved["log"])
    exposure = _exposure(p, data)
    state = TrainState(model, reflection, corrections, opt, opt_refl, opt_corrections, generator, stats,
                       iteration, log_)  # fmt: skip
    return Trainer(
        params=p,
        data=data,
        device=device,
        rasterize=rasterize,
        state=state,
        shading=shading,
        cameras=cameras,
        views=views_on_device(data.views, p.mask_by_facade, device),
        exposure=exposure,
        gains=None if exposure is None else torch.as_tensor(exposure.log_gain, **f32).exp(),
    )


def build_trainer(
    p: TrainParams,
    data: TrainData,
    rasterize: Rasterizer,
    device: torch.device | str = "cpu",
    compile: bool = False,
) -> Trainer:
    """A trainer at iteration 0: the initial Gaussians (section 3.2), the reflection module, optimisers;
    ``compile`` as ``_assemble``'s."""
    if not data.train_idx:
        raise PipelineError(None, "at least one training view", "none")
    device = torch.device(device)
    model = initial_model(
        data.init,
        data.bounds,
        p.init_max_points,
        p.init_mesh_samples,
        INIT_BOUNDS_MARGIN * facade_size(data.bounds),
        INIT_KNN,
        INIT_OPACITY,
        p.init_reflectivity,
        p.init_reflectivity_glass,
        INIT_F0,
        p.sh_degree,
        p.seed,
        device,
    )
    return _assemble(p, data, rasterize, device, model, compile=compile)


def load_checkpoint(
    path: str | Path,
    p: TrainParams,
    data: TrainData,
    rasterize: Rasterizer,
    device: torch.device | str,
    fingerprint: str,
    compile: bool = False,
) -> Trainer | None:
    """The trainer saved at ``path``, or None when ``checkpoints.read_checkpoint`` finds none to resume
    (none there, other parameters or inputs, an older format, a damaged file moved aside: the log says);
    ``compile`` as ``_assemble``'s."""
    saved = read_checkpoint(path, p, fingerprint)
    if saved is None:
        return None
    device = torch.device(device)
    model = GaussianModel.from_state(saved["model"], device)
    return _assemble(p, data, rasterize, device, model, saved, compile)


def _check_finite(tr: Trainer, what: str, tensors: dict[str, Tensor | None]) -> None:
    for name, t in tensors.items():
        if t is not None and not bool(torch.isfinite(t).all()):
            raise TrainingDivergedError(
                None,
                f"finite {what} at iteration {tr.state.iteration + 1}",
                f"NaN or Inf in '{name}' (learning rates too high? lower train_gs.lr.*)",
            )


def _check_extent(tr: Trainer) -> None:
    lo, hi = tr.shading.bounds_lo, tr.shading.bounds_hi
    centre = 0.5 * (lo + hi)
    far = float((tr.state.model.means.detach() - centre).norm(dim=-1).max()) if tr.state.model.n else 0.0
    limit = DIVERGENCE_EXTENT_FACTOR * tr.extent
    if far > limit:
        raise TrainingDivergedError(
            None,
            f"splats within {limit:.1f} m of the facade at iteration {tr.state.iteration + 1}",
            f"a splat {far:.3g} m away (exploding position learning rate? lower train_gs.lr.position_init)",
        )


def render_window(
    tr: Trainer, index: int, window: Window, select=None, chunk: int = 0, cam: Camera | None = None
) -> tuple[Render, ViewTensors]:
    """Render a window of view ``index`` with the current model (from its corrected pose, if poses are
    refined, and with its exposure gain, if exposures are); returns it with the view's data there. ``cam``
    replaces the view's camera."""
    cam = camera(tr.cameras[index], tr.state.corrections, index) if cam is None else cam
    vt = view_tensors(tr.views[index], window, tr.data.views[index].clipped)
    r = render_view(
        tr.state.model,
        tr.state.reflection,
        cam,
        window,
        tr.rasterize,
        tr.near,
        active_sh_degree(tr.params.sh_degree, tr.params.sh_degree_interval, tr.state.iteration),
        tr.shading,
        spec_mask=vt.mask,
        select=select,
        chunk=chunk,
    )
    gain = exposure_gain(tr.gains, tr.data.train_idx, index)
    if gain is not None:
        r = dataclasses.replace(r, rgb=r.rgb * gain.to(r.rgb.dtype))
    return r, vt


def step(tr: Trainer, psnr: bool = True) -> dict[str, Tensor]:
    """One optimisation step on a random training view (or patch). Returns the loss terms and, with
    ``psnr``, the PSNR of the window over its loss mask, on the device (``train`` reads them every
    ``log_every`` iterations, and asks for the PSNR in those steps only: it trains nothing).
    Raises ``TrainingDivergedError`` on NaN/Inf or runaway splats: on the CPU, where reading a value costs
    nothing, checked in every step; on a GPU, where it would make the host wait for the device, by
    ``check_state`` when ``train`` reads the figures."""
    p = tr.params
    every_step = tr.device.type == "cpu"
    set_learning_rates(tr.state.opt, tr.state.opt_refl, p, tr.extent, tr.state.iteration)
    index = tr.data.train_idx[random_int(tr.state.generator, len(tr.data.train_idx))]
    cam = tr.cameras[index]  # the imported pose: the view-space gradients for densification
    mask = tr.data.views[index].facade_mask if p.mask_by_facade else None
    window = random_window(cam, mask, p.patch_px, tr.state.generator)
    r, vt = render_window(
        tr, index, window, select=lambda c: random_subset(c, p.mlp_max_pixels, tr.state.generator)
    )
    terms = compute_losses(p, r, vt, tr.state.iteration, tr.shading.compiled)
    if every_step:
        _check_finite(tr, "loss terms", terms)
    terms["loss"].backward()
    if every_step:
        grads = {n: t.grad for n, t in tr.state.model.params().items()}
        if tr.state.corrections is not None:
            grads |= {f"view_{n}": t.grad for n, t in tr.state.corrections.named_parameters()}
        _check_finite(tr, "gradients", grads)
    densify_end = densify_window(p.iterations)[1]
    if tr.state.iteration < densify_end and tr.state.model.means.grad is not None:
        grad_of = torch_compiled(view_space_grad, True) if tr.shading.compiled else view_space_grad
        g, vis = grad_of(
            tr.state.model.means,
            tr.state.model.means.grad,
            cam.cam_from_world,
            cam.K,
            (cam.width, cam.height),
            window,
            tr.near,
        )
        accumulate(tr.state.stats, g, vis)
    for opt in (tr.state.opt, tr.state.opt_refl, tr.state.opt_corrections):
        if opt is not None:
            opt.step()
            opt.zero_grad(set_to_none=True)
    if every_step:
        check_state(tr)
    tr.state.iteration += 1
    _densify_if_due(tr)
    out = {k: v.detach() for k, v in terms.items()}
    if psnr:
        seen = recorded(r.rgb.detach(), vt.image, vt.clipped).clamp(0, 1)
        out["psnr"] = psnr_tensor(seen, vt.image, vt.mask & ~r.skipped)
    return out


def check_state(tr: Trainer) -> None:
    """Raise ``TrainingDivergedError`` where a parameter is NaN or Inf (where a loss or a gradient was,
    the optimiser's step has carried it into them) or a splat has flown off."""
    _check_finite(tr, "parameters", {n: t for n, t in tr.state.model.params().items()})
    _check_extent(tr)


def _densify_if_due(tr: Trainer) -> None:
    p, d, it = tr.params, tr.params.densify, tr.state.iteration
    start, end = densify_window(p.iterations)
    if not start < it <= end:
        return
    if d.interval > 0 and it % d.interval == 0:
        prune_big = d.opacity_reset_interval > 0 and it > d.opacity_reset_interval
        s = tr.state
        counts = densify_and_prune(s.model, s.opt, s.stats, d, tr.extent, prune_big, s.generator)
        tr.state.stats = DensifyStats.zeros(tr.state.model.n, tr.device)
        log.debug("iteration %d: densified %s -> %d splats", it, counts, tr.state.model.n)
    if last_opacity_reset(d, p.iterations, it) == it:
        reset_opacity(tr.state.model, tr.state.opt, OPACITY_RESET_VALUE)


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
    Both are run settings (``[run]``): they change how a run goes, never what it trains. The step's figures
    stay on the device between log lines: ``progress`` gets the iteration every step and the figures of
    the last log line (none before the first)."""
    p = tr.params
    end = p.iterations if stop_at is None else min(stop_at, p.iterations)
    start = tr.state.iteration
    figures: dict[str, float] = {}

    def logged(iteration: int) -> bool:
        return log_every > 0 and (iteration % log_every == 0 or iteration == p.iterations)

    while tr.state.iteration < end:
        out = step(tr, psnr=logged(tr.state.iteration + 1))
        if logged(tr.state.iteration):
            check_state(tr)
            figures = {k: float(v) for k, v in out.items()}
            record = {
                "iteration": tr.state.iteration,
                "n_gaussians": tr.state.model.n,
                **{k: (round(v, 6) if math.isfinite(v) else None) for k, v in figures.items()},
            }
            tr.state.log.append(monitored(tr, record))  # the whole-view PSNR; stops a diverging run
        if checkpoint is not None and checkpoint_every > 0 and tr.state.iteration % checkpoint_every == 0:
            check_state(tr)
            save_checkpoint(tr.state, tr.params, checkpoint, fingerprint)
        if progress is not None:
            progress(tr.state.iteration, p.iterations, {**figures, "n": tr.state.model.n})
    saved = checkpoint_every > 0 and tr.state.iteration % checkpoint_every == 0
    if tr.state.iteration > start:
        check_state(tr)
    if checkpoint is not None and tr.state.iteration > start and not saved:
        save_checkpoint(tr.state, tr.params, checkpoint, fingerprint)
    return tr
