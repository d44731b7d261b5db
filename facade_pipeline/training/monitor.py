"""What training shows of its progress beyond the step's own figures: the PSNR over whole training views.

A step's PSNR is over one random patch, so it jumps from step to step with the patch drawn. Every
``log_every`` iterations the trainer instead renders a fixed subset of its training views whole (at most
``MONITOR_VIEWS``, spread over the list) and measures them as its loss sees them: over the facade mask, with
each view's exposure gain and the camera's clipping (``losses.recorded``). That figure is comparable from
one check to the next; it is logged as ``view_psnr``. A NaN in it, or a fall of more than
``DIVERGENCE_DROP_DB`` below the best since the last opacity reset, stops training as a divergence (the
last checkpoint written stays the last good one). A reset is a fall by design: every opacity clamped to
0.01 leaves the views nearly black (on gcw_dev at the GPU budget 19.7 dB -> 6.2 dB at the reset), and the
run then builds the facade up again, so the checks after it are judged against each other.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch

from facade_pipeline.training.densify import last_opacity_reset
from facade_pipeline.training.losses import recorded

if TYPE_CHECKING:
    from facade_pipeline.training.trainer import Trainer

#: Training views rendered whole at each check: enough to average out one view's luck, few enough that a
#: check costs a few steps' time.
MONITOR_VIEWS = 4
#: A whole-view PSNR this far below the best so far (dB) is a divergence, not noise: a run that learns
#: moves by fractions of a dB between checks.
DIVERGENCE_DROP_DB = 10.0


def monitor_indices(train_idx: tuple[int, ...], n: int = MONITOR_VIEWS) -> tuple[int, ...]:
    """At most ``n`` of the training views, evenly spread over their list (the same at every check)."""
    if len(train_idx) <= n:
        return tuple(train_idx)
    step = len(train_idx) / n
    return tuple(train_idx[int(k * step)] for k in range(n))


@torch.no_grad()
def whole_view_psnr(tr: Trainer, views: tuple[int, ...] | None = None) -> float:
    """PSNR (dB) over training views rendered whole, all their loss pixels pooled: the monitored ones
    (``monitor_indices``), or ``views`` (indices of training views)."""
    from facade_pipeline.training.trainer import render_window  # the trainer imports this module

    se = 0.0
    n = 0.0
    for i in monitor_indices(tr.data.train_idx) if views is None else views:
        cam = tr.cameras[i]
        r, vt = render_window(tr, i, (0, 0, cam.width, cam.height))
        seen = recorded(r.rgb, vt.image, vt.clipped).clamp(0, 1)
        mask = (vt.mask & ~r.skipped).unsqueeze(-1).to(torch.float64)
        se += float((((seen.double() - vt.image.double()) ** 2) * mask).sum())
        n += 3.0 * float(mask.sum())
    if n == 0:
        return math.nan
    return math.inf if se == 0 else 10.0 * math.log10(n / se)


def monitored(tr: Trainer, record: dict[str, Any]) -> dict[str, Any]:
    """``record`` (a training log line) with ``view_psnr`` measured now; raises ``TrainingDivergedError``
    naming the iteration and the cause when it is NaN or fell more than ``DIVERGENCE_DROP_DB`` below the
    best of the earlier checks since the last opacity reset (this check's own step may be the reset)."""
    from facade_pipeline.training.trainer import TrainingDivergedError

    value = whole_view_psnr(tr)
    if math.isnan(value):
        raise TrainingDivergedError(
            None,
            f"a finite whole-view PSNR at iteration {tr.state.iteration}",
            "NaN (the render or the photos' masks hold no finite pixel; lower train_gs.lr.*)",
        )
    since = last_opacity_reset(tr.params.densify, tr.params.iterations, tr.state.iteration)
    best = max(
        (r["view_psnr"] for r in tr.state.log if r.get("view_psnr") is not None and r["iteration"] >= since),
        default=-math.inf,
    )
    if value < best - DIVERGENCE_DROP_DB:
        raise TrainingDivergedError(
            None,
            f"a whole-view PSNR within {DIVERGENCE_DROP_DB:g} dB of its best at iteration "
            f"{tr.state.iteration}",
            f"{value:.2f} dB after {best:.2f} dB (diverging: lower train_gs.lr.*)",
        )
    return {**record, "view_psnr": round(value, 4) if math.isfinite(value) else None}
