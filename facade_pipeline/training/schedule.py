"""Schedules expressed as fractions of the run, so that short runs keep the shape of long ones: the
generic shapes (steps, a log-linear decay, the SH bands in use) and the learning rates that follow them
during training (``position_lr``, ``reflection_lr``; the optimisers that take them are
``training.optimizers``)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: the generic shapes need no parameters
    from facade_pipeline.training.params import TrainParams

#: Where the position rate decays to, times the scene extent, from ``lr.position_init``: 3DGS's training
#: default (DESIGN.md), never tuned here, like the other splat rates of ``training.optimizers``.
POSITION_LR_FINAL = 1.6e-6
#: the reflection MLP's rate decays log-linearly from ``lr.reflection_init`` to this at the end of the run
#: (never tuned: no building moved it)
LR_REFLECTION_FINAL = 1e-5
#: Adam rate of the environment map's texel logits (constant): each texel sees few pixels, like a splat
#: colour, so it takes a splat colour's order of rate
LR_ENVMAP = 1e-2


def at_fraction(fraction: float, iterations: int) -> int:
    """The iteration at ``fraction`` of a run of ``iterations`` steps (rounded)."""
    return int(round(fraction * iterations))


def step_schedule(start: float, end: float, n_steps: int, iteration: int, iterations: int) -> float:
    """A value that moves from ``start`` to ``end`` in ``n_steps`` equal stages spread over the run
    (piecewise constant; the paper's stepwise tau and lambda_hf, Eq. 12-13). With ``n_steps`` = 1 the
    value stays ``start``."""
    if n_steps <= 1:
        return start
    t = iteration / max(iterations, 1)
    k = min(max(int(math.floor(t * n_steps)), 0), n_steps - 1)
    return start + (end - start) * k / (n_steps - 1)


def exp_decay(init: float, final: float, iteration: int, iterations: int) -> float:
    """Log-linear interpolation from ``init`` at 0 to ``final`` at ``iterations`` (the 3DGS position rate)."""
    if init <= 0.0 or final <= 0.0:
        return init if iteration == 0 else final
    t = min(max(iteration / max(iterations, 1), 0.0), 1.0)
    return math.exp((1.0 - t) * math.log(init) + t * math.log(final))


def active_sh_degree(sh_degree: int, interval: int, iteration: int) -> int:
    """The SH degree in use at ``iteration``: one more band every ``interval`` iterations (3DGS), up to
    ``sh_degree``; ``interval`` <= 0 uses every band from the start."""
    if interval <= 0:
        return sh_degree
    return min(sh_degree, iteration // interval)


def position_lr(p: TrainParams, extent: float, it: int) -> float:
    """The splat positions' rate at iteration ``it``: from ``lr.position_init`` to ``POSITION_LR_FINAL``,
    both times the scene extent ``extent`` (m), log-linearly (3DGS)."""
    return exp_decay(p.lr.position_init * extent, POSITION_LR_FINAL * extent, it, p.iterations)


def reflection_lr(p: TrainParams, it: int, group: str) -> float:
    """A reflection parameter group's rate at iteration ``it``: the MLP's decays; the environment map's and
    the proxy feature maps' are fixed."""
    if group == "proxy":
        return p.lr.proxy
    if p.reflection.model == "envmap":
        return LR_ENVMAP
    return exp_decay(p.lr.reflection_init, LR_REFLECTION_FINAL, it, p.iterations)
