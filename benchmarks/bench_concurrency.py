"""Running beside other work: one train_gs run on synthetic64 alone, then two at once (two copies of the
building), with the stages' thread policy (``facade_pipeline/threads.py``: passive OpenMP waiting, pools no
bigger than the usable cores) and without it (``FACADE_THREAD_POLICY=off``: the runtimes' defaults, where
idle threads spin). Wall and CPU time of each run; the target is a pair within 1.2x of twice the lone run.

    python benchmarks/bench_concurrency.py [--no-record] [--building synthetic64]

The building is made once (doit, up to bake_normals) under a temporary data root; each timed run starts
from no checkpoint.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import machine, record_results

ROOT = Path(__file__).resolve().parents[1]


def _prepare(building: str, tmp: Path) -> list[Path]:
    """Two data roots, each with the building run up to bake_normals."""
    a = tmp / "a"
    subprocess.run(
        [sys.executable, "-m", "doit", "-f", str(ROOT / "dodo.py"), "bake_normals", f"building={building}",
         f"data_root={a}"], cwd=ROOT, check=True, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    b = tmp / "b"
    shutil.copytree(a, b, symlinks=True)
    return [a, b]


def _start(building: str, root: Path, policy: bool) -> subprocess.Popen:
    shutil.rmtree(root / building / "07_train", ignore_errors=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMP_", "MKL_", "OPENBLAS_"))}
    env |= {"TQDM_DISABLE": "1", "FACADE_THREAD_POLICY": "1" if policy else "off"}
    if policy:
        env.pop("FACADE_THREAD_POLICY")  # as a user's run: the stage CLI puts the policy in place
    cmd = [sys.executable, "-m", "stages", "train_gs", "--building", building, "--data-root", str(root)]
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _wait(procs: list[subprocess.Popen], t0: float) -> list[tuple[float, float]]:
    """(wall s, CPU s) of each process, in the order given."""
    done: dict[int, tuple[float, float]] = {}
    while len(done) < len(procs):
        pid, status, usage = os.wait4(-1, 0)
        done[pid] = (time.perf_counter() - t0, usage.ru_utime + usage.ru_stime)
        if os.waitstatus_to_exitcode(status) != 0:
            proc = next(p for p in procs if p.pid == pid)
            raise SystemExit(f"train_gs failed: {proc.stderr.read().decode()[-2000:]}")
    for p in procs:
        p.returncode = 0
    return [done[p.pid] for p in procs]


def measure(building: str, roots: list[Path], policy: bool) -> dict[str, list[tuple[float, float]]]:
    t0 = time.perf_counter()
    alone = _wait([_start(building, roots[0], policy)], t0)
    t0 = time.perf_counter()
    pair = _wait([_start(building, r, policy) for r in roots], t0)
    return {"alone": alone, "pair": pair}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--building", default="synthetic64")
    ap.add_argument("--no-record", action="store_true", help="print only; do not append to RESULTS.md")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-concurrency-") as tmp:
        roots = _prepare(args.building, Path(tmp))
        rows = []
        for policy in (False, True):
            r = measure(args.building, roots, policy)
            ((wall1, cpu1),) = r["alone"]
            pair_wall = max(w for w, _ in r["pair"])
            pair_cpu = sum(c for _, c in r["pair"])
            rows.append(
                f"| {'passive, pools = usable cores' if policy else 'runtime defaults (off)'} | {wall1:.1f} "
                f"| {cpu1:.1f} | {pair_wall:.1f} | {pair_cpu:.1f} | {pair_wall / (2 * wall1):.2f} |"
            )
            print(rows[-1], flush=True)
    command = "python benchmarks/bench_concurrency.py" + (
        "" if args.building == "synthetic64" else f" --building {args.building}")
    text = (
        "## Two runs at once\n\n"
        f"train_gs on {args.building} alone, then two at once (two copies of the building), with the "
        "stages' thread policy (passive OpenMP waiting, pools no bigger than the usable cores) and without "
        "it (`FACADE_THREAD_POLICY=off`). Target: the pair's wall time within 1.2x of twice the lone "
        "run's.\n\n"
        f"{machine()}\n`{command}`\n\n"
        "| thread policy | alone: wall s | alone: CPU s | pair: wall s (slower) | pair: CPU s (both) "
        "| pair wall / (2 x alone) |\n| --- | --- | --- | --- | --- | --- |\n" + "\n".join(rows) + "\n"
    )
    print(text)
    if not args.no_record:
        record_results(text)


if __name__ == "__main__":
    main()
