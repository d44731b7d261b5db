"""The Python steps of benchmarks/gpu_check.sh on the CPU with tiny sizes: ``bench_train.py --speed`` from a
bundle, and the summary table read from the logs the check writes."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
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
    (tmp_path / "speed_gpu.log").write_text(run.stdout)
    (tmp_path / "tests.log").write_text("....ss\n4 passed, 2 skipped in 3.10s\n")
    point = {"variant": "mlp", "iterations": 1000, "wall_s": 34.2, "splats": 151000,
             "checks": [[100, 60000, 21.5], [500, 140000, 24.9], [1000, 151000, 24.1]],
             "stopped": "the run stopped",
             "training_views_psnr": 27.1,
             "imported": {"psnr": 24.5, "ssim": 0.8, "psnr_glass": 23.08, "psnr_glass_interior": 23.5,
                          "normal_error_glass_deg": 7.25, "lpips": 0.2},
             "aligned": {"psnr": 26.4, "ssim": 0.85, "psnr_glass": 26.01, "psnr_glass_interior": 26.5,
                         "normal_error_glass_deg": 7.25, "lpips": 0.15}}  # fmt: skip
    (tmp_path / "accuracy_1000.log").write_text("mlp: 1/1000\nresult: " + json.dumps(point) + "\n")
    (tmp_path / "skipped.log").write_text("skipped: 3000 iterations (projected 160 s, 90 s left)\n")
    gpu = _summary_module()
    speeds = gpu.SPEED.findall(run.stdout)
    assert [s[0] for s in speeds] == ["mlp", "sh"] and all(float(s[1]) > 0 for s in speeds)
    text = gpu.summary(tmp_path, "66", "300")
    assert "| CUDA tests | 4 passed, 2 skipped in 3.10s |" in text
    assert "target <= 12: " in text and "target <= 8: " in text
    assert "| 23.08 / 26.01, 24.50 / 26.40, 0.850, 0.150, 7.25, 151000, 34 |" in text
    assert "| speed, cpu budget | no result (speed_cpu.log) |" in text  # a missing step is said, not dropped
    assert "| accuracy point not run | 3000 iterations (projected 160 s, 90 s left) |" in text
    assert "| speed, gpu budget compiled | no result (speed_gpu_compiled.log) |" in text
    assert "| 21.50 (60000) at 100 / 24.90 (140000) at 500 / 24.10 (151000) at 1000 |" in text
    assert "| mlp, 1000 iterations: stopped | the run stopped |" in text
    assert "| speed, gpu budget, float32 MLP | no result (speed_gpu_fp32.log) |" in text
    assert text.count("\n| ") == 16  # header, rule, 14 rows
    svg = gpu.plot(tmp_path)
    assert svg.startswith("<svg") and "facade, 1000 iterations" in svg and "glass, 1000 iterations" in svg
