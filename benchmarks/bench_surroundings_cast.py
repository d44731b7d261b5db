"""The environment proxy's ray cast against the surroundings on the CPU: ``Surroundings.hit`` of this tree
against that of an earlier revision (``--base``, e.g. the last one that cast through open3d), in one process,
alternating, on demo's surroundings (from a training bundle) and reflected rays from its facade.

    .venv/bin/python benchmarks/bench_surroundings_cast.py --bundle demo.npz --base 97acd00 [--rays 8192]

The bundle comes from ``benchmarks/bench_train.py --save-bundle``. Prints the median milliseconds per call of
each and their ratio, and how many rays are classified alike (floor, block, sky).
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import machine  # noqa: E402

from facade_pipeline.shading.proxy import proxy_reach_m  # noqa: E402
from facade_pipeline.shading.surroundings import Surroundings  # noqa: E402
from facade_pipeline.training.data import load_bundle  # noqa: E402


def base_surroundings(rev: str):
    """The ``Surroundings`` class of revision ``rev`` (its module file alone, imported under another name)."""
    text = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:facade_pipeline/shading/surroundings.py"],
                          check=True, capture_output=True, text=True).stdout  # fmt: skip
    path = Path(tempfile.mkdtemp()) / "base_surroundings.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("base_surroundings", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.Surroundings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--base", required=True, help="the git revision to compare with")
    ap.add_argument("--rays", type=int, default=8192, help="rays per call (a 128 px patch has up to 16384)")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--cell-m", type=float, default=1.0)
    a = ap.parse_args()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    data = load_bundle(a.bundle)
    lo, hi = (torch.as_tensor(b, dtype=torch.float32) for b in data.bounds)
    reach = proxy_reach_m(lo, hi)
    new = Surroundings(lo, hi, reach, a.cell_m, data.init.points)
    in_torch = Surroundings(lo, hi, reach, a.cell_m, data.init.points)
    in_torch._caster = False  # as where open3d is not importable: the cast in torch, as on a GPU
    old = base_surroundings(a.base)(lo, hi, reach, a.cell_m, data.init.points)
    rng = np.random.default_rng(0)
    x = rng.uniform(data.bounds[0], data.bounds[1], (a.rays, 3))
    w = rng.normal(size=(a.rays, 3))
    w[:, 1] = np.abs(w[:, 1])  # away from the facade, which faces +y
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    x, w = torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(w, dtype=torch.float32)
    runs = (("base", old), ("this tree", new), ("this tree, torch cast", in_torch))
    times = {name: [] for name, _ in runs}
    outs = {}
    for _ in range(a.repeats):
        for name, s in runs:
            t0 = time.perf_counter()
            outs[name] = s.hit(x, w)
            times[name].append(1000.0 * (time.perf_counter() - t0))
    f0, _, w0 = outs["base"]
    ms = {k: statistics.median(v) for k, v in times.items()}
    n = new.heights.shape[1]
    print(machine())
    blocks = int((new.heights[1] > 0).sum())
    print(f"demo's surroundings: {n} x {n} cells of {a.cell_m} m, {blocks} with a block; {a.rays} rays per "
          f"call, median of {a.repeats}")
    for name, _ in runs:
        f1, _, w1 = outs[name]
        same = float(((f0 == f1) & ((w0[:, 1] < 0) == (w1[:, 1] < 0))).float().mean())
        ratio = ms[name] / ms["base"]
        print(f"{name}: {ms[name]:.1f} ms per call, {ratio:.2f} x base {a.base}; rays classified as base "
              f"does: {100 * same:.2f} %")


if __name__ == "__main__":
    main()
