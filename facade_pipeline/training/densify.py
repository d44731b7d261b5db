"""Densification and pruning as 2DGS does it: splats whose mean view-space positional gradient is large are
cloned (small ones) or split (large ones); transparent and oversized splats are pruned; opacities are reset
periodically. Adam's moments follow the rows they belong to (new rows start at zero)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from facade_pipeline.training.model import GaussianModel, inverse_sigmoid, quat_to_rotmat
from facade_pipeline.training.params import DensifyParams
from facade_pipeline.training.schedule import at_fraction

# 2DGS's densification numbers (its training defaults, those of 3DGS; DESIGN.md), never tuned here: they are
# fractions of the scene extent or of the run, so they carry over to any facade and budget. What a budget
# sets (interval, threshold, reset interval, cap) is in [train_gs.densify].
#: Densify from this fraction of the run (2DGS: 500 of 30k iterations) ...
DENSIFY_START_FRACTION = 0.0167
#: ... until this fraction (2DGS: 15k of 30k).
DENSIFY_END_FRACTION = 0.5
#: Splats larger than this fraction of the scene extent are split, smaller ones cloned (2DGS: percent_dense).
PERCENT_DENSE = 0.01
#: Children of a split splat (2DGS: N = 2).
SPLIT_COUNT = 2
#: Splats less opaque than this are pruned (2DGS: 0.05).
PRUNE_OPACITY = 0.05
#: After the first opacity reset, splats larger than this fraction of the extent are pruned (2DGS: 0.1).
PRUNE_WORLD_SIZE_FRACTION = 0.1
#: Opacities are clamped to at most this at a reset (2DGS: 0.01).
OPACITY_RESET_VALUE = 0.01


@dataclass
class DensifyStats:
    """Accumulated view-space gradient norms and visibility counts per splat since the last densification."""

    grad_accum: Tensor  # [N]
    count: Tensor  # [N]

    @classmethod
    def zeros(cls, n: int, device: torch.device | str) -> DensifyStats:
        return cls(torch.zeros(n, device=device), torch.zeros(n, device=device))


def view_space_grad(
    means: Tensor,
    grad: Tensor,
    cam_from_world: Tensor,
    K: Tensor,
    size: tuple[int, int],
    window: tuple[int, int, int, int],
    near: float,
) -> tuple[Tensor, Tensor]:
    """The norm of the positional gradient in NDC units [N] and which splats project into ``window`` [N].

    The loss gradient with respect to a splat's screen position is the world gradient's lateral camera
    components times z / f (moving one pixel moves z / f metres); NDC units multiply by half the image size,
    the units of the 2DGS threshold."""
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    pc = means.detach() @ R.T + t  # [N, 3]
    gc = grad @ R.T  # [N, 3]
    z = pc[:, 2].clamp_min(near)
    w, h = size
    gx = gc[:, 0] * z / K[0, 0] * (0.5 * w)
    gy = gc[:, 1] * z / K[1, 1] * (0.5 * h)
    px = K[0, 0] * pc[:, 0] / z + K[0, 2]
    py = K[1, 1] * pc[:, 1] / z + K[1, 2]
    x0, y0, ww, hh = window
    visible = (pc[:, 2] > near) & (px >= x0) & (px < x0 + ww) & (py >= y0) & (py < y0 + hh)
    return torch.sqrt(gx * gx + gy * gy), visible


def accumulate(stats: DensifyStats, grad_norm: Tensor, visible: Tensor) -> None:
    stats.grad_accum += torch.where(visible, grad_norm, torch.zeros_like(grad_norm))
    stats.count += visible.to(stats.count.dtype)


def _group(opt: torch.optim.Optimizer, name: str) -> dict:
    return next(g for g in opt.param_groups if g["name"] == name)


def _swap(opt: torch.optim.Optimizer, name: str, new: nn.Parameter, rows) -> None:
    """Replace the parameter of group ``name`` by ``new``; its Adam moments become ``rows(old moment)``."""
    group = _group(opt, name)
    old = group["params"][0]
    state = opt.state.pop(old, None)
    group["params"][0] = new
    if state:
        opt.state[new] = {k: (rows(v) if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in state.items()}


def select_rows(model: GaussianModel, opt: torch.optim.Optimizer, keep: Tensor) -> None:
    """Keep the rows where ``keep`` [N] is True, in the model and in Adam's moments."""
    tensors = {name: nn.Parameter(p.detach()[keep].contiguous()) for name, p in model.params().items()}
    for name, p in tensors.items():
        _swap(opt, name, p, lambda v: v[keep].contiguous())
    model.replace(tensors)


def append_rows(model: GaussianModel, opt: torch.optim.Optimizer, new: dict[str, Tensor]) -> None:
    """Append rows (one tensor per parameter) to the model; their Adam moments start at zero."""
    tensors = {}
    for name, p in model.params().items():
        tensors[name] = nn.Parameter(torch.cat([p.detach(), new[name].detach()]).contiguous())
        extra = new[name].shape[0]
        _swap(opt, name, tensors[name], lambda v, e=extra: torch.cat([v, v.new_zeros((e, *v.shape[1:]))]))
    model.replace(tensors)


def densify_and_prune(
    model: GaussianModel,
    opt: torch.optim.Optimizer,
    stats: DensifyStats,
    p: DensifyParams,
    extent: float,
    prune_big: bool,
    generator: torch.Generator,
) -> dict[str, int]:
    """One densification step: clone, split, prune. Returns the counts of each."""
    avg = torch.where(
        stats.count > 0, stats.grad_accum / stats.count.clamp_min(1), torch.zeros_like(stats.count)
    )
    big = model.scales().detach().max(dim=-1).values > PERCENT_DENSE * extent
    hot = avg >= p.grad_threshold
    budget = max(p.max_gaussians - model.n, 0) // SPLIT_COUNT
    if int(hot.sum()) > budget:  # keep the hottest within the budget
        order = torch.argsort(torch.where(hot, avg, torch.full_like(avg, -1.0)), descending=True)
        hot = torch.zeros_like(hot)
        hot[order[:budget]] = True
    clone, split = hot & ~big, hot & big
    n_before = model.n
    # judged before a clone shares its opacity with its copy: a pair is as opaque as the splat was
    opaque = model.opacities().detach() >= PRUNE_OPACITY
    if clone.any():
        _halve_opacity(model, clone)
        append_rows(model, opt, {name: t.detach()[clone] for name, t in model.params().items()})
        opaque = torch.cat([opaque, opaque[clone]])
    if split.any():
        grown = torch.cat([split, split.new_zeros(model.n - n_before)])  # clones are never split
        append_rows(model, opt, _split_rows(model, grown, SPLIT_COUNT, generator))
        opaque = torch.cat([opaque, opaque[grown].repeat_interleave(SPLIT_COUNT)])
    split_full = torch.cat([split, split.new_zeros(model.n - n_before)])
    keep = ~split_full & opaque
    if prune_big:
        keep &= model.scales().detach().max(dim=-1).values <= PRUNE_WORLD_SIZE_FRACTION * extent
    if not keep.any():  # never prune everything: keep the most opaque splat
        keep[torch.argmax(model.opacities().detach())] = True
    n_pruned = int((~keep).sum()) - int(split.sum())
    select_rows(model, opt, keep)
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": n_pruned}


def _halve_opacity(model: GaussianModel, rows: Tensor) -> None:
    """Give the splats of ``rows`` the opacity a' with 1 - (1 - a')^2 = a, so that a splat and its exact
    copy blend to what the splat alone did: a clone changes no pixel (2DGS's copies keep a each and
    composite to 1 - (1 - a)^2, a jump in every render at each densification, as Rota Bulo et al. 2024
    note). Adam's moments of these rows are kept; the copies' start at zero."""
    a = model.opacities().detach()[rows]
    with torch.no_grad():
        model.opacity_logits[rows] = inverse_sigmoid(1.0 - torch.sqrt(1.0 - a))


def _split_rows(model: GaussianModel, split: Tensor, k: int, generator: torch.Generator) -> dict[str, Tensor]:
    """``k`` children per selected splat: centres drawn from the splat's own Gaussian in its plane, scales
    divided by 0.8 k, everything else copied."""
    rows = {name: t.detach()[split].repeat_interleave(k, dim=0) for name, t in model.params().items()}
    s = rows["log_scales"].exp()  # [M, 2]
    eps = torch.randn(s.shape, generator=generator, device="cpu").to(s.device) * s
    R = quat_to_rotmat(rows["quats"] / rows["quats"].norm(dim=-1, keepdim=True))
    rows["means"] = rows["means"] + (R[:, :, :2] @ eps.unsqueeze(-1)).squeeze(-1)
    rows["log_scales"] = (s / (0.8 * k)).log()
    return rows


def densify_window(iterations: int) -> tuple[int, int]:
    """(start, end): densification, and the opacity resets with it, run at the iterations ``it`` with
    start < it <= end of a run of ``iterations``."""
    return at_fraction(DENSIFY_START_FRACTION, iterations), at_fraction(DENSIFY_END_FRACTION, iterations)


def last_opacity_reset(d: DensifyParams, iterations: int, iteration: int) -> int:
    """The last iteration at or before ``iteration`` at which a run of ``iterations`` reset its opacities
    (0: none yet): a multiple of ``d.opacity_reset_interval`` inside ``densify_window``."""
    if d.opacity_reset_interval <= 0:
        return 0
    start, end = densify_window(iterations)
    last = min(iteration, end) // d.opacity_reset_interval * d.opacity_reset_interval
    return last if last > start else 0


def reset_opacity(model: GaussianModel, opt: torch.optim.Optimizer, value: float) -> None:
    """Clamp every opacity to at most ``value`` and zero its Adam moments (2DGS opacity reset)."""
    new = nn.Parameter(
        torch.minimum(
            model.opacity_logits.detach(), inverse_sigmoid(torch.tensor(value, device=model.means.device))
        )
    )
    _swap(opt, "opacity_logits", new, torch.zeros_like)
    model.opacity_logits = new
