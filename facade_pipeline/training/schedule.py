"""Schedules expressed as fractions of the run, so that short runs keep the shape of long ones."""

from __future__ import annotations

import math


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
