"""One Dask task: one stage of one building, run on a worker through the building's doit tasks.

The task runs ``doit -s STAGE building=B data_root=D`` (under ``guard``, which ends it should the worker
die), so a stage that is up to date does nothing, and one that runs writes its outputs and manifest as a
run by hand would, holding the building's lock. What doit printed goes to ``.batch/<stage>.log`` beside
the building; the record (``record``) says running, done or failed with the stage's one-line error.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import facade_pipeline
from facade_pipeline.config import BUDGET_ENV, CONFIG_DIR_ENV
from facade_pipeline.errors import PipelineError
from facade_pipeline.io.lock import BuildingBusyError, acquire, release
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.threads import COUNT_VARS

from . import record
from .fanout import SCHEDULER_ENV

DODO = Path(facade_pipeline.__file__).resolve().parents[1] / "dodo.py"
#: how long a task waits for the building's lock: a killed worker's stage is being ended by its guard
LOCK_WAIT_S = 60.0


class StageFailed(Exception):
    """A stage of a building failed; the message is one line: building, stage, the stage's own error."""


def worker_name() -> str:
    """This worker's address and host (the process's own host outside a Dask worker)."""
    try:
        from distributed import get_worker

        return f"worker {get_worker().address} on {socket.gethostname()}"
    except (ImportError, ValueError):
        return f"process {os.getpid()} on {socket.gethostname()}"


def check_data_root(data_root: str) -> str | None:
    """None when this machine sees the data root as a writable folder, else one line naming it and the
    worker (run on every worker before a batch, and by every task)."""
    root = Path(data_root)
    if not root.is_dir():
        found = "no such folder" if not root.exists() else "not a folder"
    elif not os.access(root, os.W_OK | os.X_OK):
        found = "a folder it may not write"
    else:
        return None
    return (f"{worker_name()}: {root}: expected the batch's data root, found {found}; mount the shared data "
            "root at the same path on every worker (or pass --data-root)")


def run_stage(
    building: str,
    stage: str,
    data_root: str,
    config_dir: str,
    threads: int | None,
    first_of: list[str] | None,
    scheduler: str | None = None,
    after: Any = None,
    budget: str = "cpu",
) -> dict[str, Any]:
    """Run ``stage`` of ``building`` and return {"building", "stage", "ran", "seconds", "worker"}; raise
    ``StageFailed`` with the one-line error. ``first_of``: the building's stages, for the first task of a
    batch (the record starts anew); ``scheduler``: the address the stage fans its views out to (None:
    its own process); ``after``: the previous stage's result (Dask waits for it); ``budget``: the compute
    budget (``config.BUDGETS``) the batch was started with."""
    bad = check_data_root(data_root)
    if bad is not None:
        raise StageFailed(bad)
    layout = BuildingLayout(Path(data_root), building)
    layout.root.mkdir(exist_ok=True)
    if first_of is not None:
        record.start(layout, first_of)
    worker = worker_name()
    record.update(layout, stage, "running", worker=worker)
    t0 = time.perf_counter()
    try:
        _wait_for_lock(layout)
        log = layout.path("batch_log", stage=stage)
        code = _run_doit(building, stage, data_root, config_dir, threads, scheduler, log, budget)
        text = log.read_text(errors="replace")
    except (PipelineError, OSError) as e:
        code, text = -1, f"{stage}: {e}"
    seconds = round(time.perf_counter() - t0, 1)
    if code != 0:
        line = error_line(text, stage, code)
        record.update(layout, stage, "failed", worker=worker, error=line, seconds=seconds)
        raise StageFailed(f"{building} {stage}: {line}")
    ran = bool(re.search(rf"^\.  {re.escape(stage)}$", text, flags=re.M))
    record.update(layout, stage, "done", worker=worker, ran=ran, seconds=seconds)
    return {"building": building, "stage": stage, "ran": ran, "seconds": seconds, "worker": worker}


def _wait_for_lock(layout: BuildingLayout) -> None:
    """Wait until no other run holds the building (a retried task may start while the guard of the killed
    one is still ending it); then leave the lock to the doit run."""
    deadline = time.monotonic() + LOCK_WAIT_S
    while True:
        try:
            release(acquire(layout.lock))
            return
        except BuildingBusyError:
            if time.monotonic() > deadline:
                raise
            time.sleep(1.0)


def _run_doit(building: str, stage: str, data_root: str, config_dir: str, threads: int | None,
              scheduler: str | None, log: Path, budget: str) -> int:
    # the budget the batch was started with, not a remote worker's own environment's
    env = {**os.environ, CONFIG_DIR_ENV: config_dir, BUDGET_ENV: budget, "TQDM_DISABLE": "1"}
    env.pop(SCHEDULER_ENV, None)
    if threads is not None:  # the worker's share of its machine's cores
        env |= {var: str(threads) for var in COUNT_VARS}
    if scheduler is not None:
        env[SCHEDULER_ENV] = scheduler
    command = [sys.executable, "-m", "facade_pipeline.batch.guard", sys.executable, "-m", "doit", "-f",
               str(DODO), "-s", stage, f"building={building}", f"data_root={data_root}"]
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as out:
        return subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, env=env,
                              cwd=DODO.parent).returncode


_EXCEPTION = re.compile(r"^[A-Za-z_][\w.]*(Error|Exception|Interrupt|Exit)\b")


def error_line(text: str, stage: str, code: int) -> str:
    """The one line that says why the stage failed: its own (``stage: file: expected ..., found ...``) or
    doit's, else the exception a crash ended with, else the last line printed."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    own = [line for line in lines if line.startswith((f"{stage}: ", "doit: "))]
    if own:
        return own[-1]
    crash = [line for line in lines if _EXCEPTION.match(line)]
    if crash:
        return crash[-1]
    return lines[-1] if lines else f"exit code {code}, no output"
