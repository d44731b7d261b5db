"""How a stage process uses threads when it shares the machine with other work.

OpenMP runtimes (torch's, open3d's, the compiled splatting kernel's) keep idle worker threads spinning by
default; two processes on the same cores then burn each other's time (two torch training loops on two cores
took 4x as long as one, not 2x). Passive waiting gives idle cores back, and no pool is bigger than the cores
this process may run on (``os.sched_getaffinity``: a container's or ``taskset``'s limit, not the machine's).
OpenCV here runs its own pthreads pool (``cv2.getBuildInformation()``: "Parallel framework: pthreads"), which
no OpenMP variable reaches; ``OPENCV_FOR_THREADS_NUM`` sizes it when cv2 loads, as ``cv2.setNumThreads``
would, without importing cv2 in a stage that never uses it.

The runtimes read these variables once, when their library is loaded, so they are set before anything imports
torch, OpenCV, open3d or NumPy: ``python -m stages NAME`` does it first. A value the user set is kept;
``FACADE_THREAD_POLICY=off`` leaves the runtimes' own defaults (to measure what the policy changes).
"""

from __future__ import annotations

import os

#: set in the environment once the policy is in place (the stage CLI re-executes itself without it)
POLICY_ENV = "FACADE_THREAD_POLICY"
COUNT_VARS = (
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
)


def usable_cores() -> int:
    """Cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def thread_policy(environ: dict[str, str] | os._Environ[str]) -> dict[str, str]:
    """The variables to add to ``environ`` (those it already has are left as the user set them)."""
    if environ.get(POLICY_ENV) == "off":
        return {}
    wanted = {"OMP_WAIT_POLICY": "PASSIVE", POLICY_ENV: "1"}
    n = str(usable_cores())
    wanted |= {var: n for var in COUNT_VARS}
    return {k: v for k, v in wanted.items() if k not in environ}


def policy_in_place() -> bool:
    return os.environ.get(POLICY_ENV) in ("1", "off")


def apply_thread_policy() -> None:
    """Set the policy in this process's environment. Call before importing any numerical library."""
    os.environ.update(thread_policy(os.environ))
