"""train_gs's training loop on the CPU, this tree against an earlier revision (``--base``), from one training
bundle, alternating, so that a change's cost in time shows beside the revision it is measured against.

    .venv/bin/python benchmarks/bench_train_vs.py --bundle demo.npz --base 97acd00 [--only mlp,sh]
        [--iterations 200] [--rounds 3] [--this-args "--lowpass-sigma-px 0.5"] [--base-args ""]

The bundle comes from ``benchmarks/bench_train.py --save-bundle``. Each run is a fresh process of that
revision's own ``bench_train.py --bundle ... --only VARIANT --iterations N``, timed over ``train()`` from
its 10th iteration to its end (one-time work, such as loading the C++ kernel, left out; the held-out
measurement too), so that both revisions train the same steps from the same data
whatever their other code. Settings that one revision's bench lacks (e.g. ``--lowpass-sigma-px``) are passed
to one side only (``--this-args``, ``--base-args``). The base revision's tree is extracted with ``git
archive`` into a temporary folder (its C++ kernel is built on its first run: a warm-up run of each side comes
first and is not counted). Prints seconds per run and the median ratio of this tree to the base, per variant.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from _common import machine  # noqa: E402

# Run inside the revision's tree: its bench_train with the measurement patched out and train() timed.
DRIVER = """
import collections, sys, time
import bench_train as b
orig = b.train
WARM = 10
def timed(tr, *a, **k):
    marks = {}
    def progress(it, total, out):
        if it == WARM:
            marks["warm"] = time.perf_counter()
    k["progress"] = progress
    out = orig(tr, *a, **k)
    print(f"\\nTRAIN_S {time.perf_counter() - marks['warm']:.3f}", flush=True)
    return out
b.train = timed
b.measure = lambda *a, **k: (collections.defaultdict(float), None)
if hasattr(b, "whole_view_psnr"):
    b.whole_view_psnr = lambda *a, **k: 0.0
b.report = lambda *a, **k: None
sys.argv = ["bench_train.py"] + sys.argv[1:]
b.main()
"""


def run(tree: Path, bundle: str, variant: str, iterations: int, extra: list[str]) -> float:
    cmd = [sys.executable, "-c", DRIVER, "--bundle", bundle, "--only", variant, "--iterations",
           str(iterations), "--no-write", *extra]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": f"{tree}:{tree / 'benchmarks'}"}
    p = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    times = [float(line.split()[1]) for line in p.stdout.splitlines() if line.startswith("TRAIN_S")]
    if p.returncode != 0 or not times:
        sys.exit(f"bench_train_vs: {tree} {variant}: {(p.stderr or p.stdout).strip().splitlines()[-1:]}")
    return times[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--base", required=True, help="the git revision to compare with")
    ap.add_argument("--only", default="mlp,sh")
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--this-args", default="", help="extra bench_train.py options for this tree only")
    ap.add_argument("--base-args", default="", help="extra bench_train.py options for the base only")
    a = ap.parse_args()
    bundle = str(Path(a.bundle).resolve())
    with tempfile.TemporaryDirectory(prefix="bench-train-vs-") as tmp:
        compare(a, bundle, Path(tmp))


def compare(a: argparse.Namespace, bundle: str, base_dir: Path) -> None:
    archive = subprocess.run(["git", "-C", str(REPO), "archive", a.base], check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(base_dir)], input=archive.stdout, check=True)
    sides = {"base": (base_dir, shlex.split(a.base_args)), "this": (REPO, shlex.split(a.this_args))}
    print(f"{machine()} Base {a.base}; {a.iterations} iterations per run, {a.rounds} rounds.", flush=True)
    for variant in a.only.split(","):
        for tree, extra in sides.values():  # warm-up: builds each tree's kernel
            run(tree, bundle, variant, 12, extra)
        secs = {name: [] for name in sides}
        for r in range(a.rounds):
            for name, (tree, extra) in sides.items():
                secs[name].append(run(tree, bundle, variant, a.iterations, extra))
                print(f"  {variant} round {r + 1} {name}: {secs[name][-1]:.1f} s", flush=True)
        ratio = statistics.median(t / b for t, b in zip(secs["this"], secs["base"], strict=True))
        print(f"{variant}: base {statistics.median(secs['base']):.1f} s, this tree "
              f"{statistics.median(secs['this']):.1f} s (median); this / base {ratio:.2f} (median of rounds)",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
