"""Benchmark of the 2DGS renderer: forward + backward time and peak memory on 2 CPU threads.

Scenes: splats on a facade-like plane (40 m x 30 m, normals within ~10 degrees of the facade normal, a few
cm of relief, opacities 0.2-1, 8 feature channels) seen by a UAV-like camera 35 m away, 12 m up and yawed 25
degrees. Sizes and targets (seconds, forward + backward): (2k, 64x64) 0.015, (10k, 128x128) 0.15,
(50k, 256x256) 1.0, (200k, 512x384) 5.0. Each (case, backend) runs in a fresh process (so its peak RSS is its
own); times are the best of several repeats because other jobs share the 2 cores. The dense float64-capable
reference of the tests (every splat at every pixel) is timed, in float32, where it fits in memory, and the
ratio to the compiled backend is printed.

    python benchmarks/bench_splatting.py [--no-record] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from _common import machine, record_results

ROOT = Path(__file__).resolve().parents[1]

# (splats, width, height, target s)
CASES = [(2_000, 64, 64, 0.015), (10_000, 128, 128, 0.15), (50_000, 256, 256, 1.0), (200_000, 512, 384, 5.0)]
GPU_CASES = [(n, w, h) for n, w, h, _ in CASES] + [(1_000_000, 1920, 1080)]
GPU_TORCH_MAX_PIXELS_X_SPLATS = 200_000 * 512 * 384  # the exact torch backend on the GPU up to this size
TORCH_MAX_SPLATS = 10_000  # the pure-torch reference backend is timed up to this size
DENSE_MAX_PAIRS = 10_000_000  # splats x pixels up to which the dense reference is timed

CHILD = r"""
import json, math, resource, sys, time
import torch
torch.set_num_threads(2)
sys.path.insert(0, sys.argv[5])
from facade_pipeline.splatting import render_2dgs
from facade_pipeline.splatting.render import resolve_backend
from facade_pipeline.geometry.camera import look_at, intrinsics

n, width, height, backend, _, repeats, device = sys.argv[1:8]
n, width, height, repeats, device = int(n), int(width), int(height), int(repeats), torch.device(device)
cuda = device.type == "cuda"
def sync():
    if cuda:
        torch.cuda.synchronize()
g = torch.Generator().manual_seed(0)
def rand(*shape):
    return torch.rand(*shape, generator=g)

def quat_mul(a, b):
    aw, ax, ay, az = a.unbind(-1); bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw*bw - ax*bx - ay*by - az*bz, aw*bx + ax*bw + ay*bz - az*by,
                        aw*by - ax*bz + ay*bw + az*bx, aw*bz + ax*by - ay*bx + az*bw], -1)

def axis_quat(axis, angle):
    half = angle[:, None] / 2
    return torch.cat([torch.cos(half), torch.sin(half) * axis], -1)

facade_w, facade_h = 40.0, 30.0
means = torch.stack([(rand(n) - 0.5) * facade_w, (rand(n) - 0.5) * 0.05, rand(n) * facade_h], -1)
spacing = math.sqrt(facade_w * facade_h / n)
scales = spacing * 0.6 * (0.5 + rand(n, 2))
base = axis_quat(torch.tensor([1.0, 0, 0]), torch.full((n,), -math.pi / 2))  # local z -> world +y
tilt = axis_quat(torch.nn.functional.normalize(rand(n, 3) - 0.5, dim=-1), (rand(n) - 0.5) * 0.35)
spin = axis_quat(torch.tensor([0, 0, 1.0]), rand(n) * 2 * math.pi)
quats = quat_mul(quat_mul(base, tilt), spin)
opacities = 0.2 + 0.8 * rand(n)
features = rand(n, 8)
yaw = math.radians(25)
eye = [35 * math.sin(yaw), 35 * math.cos(yaw), 12.0]
cam_from_world = torch.tensor(look_at(eye, [0.0, 0.0, 15.0]), dtype=torch.float32, device=device)
f = 0.9 * width
K = torch.tensor(intrinsics(f, f, width / 2, height / 2), dtype=torch.float32, device=device)
params = [x.to(device).requires_grad_() for x in (means, quats, scales, opacities, features)]
weights = None

def step():
    global weights
    if backend == "dense":
        sys.path.insert(0, sys.argv[5] + "/tests/splatting")
        from dense_reference import render_dense
        out = render_dense(*params, cam_from_world, K, width, height)
    else:
        r = render_2dgs(*params, cam_from_world, K, width, height, backend=backend)
        out = {k: getattr(r, k) for k in ("features", "alpha", "depth_expected", "depth_median", "normal",
                                          "distortion")}
    if weights is None:
        weights = {k: torch.rand(v.shape, generator=g).to(device) for k, v in out.items()}
    loss = sum((out[k] * weights[k]).sum() for k in out)
    loss.backward()
    return float(out["alpha"].mean())

rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
chosen = backend if backend == "dense" else resolve_backend(backend, device)
if backend != "dense":
    step()  # warm-up (kernel load, allocator); the dense reference is too slow to run twice
    for p in params:
        p.grad = None
if cuda:
    torch.cuda.reset_peak_memory_stats()
times = []
for _ in range(repeats):
    sync()
    t0 = time.perf_counter()
    coverage = step()  # float(): synchronises
    sync()
    times.append(time.perf_counter() - t0)
    for p in params:
        p.grad = None
if cuda:
    peak = torch.cuda.max_memory_allocated() / 2**20
else:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"best_s": min(times), "median_s": sorted(times)[len(times) // 2], "backend": chosen,
                  "peak_mb": peak, "base_mb": rss0, "mean_alpha": coverage}))
"""


def run_case(n: int, width: int, height: int, backend: str, repeats: int, device: str = "cpu") -> dict | None:
    env = dict(os.environ, OMP_NUM_THREADS="2")
    args = [sys.executable, "-c", CHILD, str(n), str(width), str(height), backend, str(ROOT), str(repeats),
            device]
    out = subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        print(out.stderr[-2000:], file=sys.stderr)
        return None
    return json.loads(out.stdout.strip().splitlines()[-1])


def ratio(r: dict | None, base: dict | None) -> str:
    return "-" if r is None or base is None else f"{r['best_s'] / base['best_s']:.0f}x"


def fmt(r: dict | None, key: str = "best_s") -> str:
    return "-" if r is None else f"{r[key]:.4f}"


def gpu_table(repeats: int) -> str:
    """gsplat and the exact torch backend on the GPU, forward + backward."""
    import torch

    lines = [
        f"GPU: {torch.cuda.get_device_name(0)}, torch {torch.__version__}, CUDA {torch.version.cuda}",
        "",
        "| splats | image | gsplat best s (median) | gsplat peak GPU MB | torch (exact) best s | "
        "torch peak GPU MB | torch / gsplat | mean alpha |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for n, w, h in GPU_CASES:
        gs = run_case(n, w, h, "gsplat", repeats, "cuda")
        tr = run_case(n, w, h, "torch", 3, "cuda") if n * w * h <= GPU_TORCH_MAX_PIXELS_X_SPLATS else None
        line = (f"| {n:,} | {w}x{h} | {fmt(gs)} ({fmt(gs, 'median_s')}) | {fmt(gs, 'peak_mb')[:-2]} | "
                f"{fmt(tr)} | {fmt(tr, 'peak_mb')[:-2]} | {ratio(tr, gs)} | "
                f"{'-' if gs is None else round(gs['mean_alpha'], 3)} |")
        lines.append(line)
        print(line, flush=True)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--no-record", action="store_true", help="print only, do not append to RESULTS.md")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--cases", type=int, default=len(CASES), help="run only the first N cases")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    args = ap.parse_args()
    if args.device == "cuda":
        table = gpu_table(args.repeats)
        print(table)
        if not args.no_record:
            record_results(f"\n## Splatting speed on a GPU\n\n{machine()}\n\n{table}\n")
        return
    lines = ["| splats | image | target s | cpp best s (median) | cpp peak RSS MB | torch best s | "
             "dense ref best s | torch / cpp | dense / cpp | mean alpha | ok |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for n, w, h, target in CASES[: args.cases]:
        reps = args.repeats if n <= 50_000 else max(2, args.repeats // 2)
        cpp = run_case(n, w, h, "cpp", reps)
        torch_r = run_case(n, w, h, "torch", 2) if n <= TORCH_MAX_SPLATS else None
        dense = run_case(n, w, h, "dense", 1) if n * w * h <= DENSE_MAX_PAIRS else None
        ok = cpp is not None and cpp["backend"] == "cpp" and cpp["best_s"] <= target
        line = (f"| {n:,} | {w}x{h} | {target} | {fmt(cpp)} ({fmt(cpp, 'median_s')}) | "
                f"{fmt(cpp, 'peak_mb')[:-2]} | {fmt(torch_r)} | {fmt(dense)} | {ratio(torch_r, cpp)} | "
                f"{ratio(dense, cpp)} | "
                f"{'-' if cpp is None else round(cpp['mean_alpha'], 3)} | {'yes' if ok else 'NO'} |")
        lines.append(line)
        print(line, flush=True)
    table = "\n".join(lines)
    print(table)
    if not args.no_record:
        note = ("Forward + backward of `render_2dgs` (loss on all six maps), best of several runs in a fresh "
                "process per cell; other jobs shared the 2 cores, so medians are noisy. Peak RSS includes "
                "the interpreter and torch (~300 MB).")
        record_results(f"\n## Splatting speed\n\n{machine()}\n\n{note}\n\n{table}\n")


if __name__ == "__main__":
    main()
