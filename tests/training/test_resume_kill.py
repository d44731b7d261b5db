"""kill -9 in the middle of training: the rerun resumes from the last checkpoint and ends exactly where an
uninterrupted run ends (model, reflection MLP, optimiser state, log)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
ITERATIONS = 30


def _start(data_root: Path, ckpt: Path, out: Path) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "tests.training.resume_worker",
        str(data_root),
        str(ckpt),
        str(out),
        str(ITERATIONS),
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _checkpoint_iteration(ckpt: Path) -> int:
    try:
        return int(torch.load(ckpt, map_location="cpu", weights_only=True)["iteration"])
    except (FileNotFoundError, RuntimeError, EOFError, KeyError):
        return -1


def _equal(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    if torch.is_tensor(a):
        return torch.equal(a, b)
    return a == b


def test_kill_9_then_resume_equals_uninterrupted(synth64, tmp_path):
    data_root = synth64.data_root
    whole = _start(data_root, tmp_path / "a.pt", tmp_path / "a.out")  # runs beside the one we kill
    victim = _start(data_root, tmp_path / "b.pt", tmp_path / "b.out")
    t0 = time.time()
    while _checkpoint_iteration(tmp_path / "b.pt") < 6:
        assert victim.poll() is None, victim.communicate()
        # only a hang ends this wait: a live victim on a loaded machine may take minutes to its 6th step
        assert time.time() - t0 < 600, "no checkpoint in 600 s from a live training"
        time.sleep(0.05)
    victim.send_signal(signal.SIGKILL)
    assert victim.wait(30) == -signal.SIGKILL
    stopped_at = _checkpoint_iteration(tmp_path / "b.pt")
    assert 6 <= stopped_at < ITERATIONS and not (tmp_path / "b.out").exists()
    rerun = _start(data_root, tmp_path / "b.pt", tmp_path / "b.out")
    out, err = rerun.communicate(timeout=300)
    assert rerun.returncode == 0, err
    assert f"resumed from {stopped_at}" in out
    assert whole.wait(300) == 0, whole.communicate()
    a = torch.load(tmp_path / "a.out", weights_only=True)
    b = torch.load(tmp_path / "b.out", weights_only=True)
    assert len(a["log"]) == ITERATIONS // 5
    assert _equal(a, b)
