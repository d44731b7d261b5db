"""The training loop: the ``Trainer`` (everything that changes during training), ``build_trainer`` (at
iteration 0) and ``load_checkpoint`` (from a checkpoint), ``step`` (one optimisation step: draw a window,
render it, the losses, update, check for divergence, densify when due) and ``train`` (steps with
checkpoints and a progress callback).

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
from torch import Tensor, nn

from facade_pipeline.errors import PipelineError
from facade_pipeline.shading.reflection import build_reflection_module
from facade_pipeline.training.batches import (
    ViewTensors,
    camera,
    exposure_gain,
    random_int,
    random_window,
    view_tensors,
    views_on_device,
)
from facade_pipeline.training.checkpoints import read_checkpoint, save_checkpoint
from facade_pipeline.training.corrections import ViewCorrections
from facade_pipeline.training.data import ExposureEstimate, TrainData
from facade_pipeline.training.densify import (
    DENSIFY_END_FRACTION,
    DENSIFY_START_FRACTION,
    OPACITY_RESET_VALUE,
    DensifyStats,
    accumulate,
    densify_and_prune,
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
from facade_pipeline.training.schedule import active_sh_degree, at_fraction

log = logging.getLogger(__name__)
#: A splat this many scene extents from the facade means the run diverged: a sanity bound, far beyond any
#: real splat (the surroundings are within a few extents).
DIVERGENCE_EXTENT_FACTOR = 100.0
#: Adam rates of the per-view pose corrections (``pose_refinement``, constant): rotation (rad) and
#: translation (times the scene extent, so that a 1:25 model's poses move as the building's). Enough to
#: undo a real photo's pose error within a short run (gcw_dev's motion capture: about 5 mm, 3 % of its
#: extent, in 300 steps), and still small steps for demo's (3 cm, 0.05 % of its extent).
LR_POSE_ROTATION = 1e-4
LR_POSE_TRANSLATION = 1e-4


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
    """per-view pose corrections (``pose_refinement``), else None"""
    opt_corrections: torch.optim.Adam | None = None
    exposure: ExposureEstimate | None = None
    """per-view gains estimated from the photos before training (``exposure_estimate``), else None"""

    views: tuple[ViewTensors, ...] = field(init=False, repr=False)
    """every view's data on the device (``batches.views_on_device``)"""
    gains: Tensor | None = field(init=False, repr=False)
    """[V, 3] the exposure gains on the device (``exposure``), else None"""

    def __post_init__(self) -> None:
        self.views = views_on_device(self.data.views, self.params.mask_by_facade, self.device)
        self.gains = None
        if self.exposure is not None:
            log_gain = torch.as_tensor(self.exposure.log_gain, dtype=torch.float32, device=self.device)
            self.gains = log_gain.exp()

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


def _build_parts(p: TrainParams, data: TrainData, device: torch.device, model: GaussianModel):
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
    )
    with torch.random.fork_rng(devices=[]):  # the module's initial weights come from the seed alone
        torch.manual_seed(p.seed)
        reflection = build_reflection_module(
            p.reflection_strategy(data.bounds),
            device,
            (shading.bounds_lo, shading.bounds_hi),
            data.init.points,
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
    return reflection, opt, opt_refl, shading, cameras


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
    reflection, opt, opt_refl, shading, cameras = _build_parts(p, data, device, model)
    gen = torch.Generator(device="cpu")
    gen.manual_seed(p.seed)
    corrections, opt_corrections = _build_corrections(p, len(data.views), data.extent, device)
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
        exposure=_exposure(p, data),
    )


def load_checkpoint(
    path: str | Path,
    p: TrainParams,
    data: TrainData,
    rasterize: Rasterizer,
    device: torch.device | str,
    fingerprint: str,
) -> Trainer | None:
    """The trainer saved at ``path``, or None when ``checkpoints.read_checkpoint`` finds none to resume
    (none there, other parameters or inputs, an older format, a damaged file moved aside: the log says)."""
    state = read_checkpoint(path, p, fingerprint)
    if state is None:
        return None
    device = torch.device(device)
    model = GaussianModel.from_state(state["model"], device)
    reflection, opt, opt_refl, shading, cameras = _build_parts(p, data, device, model)
    opt.load_state_dict(state["opt"])
    if reflection is not None:
        reflection.load_state_dict(state["reflection"])
        opt_refl.load_state_dict(state["opt_refl"])
    corrections, opt_corrections = _build_corrections(p, len(data.views), data.extent, device)
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
        _exposure(p, data),
    )


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
    limit = DIVERGENCE_EXTENT_FACTOR * tr.extent
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
    vt = view_tensors(tr.views[index], window)
    r = render_view(
        tr.model,
        tr.reflection,
        cam,
        window,
        tr.rasterize,
        tr.near,
        active_sh_degree(tr.params.sh_degree, tr.params.sh_degree_interval, tr.iteration),
        tr.shading,
        spec_mask=vt.mask,
        select=select,
        chunk=chunk,
    )
    gain = exposure_gain(tr, index)
    if gain is not None:
        r = dataclasses.replace(r, rgb=r.rgb * gain.to(r.rgb.dtype))
    return r, vt


def step(tr: Trainer) -> dict[str, Tensor]:
    """One optimisation step on a random training view (or patch). Returns the loss terms and the PSNR of
    the window over its loss mask, on the device (``train`` reads them every ``log_every`` iterations).
    Raises ``TrainingDivergedError`` on NaN/Inf or runaway splats: on the CPU, where reading a value costs
    nothing, checked in every step; on a GPU, where it would make the host wait for the device, by
    ``check_state`` when ``train`` reads the figures."""
    p = tr.params
    every_step = tr.device.type == "cpu"
    set_learning_rates(tr)
    index = tr.data.train_idx[random_int(tr.generator, len(tr.data.train_idx))]
    cam = tr.cameras[index]  # the imported pose: the view-space gradients for densification
    window = random_window(tr, index)
    r, vt = render_window(
        tr, index, window, select=lambda c: random_subset(c, p.mlp_max_pixels, tr.generator)
    )
    terms = compute_losses(p, r, vt, tr.iteration)
    if every_step:
        _check_finite(tr, "loss terms", terms)
    terms["loss"].backward()
    if every_step:
        grads = {n: t.grad for n, t in tr.model.params().items()}
        if tr.corrections is not None:
            grads |= {f"view_{n}": t.grad for n, t in tr.corrections.named_parameters()}
        _check_finite(tr, "gradients", grads)
    densify_end = at_fraction(DENSIFY_END_FRACTION, p.iterations)
    if tr.iteration < densify_end and tr.model.means.grad is not None:
        g, vis = view_space_grad(
            tr.model.means,
            tr.model.means.grad,
            cam.cam_from_world,
            cam.K,
            (cam.width, cam.height),
            window,
            tr.near,
        )
        accumulate(tr.stats, g, vis)
    for opt in (tr.opt, tr.opt_refl, tr.opt_corrections):
        if opt is not None:
            opt.step()
            opt.zero_grad(set_to_none=True)
    if every_step:
        check_state(tr)
    tr.iteration += 1
    _densify_if_due(tr)
    out = {k: v.detach() for k, v in terms.items()}
    seen = recorded(r.rgb.detach(), vt.image, vt.clipped).clamp(0, 1)
    out["psnr"] = psnr_tensor(seen, vt.image, vt.mask & ~r.skipped)
    return out


def check_state(tr: Trainer) -> None:
    """Raise ``TrainingDivergedError`` where a parameter is NaN or Inf (where a loss or a gradient was,
    the optimiser's step has carried it into them) or a splat has flown off."""
    _check_finite(tr, "parameters", {n: t for n, t in tr.model.params().items()})
    _check_extent(tr)


def _densify_if_due(tr: Trainer) -> None:
    p, d, it = tr.params, tr.params.densify, tr.iteration
    start, end = (at_fraction(f, p.iterations) for f in (DENSIFY_START_FRACTION, DENSIFY_END_FRACTION))
    if not start < it <= end:
        return
    if d.interval > 0 and it % d.interval == 0:
        prune_big = d.opacity_reset_interval > 0 and it > d.opacity_reset_interval
        counts = densify_and_prune(tr.model, tr.opt, tr.stats, d, tr.extent, prune_big, tr.generator)
        tr.stats = DensifyStats.zeros(tr.model.n, tr.device)
        log.debug("iteration %d: densified %s -> %d splats", it, counts, tr.model.n)
    if d.opacity_reset_interval > 0 and it % d.opacity_reset_interval == 0:
        reset_opacity(tr.model, tr.opt, OPACITY_RESET_VALUE)


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
    start = tr.iteration
    figures: dict[str, float] = {}
    while tr.iteration < end:
        out = step(tr)
        if log_every > 0 and (tr.iteration % log_every == 0 or tr.iteration == p.iterations):
            check_state(tr)
            figures = {k: float(v) for k, v in out.items()}
            record = {
                "iteration": tr.iteration,
                "n_gaussians": tr.model.n,
                **{k: (round(v, 6) if math.isfinite(v) else None) for k, v in figures.items()},
            }
            tr.log.append(monitored(tr, record))  # the whole-view PSNR; stops a diverging run
        if checkpoint is not None and checkpoint_every > 0 and tr.iteration % checkpoint_every == 0:
            check_state(tr)
            save_checkpoint(tr, checkpoint, fingerprint)
        if progress is not None:
            progress(tr.iteration, p.iterations, {**figures, "n": tr.model.n})
    saved = checkpoint_every > 0 and tr.iteration % checkpoint_every == 0
    if tr.iteration > start:
        check_state(tr)
    if checkpoint is not None and tr.iteration > start and not saved:
        save_checkpoint(tr, checkpoint, fingerprint)
    return tr
