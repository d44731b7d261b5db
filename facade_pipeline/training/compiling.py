"""``torch_compiled``: a function of a training step through ``torch.compile`` (``[run] compile``). On a GPU a
step of eager torch is launch-bound: about 1,800 kernel launches, each a few microseconds of the host, for
17 ms of device work (benchmarks/RESULTS.md, "The GPU check"); compiled, the element-wise chains of the
shading, the losses and their backward become a few fused kernels. The functions compiled take tensors and
flags only, with shapes that do not depend on the values, so that nothing in them waits for the device."""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch


@functools.cache
def torch_compiled(fn: Callable, dynamic: bool | None) -> Callable:
    """``fn`` through ``torch.compile``, made once per function. ``dynamic``: True for a function of the
    splats (their count changes at each densification: symbolic from the start, not compiled again then);
    None for one of a window (a patch's corner moves at each step: symbolic after the first move); False
    for one of a window's pixels alone (a run's windows are all of one size)."""
    return torch.compile(fn, dynamic=dynamic)
