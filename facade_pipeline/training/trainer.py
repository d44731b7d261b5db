"""The trainer: ``build_trainer``, ``step``, ``save_checkpoint`` / ``load_checkpoint`` and
``train`` (the loop that ties them together with checkpoints and a progress callback).

Losses (Eq. 13): L = L_c + lambda_n L_n + lambda_np L_np + lambda_hf L_hf, with L_c = 0.8 L1
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

from facade_pipeline.config import to_dict
from facade_pipeline.errors import PipelineError
from facade_pipeline.io.atomic import write_bytes
from facade_pipeline.shading.reflection import build_reflection_module
from facade_pipeline.splatting.types import NEAR_M
from facade_pipeline.training import losses
from facade_pipeline.training.corrections import ViewCorrections
from facade_pipeline.training.data import TrainData, TrainView
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
from facade_pipeline.training.exposure import ExposureEstimate, ExposureParams, estimate_exposures
from facade_pipeline.training.init import INIT_KNN, INIT_OPACITY, initial_model
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
from facade_pipeline.training.schedule import active_sh_degree, at_fraction, exp_decay, step_schedule

log = logging.getLogger(__name__)
CHECKPOINT_FORMAT = 2

# Adam rates of the splat attributes that 2DGS shares with 3DGS (their training defaults; DESIGN.md). They
# are per-attribute rates on activation-space parameters, not tied to a scene's size, and were never tuned
# here: the splat geometry and colour train as the reference does. The position rate decays from
# ``lr.position_init`` to this, times the scene extent, as in 3DGS.
POSITION_LR_FINAL = 1.6e-6
SH_DC_LR = 2.5e-3
SH_REST_LR = SH_DC_LR / 20.0  # 3DGS: the higher SH bands at a twentieth of the DC rate
OPACITY_LR = 0.05
SCALING_LR = 5e-3
ROTATION_LR = 1e-3
#: Weight of D-SSIM in L_c = (1 - w) L1 + w D-SSIM: the paper's (Eq. 13, after 2DGS), never tuned here.
LAMBDA_DSSIM = 0.2
#: Normal consistency from this fraction of the run: 2DGS's 7k of 30k iterations (a fraction, so that short
#: runs keep its schedule), never tuned here.
NORMAL_START_FRACTION = 0.2333
#: A splat this many scene extents from the facade means the run diverged: a sanity bound, far beyond any
#: real splat (the surroundings are within a few extents).
DIVERGENCE_EXTENT_FACTOR = 100.0
#: How the per-view exposure gains are estimated before training (``training.exposure``): its defaults.
EXPOSURE_ESTIMATE = ExposureParams()


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
        "quats": ROTATION_LR,
        "log_scales": SCALING_LR,
        "opacity_logits": OPACITY_LR,
        "sh_dc": SH_DC_LR,
        "sh_rest": SH_REST_LR,
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
            p.reflection_strategy(), device, (shading.bounds_lo, shading.bounds_hi), data.init.points
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


def _build_corrections(
    p: TrainParams, n_views: int, device: torch.device
) -> tuple[ViewCorrections | None, torch.optim.Adam | None]:
    if not p.pose_refinement:
        return None, None
    corr = ViewCorrections(n_views, device, pose=True)
    return corr, corr.optimizer(p.lr.pose_rotation, p.lr.pose_translation, lr_exposure=0.0)


def _estimate_exposure(p: TrainParams, data: TrainData) -> ExposureEstimate | None:
    if not p.exposure_estimate:
        return None
    m = data.init
    est = estimate_exposures(
        data.views, m.mesh_vertices, m.mesh_triangles, m.mesh_glass, data.train_idx, EXPOSURE_ESTIMATE, p.seed
    )
    few = [data.views[i].stem for i in data.train_idx if est.samples[i] < EXPOSURE_ESTIMATE.min_samples]
    if few:
        shown = ", ".join(few[:5]) + (f" and {len(few) - 5} more" if len(few) > 5 else "")
        log.warning(
            "exposure estimate: %d of %d training views have fewer than %d usable samples of the facade's "
            "opaque parts (non-glass points of the corrected mesh inside their facade mask) (%s); their gain "
            "stays 1. Expected where the mesh covers little of a view",
            len(few), len(data.train_idx), EXPOSURE_ESTIMATE.min_samples, shown,
        )  # fmt: skip
    return est


def exposure_gain(tr: Trainer, index: int) -> Tensor | None:
    """View ``index``'s exposure gain per colour channel [3] as estimated before training
    (``exposure_estimate``), relative to the training views' geometric mean so that the splats keep the
    mean exposure; None for held-out views and without the estimate."""
    if index not in tr.data.train_idx or tr.exposure is None:
        return None
    return torch.as_tensor(tr.exposure.log_gain[index], device=tr.device).exp()


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
        INIT_KNN,
        INIT_OPACITY,
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
                p.lr.position_init * tr.extent, POSITION_LR_FINAL * tr.extent, it, p.iterations
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
    if p.reflection.model == "envmap":
        return p.lr.envmap
    return exp_decay(p.lr.reflection_init, p.lr.reflection_final, it, p.iterations)


def compute_losses(p: TrainParams, r: Render, vt: ViewTensors, iteration: int) -> dict[str, Tensor]:
    """The terms of Eq. 13 for one rendered window and the weighted total (key ``loss``)."""
    zero = r.rgb.new_zeros(())
    loss_mask = vt.mask & ~r.skipped
    terms = {"color": losses.color_loss(r.rgb, vt.image, loss_mask, LAMBDA_DSSIM)}
    total = terms["color"]
    if p.lambda_normal > 0 and iteration >= at_fraction(NORMAL_START_FRACTION, p.iterations):
        terms["normal"] = losses.normal_consistency_loss(r.normal, losses.depth_normals(r.points), loss_mask)
        total = total + p.lambda_normal * terms["normal"]
    if p.lambda_normal_prior > 0:
        terms["normal_prior"] = losses.normal_prior_loss(r.normal, vt.prior, vt.prior_valid & vt.mask)
        total = total + p.lambda_normal_prior * terms["normal_prior"]
    tau = step_schedule(p.hf_tau_start, p.hf_tau_end, p.hf_steps, iteration, p.iterations)
    lam = step_schedule(p.lambda_hf_start, p.lambda_hf_end, p.hf_steps, iteration, p.iterations)
    if lam > 0:
        terms["hf"] = losses.high_frequency_loss(r.rgb, vt.image, loss_mask, tau)
        total = total + lam * terms["hf"]
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
    vt = view_tensors(tr.data.views[index], window, tr.params.mask_by_facade, tr.device)
    r = render_view(
        tr.model,
        tr.reflection,
        cam,
        window,
        tr.rasterize,
        NEAR_M,
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
    densify_end = at_fraction(DENSIFY_END_FRACTION, p.iterations)
    if tr.iteration < densify_end and tr.model.means.grad is not None:
        g, vis = view_space_grad(
            tr.model.means,
            tr.model.means.grad,
            cam.cam_from_world,
            cam.K,
            (cam.width, cam.height),
            window,
            NEAR_M,
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


def save_checkpoint(tr: Trainer, path: str | Path, fingerprint: str) -> None:
    """Everything needed to continue exactly, written atomically."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "fingerprint": fingerprint,
        "params": to_dict(tr.params),  # to tell, when it does not match, what changed
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
    inputs (its fingerprint differs) or an older format, which the log says (naming the parameters that
    changed when the checkpoint records them). A damaged file is moved aside to ``<name>.bad`` (kept for a
    person to look at) and training starts afresh."""
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
            "%s: checkpoint of iteration %s not resumed: %s; training starts from iteration 0",
            path, state.get("iteration", "?"), _mismatch(state, p),
        )  # fmt: skip
        return None
    log.info("%s: resuming from the checkpoint of iteration %s", path, state["iteration"])
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


def _mismatch(state: dict[str, Any], p: TrainParams) -> str:
    """Why a checkpoint's fingerprint differs, as far as it records: its format, the parameters that
    changed (dotted [train_gs] keys, old -> new, the first few), or else the inputs or the code."""
    if state.get("format") != CHECKPOINT_FORMAT:
        return f"it has format {state.get('format')!r}, this version reads {CHECKPOINT_FORMAT}"
    saved = state.get("params")
    if not isinstance(saved, dict):
        return "it was made with other parameters, inputs or code"
    old, new = _dotted(saved), _dotted(to_dict(p))
    keys = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    changed = [f"{k} {old.get(k, '(none)')!r} -> {new.get(k, '(none)')!r}" for k in keys]
    if not changed:
        return "same parameters, other inputs or code (an upstream output or facade_pipeline changed)"
    more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
    return "other parameters: " + ", ".join(changed[:3]) + more


def _dotted(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in table.items():
        if isinstance(value, dict):
            out |= _dotted(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


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
