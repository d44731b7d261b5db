"""The thread policy of a stage process: passive waiting, every pool (OpenMP, BLAS, OpenCV's pthreads) sized
to the cores the process may run on, a user's own values kept, and nothing set when it is switched off."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from facade_pipeline import threads
from facade_pipeline.threads import COUNT_VARS, POLICY_ENV, apply_thread_policy, thread_policy, usable_cores

REPO = Path(__file__).resolve().parents[1]


def test_the_policy_sets_passive_waiting_and_every_pool_to_the_usable_cores(monkeypatch):
    monkeypatch.setattr(threads.os, "sched_getaffinity", lambda pid: {0, 2, 5})
    assert usable_cores() == 3
    wanted = thread_policy({})
    assert wanted == {"OMP_WAIT_POLICY": "PASSIVE", POLICY_ENV: "1", **{v: "3" for v in COUNT_VARS}}
    assert "OPENCV_FOR_THREADS_NUM" in wanted and "OMP_NUM_THREADS" in wanted


def test_a_users_values_are_kept_and_off_sets_nothing(monkeypatch):
    monkeypatch.setattr(threads.os, "sched_getaffinity", lambda pid: {0, 1})
    mine = {"OMP_NUM_THREADS": "7", "OMP_WAIT_POLICY": "ACTIVE"}
    wanted = thread_policy(mine)
    assert not set(wanted) & set(mine) and wanted["MKL_NUM_THREADS"] == "2"
    assert thread_policy({POLICY_ENV: "off"}) == {}
    env = {POLICY_ENV: "off"}
    monkeypatch.setattr(threads.os, "environ", env)
    apply_thread_policy()
    assert env == {POLICY_ENV: "off"}


def test_without_affinity_the_cpu_count_is_used(monkeypatch):
    def unsupported(pid):
        raise OSError("no affinity here")

    monkeypatch.setattr(threads.os, "sched_getaffinity", unsupported)
    monkeypatch.setattr(threads.os, "cpu_count", lambda: 6)
    assert usable_cores() == 6


_REPORT = (
    "from facade_pipeline.threads import apply_thread_policy; apply_thread_policy(); "
    "import os, cv2, torch; "
    "print(cv2.getNumThreads(), torch.get_num_threads(), os.environ.get('OMP_WAIT_POLICY'))"
)


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs os.sched_setaffinity")
def test_opencv_and_torch_pools_follow_the_policy_in_a_new_process():
    """A process pinned to one core: the policy, set before cv2 and torch load, gives each pool one thread
    and passive waiting; OpenCV's pool takes its size from the policy's variable (here one a user set)."""
    env = {k: v for k, v in os.environ.items() if k not in (*COUNT_VARS, "OMP_WAIT_POLICY", POLICY_ENV)}
    env["PYTHONPATH"] = str(REPO)
    one = next(iter(os.sched_getaffinity(0)))

    def run(extra):
        out = subprocess.run([sys.executable, "-c", _REPORT], env={**env, **extra}, cwd=REPO, text=True,
                             capture_output=True, preexec_fn=lambda: os.sched_setaffinity(0, {one}),
                             timeout=300)  # fmt: skip
        assert out.returncode == 0, out.stderr
        return out.stdout.split()

    assert run({}) == ["1", "1", "PASSIVE"]
    # switched off, the libraries choose for themselves and no variable is set
    assert run({POLICY_ENV: "off"})[2] == "None"
    # a count the user set is what the pools get
    assert run({"OPENCV_FOR_THREADS_NUM": "3"})[0] == "3"
