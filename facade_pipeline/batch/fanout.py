"""A stage's per-view loop, fanned out: ``map_views(fn, views, workers)`` is ``[fn(v) for v in views]``,
computed on the batch's Dask cluster when the stage runs under ``facade-batch`` (its scheduler's address in
``FACADE_BATCH_SCHEDULER``), over ``workers`` processes of this machine otherwise (``[run] view_workers``;
1: in the stage's own process, 0: one per core).

``fn`` is a picklable function of one view that writes that view's outputs and returns what the stage
collects; results come back in the order of ``views``, so the stage's manifest and metrics are those of the
serial loop. What every view needs (a mesh, a point cloud) is loaded once per process through ``shared``.
Processes are started with ``spawn``: forking a process whose OpenMP or OpenCV thread pools already run
can hang the child. They inherit the stage's environment, thread policy included, so each view computes
with the thread counts of the serial loop; a Dask worker has its own (its nanny's: one OpenMP thread), so a
view whose bytes depend on the thread count sets the stage's count in ``fn`` (evaluate's renders: a sum
split over another number of threads rounds differently).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

from facade_pipeline.threads import usable_cores

SCHEDULER_ENV = "FACADE_BATCH_SCHEDULER"
T = TypeVar("T")
R = TypeVar("R")


def map_views(
    fn: Callable[[T], R],
    views: Iterable[T],
    workers: int = 1,
    done: Callable[[R], Any] | None = None,
    spread: bool = True,
) -> list[R]:
    """``[fn(v) for v in views]``, fanned out as the module says; ``done(result)`` after each view, in
    order (a progress bar). ``spread=False`` keeps every view in the stage's own process (views that need
    its device: a GPU renders them faster than processes sharing it would)."""
    views = list(views)
    address = os.environ.get(SCHEDULER_ENV) if spread else None
    n = (usable_cores() if workers == 0 else workers) if spread else 1
    if address and len(views) > 1:
        return _on_cluster(address, fn, views, done)
    if min(n, len(views)) > 1:
        return _in_processes(fn, views, min(n, len(views)), done)
    results = []
    for v in views:
        results.append(fn(v))
        if done is not None:
            done(results[-1])
    return results


def _in_processes(fn, views, n, done):
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(n, mp_context=context) as pool:
        futures = [pool.submit(fn, v) for v in views]
        return _in_order(futures, done)


def _on_cluster(address, fn, views, done):
    from distributed import Client

    with Client(address, set_as_default=False) as client:
        futures = client.map(fn, views, pure=False)
        return _in_order(futures, done)


def _in_order(futures, done):
    results = []
    for f in futures:
        results.append(f.result())
        if done is not None:
            done(results[-1])
    return results


#: what ``shared`` loaded in this process, by loader and files (a worker outlives stages and buildings)
_LOADED: dict[tuple, Any] = {}
_LOADED_MAX = 4


def shared(loader: Callable[..., R], *args: Any) -> R:
    """``loader(*args)``, once per process for as long as the files among ``args`` (paths) stay the same
    (their size and time); the other arguments must be hashable."""
    key = (loader, *(
        (os.fspath(a), os.stat(a).st_size, os.stat(a).st_mtime_ns) if isinstance(a, os.PathLike) else a
        for a in args
    ))
    if key not in _LOADED:
        if len(_LOADED) >= _LOADED_MAX:
            _LOADED.clear()
        _LOADED[key] = loader(*args)
    return _LOADED[key]
