"""Compare the figures of two runs of the pipeline on one building: every number in the stages' manifests
(metrics) and in 08_evaluate/metrics.json, less timings and sizes of the machine, matched by their path.

    python benchmarks/compare_runs.py DATA_ROOT_A DATA_ROOT_B --building demo [--rtol 1e-6] [--record TITLE]

Prints the headline figures side by side and every figure that differs by more than ``--rtol`` (relative)
or appears in one run only; exits 1 when any does. A refactoring that must not change results is checked
by running the DAG at both commits into two data roots and comparing them. ``--record TITLE`` also puts
the table on the results page under ``## TITLE``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import machine, record_results  # noqa: E402

from facade_pipeline.layout import BuildingLayout  # noqa: E402
from stages import PIPELINE  # noqa: E402

#: parts of a figure's path that mark a timing or a machine-dependent size, not a result
NOT_RESULTS = ("seconds", "wall", "_s", "per_s", "peak", "memory", "time", "rays_per", "fps", "ms_")
#: the figures shown whether or not they differ (regular expressions over a figure's path)
HEADLINE = re.compile(
    r"^(04_regularize/(n_panels|n_parts|truth/.*mean.*)"
    r"|05_correct_mesh/truth/corrected/glass_.*_mean_.*"
    r"|06_bake_normals/(valid_fraction|truth/[^/]*_mean.*|truth/[^/]*_min)"
    r"|07_train/(final_train_psnr|test_psnr_glass|test_normal_error_glass_deg)"
    r"|metrics/variants/[^/]+/(test|test_aligned)/mean/(facade|glass|frames)/psnr"
    r"|metrics/variants/[^/]+/geometry/glass_.*_mean_.*)$"
)


def _flatten(value, prefix: str, out: dict[str, float | str]) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(v, f"{prefix}/{k}", out)
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _flatten(v, f"{prefix}[{i}]", out)
    elif isinstance(value, bool) or value is None or isinstance(value, str):
        out[prefix] = "null" if value is None else str(value)
    elif isinstance(value, (int, float)):
        out[prefix] = float(value)


def is_result(path: str) -> bool:
    leaf = path.rsplit("/", 1)[-1].lower()
    return not any(mark in leaf for mark in NOT_RESULTS)


def figures(layout: BuildingLayout) -> dict[str, float | str]:
    """Every result figure of one run: ``<stage folder>/<metric path>`` and ``metrics/<path>``."""
    out: dict[str, float | str] = {}
    for stage in PIPELINE:
        manifest = layout.manifest(stage)
        if manifest.is_file():
            _flatten(json.loads(manifest.read_text()).get("metrics", {}), manifest.parent.name, out)
    evaluation = layout.path("eval_metrics")
    if evaluation.is_file():
        _flatten(json.loads(evaluation.read_text()), "metrics", out)
    return {k: v for k, v in out.items() if is_result(k)}


def differs(a: float | str | None, b: float | str | None, rtol: float) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        if math.isnan(a) and math.isnan(b):
            return False
        return abs(a - b) > rtol * max(abs(a), abs(b), 1e-12)
    return a != b


def fmt(x: float | str | None) -> str:
    if x is None:
        return "(absent)"
    return f"{x:.6g}" if isinstance(x, float) else x


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root_a", type=Path)
    ap.add_argument("root_b", type=Path)
    ap.add_argument("--building", default="demo")
    ap.add_argument("--rtol", type=float, default=1e-6, help="relative difference that counts (default 1e-6)")
    ap.add_argument("--record", metavar="TITLE", help="put the headline table on the results page (## TITLE)")
    a = ap.parse_args()
    fa, fb = figures(BuildingLayout(a.root_a, a.building)), figures(BuildingLayout(a.root_b, a.building))
    if not fa or not fb:
        missing = a.root_a / a.building if not fa else a.root_b / a.building
        print(f"{missing}: expected a building with stage manifests, found none", file=sys.stderr)
        return 2
    keys = sorted(set(fa) | set(fb))
    head = [k for k in keys if HEADLINE.match(k)]
    diff = [k for k in keys if differs(fa.get(k), fb.get(k), a.rtol)]
    lines = [
        f"{len(keys)} figures of {a.building}; {len(diff)} differ by more than rtol {a.rtol:g} or are in "
        "one run only.",
        "",
        "| figure | run A | run B |",
        "| --- | --- | --- |",
        *[f"| `{k}` | {fmt(fa.get(k))} | {fmt(fb.get(k))} |" for k in head if k not in diff],
        *[f"| **`{k}`** | {fmt(fa.get(k))} | {fmt(fb.get(k))} |" for k in diff],
    ]
    table = "\n".join(lines)
    print(table)
    if a.record:
        by_stage: dict[str, int] = {}
        for k in diff:
            stage = k.split("/", 1)[0]
            by_stage[stage] = by_stage.get(stage, 0) + 1
        where = ", ".join(f"{stage} {n}" for stage, n in sorted(by_stage.items())) or "none"
        short = "\n".join(
            [
                f"{len(keys)} figures of {a.building}; differing by more than rtol {a.rtol:g} or in one run "
                f"only, by stage folder: {where}.",
                "",
                "| figure | run A | run B |",
                "| --- | --- | --- |",
                *[
                    f"| {'**' if k in diff else ''}`{k}`{'**' if k in diff else ''} | {fmt(fa.get(k))} | "
                    f"{fmt(fb.get(k))} |"
                    for k in head
                ],
            ]
        )
        record_results(
            f"## {a.record}\n\n{machine()} Run A: `{a.root_a}`, run B: `{a.root_b}`. Command: "
            f"`python benchmarks/compare_runs.py A B --building {a.building} --record ...` (headline "
            f"figures; the script prints every figure that differs).\n\n{short}\n"
        )
    return 1 if diff else 0


if __name__ == "__main__":
    raise SystemExit(main())
