"""Benchmark of the ``synthesize`` stage: wall time and peak memory for the shipped scenes.

Targets: synthetic64 within 10 s and demo within 2 minutes on 2 CPU cores; peak memory bounded
by the image size, not by the number of views (checked by running demo with 15 and with 60 UAV views).

Each case runs in a fresh process (so peak RSS is its own) against a temporary data root. The script prints
a table and appends a dated section with the machine to benchmarks/RESULTS.md.

    python benchmarks/bench_synthesize.py [--no-record]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import machine, record_results

ROOT = Path(__file__).resolve().parents[1]

# (label, building, UAV views or None for the shipped number, target seconds or None)
CASES = [
    ("synthetic64", "synthetic64", None, 10.0),
    ("synthetic64_curved", "synthetic64_curved", None, 10.0),
    ("demo, 15 UAV views", "demo", 15, None),
    ("demo", "demo", None, 120.0),
]

CHILD = """
import dataclasses, json, resource, sys, time
t0 = time.perf_counter()
from facade_pipeline.layout import BuildingLayout
from stages import load_stage
from stages._runner import execute, load_params
stage = load_stage("synthesize")
params = load_params(stage, sys.argv[1])
if sys.argv[2] != "None":
    cams = dataclasses.replace(params.cameras, uav_count=int(sys.argv[2]))
    params = dataclasses.replace(params, cameras=cams)
m = execute(stage, BuildingLayout(sys.argv[3], sys.argv[1]), params)
print(json.dumps({"process_s": time.perf_counter() - t0, "stage_s": m["wall_time_s"],
                  "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                  "views": m["metrics"]["uav_views"] + m["metrics"]["frontal_views"],
                  "pixels": params.cameras.width_px * params.cameras.height_px,
                  "metrics": m["metrics"]}))
"""


def run_case(building: str, uav: int | None, data_root: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT), TQDM_DISABLE="1", FACADE_LOG_LEVEL="WARNING")
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", CHILD, building, str(uav), data_root], cwd=ROOT, env=env,
                         capture_output=True, text=True, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["wall_s"] = time.perf_counter() - t0  # includes interpreter start and imports
    return result


def table(rows: list[tuple[str, dict, float | None]]) -> str:
    lines = ["| case | views | px/view | wall s (process) | stage s | render s | peak MB | target | ok |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for label, r, target in rows:
        ok = "" if target is None else ("yes" if r["wall_s"] <= target else "NO")
        lines.append(f"| {label} | {r['views']} | {r['pixels']} | {r['wall_s']:.1f} | {r['stage_s']:.1f} | "
                     f"{r['metrics']['render_s']:.1f} | {r['peak_mb']:.0f} | "
                     f"{'' if target is None else f'<= {target:.0f} s'} | {ok} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-record", action="store_true", help="do not append to benchmarks/RESULTS.md")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_synth_") as tmp:
        for label, building, uav, target in CASES:
            rows.append((label, run_case(building, uav, tmp), target))
    by = {label: r for label, r, _ in rows}
    few, many = by["demo, 15 UAV views"], by["demo"]
    growth = many["peak_mb"] - few["peak_mb"]
    text = table(rows)
    note = (f"Peak memory with {many['views']} views minus with {few['views']} views: {growth:+.0f} MB "
            f"({'bounded by image size' if growth < 0.1 * few['peak_mb'] else 'GROWS with views'}). "
            f"demo rays: {many['metrics']['primary_rays']:,} primary, {many['metrics']['secondary_rays']:,} "
            f"secondary, {many['metrics']['ground_truth_rays']:,} ground-truth.")
    print(text)
    print(note)
    if not args.no_record:
        intro = ("Wall time and memory of the simulator per scene: the process, the stage alone, and its ray "
                 "tracing.")
        command = "`python benchmarks/bench_synthesize.py`"
        record_results(f"\n## synthesize\n\n{intro}\n\n{machine()} {command}\n\n{text}\n\n{note}\n")
    failed = [label for label, r, target in rows if target is not None and r["wall_s"] > target]
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
