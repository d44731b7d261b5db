"""``python -m facade_pipeline.batch.guard COMMAND...``: run COMMAND in a process group of its own and
kill that group when the Dask worker that started this guard dies.

A worker killed with SIGKILL runs no code: without the guard its doit run and that run's stage would go on
as orphans, holding the building's lock, while the scheduler retries the task on another worker. The kernel
sends this process SIGTERM when its parent dies (``PR_SET_PDEATHSIG``, Linux); it then kills the whole
group, doit and the stage alike. The stage contract makes that safe: its manifest was deleted first and
its outputs are written under temporary names, so the retry starts it afresh.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def main(argv: list[str]) -> int:
    if not argv:
        print("usage: python -m facade_pipeline.batch.guard COMMAND [ARG...]", file=sys.stderr)
        return 2
    parent = os.getppid()
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:  # the worker died before the request took effect
        return 128 + signal.SIGTERM
    child = subprocess.Popen(argv, start_new_session=True)

    def stop(signum, frame):
        try:
            os.killpg(child.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    code = child.wait()
    return 128 - code if code < 0 else code  # killed by a signal: the shell's convention


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
