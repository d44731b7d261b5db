"""The Python steps of benchmarks/gpu_check.sh on the CPU with tiny sizes: ``bench_train.py --speed`` from a
bundle, and the summary table read from the logs the check writes."""

from __future__ import annotations

import dataclasses
import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from facade_pipeline.training.data import ExposureEstimate, save_bundle
from tests.training.scenes import hard_scene

REPO = Path(__file__).resolve().parents[2]


def _summary_module():
    spec = importlib.util.spec_from_file_location("gpu_summary", REPO / "benchmarks" / "gpu_summary.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_speed_from_a_bundle_on_the_cpu_and_its_summary(tmp_path):
    data = hard_scene()
    est = ExposureEstimate(np.zeros((len(data.views), 3), np.float32), np.full(len(data.views), 100))
    save_bundle(dataclasses.replace(data, exposure=est), tmp_path / "tiny.npz")
    cmd = [sys.executable, "benchmarks/bench_train.py", "--bundle", str(tmp_path / "tiny.npz"), "--device",
           "cpu", "--patch-px", "0", "--init-points", "40", "--max-gaussians", "80", "--speed", "2",
           "--warmup", "1", "--only", "mlp,sh", "--lowpass-sigma-px", "0.7071", "--set", "seed=3",
           "--no-write"]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "set with `--set`: `seed=3`" in run.stdout  # a figure's table says what it was measured with
    (tmp_path / "speed.log").write_text(run.stdout)
    (tmp_path / "tests.log").write_text("....ss\n4 passed, 2 skipped in 3.10s\n")
    (tmp_path / "accuracy.log").write_text(
        "mlp: 1/9\nmlp: glass PSNR 23.08 dB, facade PSNR 24.50 dB, normal error 7.25 deg, 34 s; "
        "aligned: glass PSNR 26.01 dB\n"
    )
    gpu = _summary_module()
    speeds = gpu.SPEED.findall(run.stdout)
    assert [s[0] for s in speeds] == ["mlp", "sh"] and all(float(s[1]) > 0 for s in speeds)
    text = gpu.summary(tmp_path, "66", "1000", "300")
    assert "| CUDA tests | 4 passed, 2 skipped in 3.10s |" in text
    assert "target <= 12: " in text and "target <= 8: " in text
    assert "| 23.08 / 26.01, 24.50, 7.25, 34 |" in text
    assert text.count("\n| ") == 10  # header, rule, 8 rows
