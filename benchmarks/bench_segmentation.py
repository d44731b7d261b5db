"""Accuracy and time per image of rectify + segment_panels on the shipped synthetic scenes against gt/;
appends a section to benchmarks/RESULTS.md.

    .venv/bin/python benchmarks/bench_segmentation.py [--data-root /tmp/bench] [buildings...]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import append_results, machine  # noqa: E402

from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.manifest import read_manifest  # noqa: E402
from facade_pipeline.scene import ImportedScene  # noqa: E402
from facade_pipeline.segmentation.accuracy import evaluate_view  # noqa: E402


def row(building: str, layout: BuildingLayout) -> str:
    scene = ImportedScene.load(layout)
    panels, gt_scene = (json.loads(layout.gt(k).read_text()) for k in ("panels", "scene"))
    r = [
        evaluate_view(layout, v, panels, gt_scene, 4)
        for v in scene.frontal_views
    ]
    err = np.concatenate([v["corner_errors_px"] for v in r])
    iou_c = np.concatenate([v["iou_complete"] for v in r])
    iou_x = np.concatenate([v["iou_cut"] for v in r])
    vis_c = np.concatenate([v["iou_visible_glass_complete"] for v in r])
    straight = np.concatenate([v["edge_straightness_px"] for v in r])
    exact = sum(v["n_pred"] == v["n_true"] for v in r)
    t_rect = read_manifest(layout, "rectify").metrics["seconds_per_view"]
    t_seg = read_manifest(layout, "segment_panels").metrics["seconds_per_view"]
    sizes = sorted({f"{v.camera.width}x{v.camera.height}" for v in scene.frontal_views})
    return (
        f"| {building} | {len(r)} ({', '.join(sizes)} px) | "
        f"{max(v['rectify_residual_px'] for v in r):.4f} | {straight.max():.3f} | "
        f"{np.median(err):.2f} | {np.percentile(err, 95):.2f} | {err.max():.2f} | {exact}/{len(r)} | "
        f"{iou_c.min():.3f} / {np.median(iou_c):.3f} ({len(iou_c)}) | {iou_x.min():.2f} / "
        f"{np.median(iou_x):.2f} "
        f"({len(iou_x)}) | {vis_c.min():.3f} / {np.median(vis_c):.3f} | {t_rect:.2f} + {t_seg:.2f} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data-root", default="/tmp/bench_segmentation")
    ap.add_argument("buildings", nargs="*", default=["synthetic64", "synthetic64_curved", "demo"])
    args = ap.parse_args()
    env = {**os.environ, "TQDM_DISABLE": "1"}
    rows = []
    for b in args.buildings:
        subprocess.run(
            [
                sys.executable,
                "-m",
                "doit",
                "-f",
                str(REPO / "dodo.py"),
                "segment_panels",
                f"building={b}",
                f"data_root={args.data_root}",
            ],
            cwd=REPO,
            env=env,
            check=True,
            capture_output=True,
        )
        rows.append(row(b, BuildingLayout(Path(args.data_root), b)))
    text = "\n".join(
        [
            f"\n## rectify + segment_panels, {datetime.datetime.now():%Y-%m-%d %H:%M}\n",
            f"{machine()}\n",
            "Against gt/ (reflections on). Corner errors: predicted corners off the image border "
            "against the nearest "
            "projected true glass corner (true camera, gt/frontal/sparse/0). "
            "IoU: per predicted panel against the true panel it overlaps most (its outline projected "
            "through the true camera, glass behind the frames included), "
            "min / median (count), whole panels and panels cut by the border separately; and, for whole "
            "panels, against the visible glass (gt's glass mask). Targets: "
            "residual <= 0.5 "
            "px, straightness <= 1 px, corner median <= 1 px and p95 <= 2 px, count exact, IoU >= 0.95.\n",
            "| building | frontal views (size) | warp residual max px | true edges after rectification: max "
            "deviation px | corner "
            "median px | corner p95 px | corner max px | views with exact count | IoU whole panels | "
            "IoU cut panels | IoU whole panels vs visible glass | "
            "s per view (rectify + segment) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
            *rows,
            "",
        ]
    )
    append_results(text)
    print(text)


if __name__ == "__main__":
    main()
