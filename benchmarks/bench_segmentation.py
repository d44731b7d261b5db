"""Accuracy and time per image of rectify + segment_panels on the shipped synthetic scenes against gt/,
and on real photos with truth (``--real DIR``: a folder laid out as shared/real/gcw_dev, made into the
building ``--real-building`` by scripts/make_gcw_building.py and run through regularize_corners); appends a
section to benchmarks/RESULTS.md. ``--losses``: what the glass masks lose against the truth, per class of
wrong pixel (``real_truth.mask_losses``), on the real photos and on ``real_like`` scored as they are
(``accuracy.truth_as_real``).

    .venv/bin/python benchmarks/bench_segmentation.py [--data-root /tmp/bench] \
        [--real ../shared/real/gcw_dev [--exposures]] [--losses] [buildings...]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import machine, record_results  # noqa: E402

from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.manifest import read_manifest  # noqa: E402
from facade_pipeline.panels3d.model import PanelSet  # noqa: E402
from facade_pipeline.scene import ImportedScene  # noqa: E402
from facade_pipeline.segmentation.accuracy import evaluate_view, truth_as_real  # noqa: E402
from facade_pipeline.segmentation.real_truth import (  # noqa: E402
    EXPOSURES,
    LOSS_CLASSES,
    evaluate_building,
    evaluate_photo,
    exposed_copy,
    grid_corner_errors_m,
    mask_losses,
    summary,
)
from facade_pipeline.segmentation.result import ViewSegmentation  # noqa: E402
from facade_pipeline.synthetic.truth import SyntheticTruth  # noqa: E402
from scripts.make_gcw_building import WORLD_FROM_WALL  # noqa: E402


def row(building: str, layout: BuildingLayout) -> str:
    scene = ImportedScene.load(layout)
    truth = SyntheticTruth.load(layout, scene.georef_from_local)
    r = [evaluate_view(layout, v, truth, 4) for v in scene.frontal_views]
    err = np.concatenate([v["corner_errors_px"] for v in r])
    iou_c = np.concatenate([v["iou_complete"] for v in r])
    iou_x = np.concatenate([v["iou_cut"] for v in r])
    vis_c = np.concatenate([v["iou_visible_glass_complete"] for v in r])
    straight = np.concatenate([v["edge_straightness_px"] for v in r])
    exact = sum(v["n_pred"] == v["n_true"] for v in r)
    t_rect = read_manifest(layout, "rectify").metrics["seconds_per_view"]
    t_seg = read_manifest(layout, "segment_panels").metrics["seconds_per_view"]
    sizes = sorted({f"{v.camera.width}x{v.camera.height}" for v in scene.frontal_views})
    e3 = panel_corner_errors_mm(layout, truth)
    return (
        f"| {building} | {len(r)} ({', '.join(sizes)}) | "
        f"{max(v['rectify_residual_px'] for v in r):.4f} | {straight.max():.3f} | "
        f"{np.median(err):.2f} / {np.percentile(err, 95):.2f} / {err.max():.2f} | {exact}/{len(r)} | "
        f"{iou_c.min():.3f} / {np.median(iou_c):.3f} ({len(iou_c)}) | {iou_x.min():.2f} / "
        f"{np.median(iou_x):.2f} "
        f"({len(iou_x)}) | {vis_c.min():.3f} / {np.median(vis_c):.3f} | "
        + ("-" if e3 is None else f"{np.median(e3):.0f} / {e3.max():.0f} ({len(e3) // 4})")
        + f" | {t_rect:.2f} + {t_seg:.2f} |"
    )


def panel_corner_errors_mm(layout: BuildingLayout, truth: SyntheticTruth) -> np.ndarray | None:
    """Each corner of regularize_corners' 3D panels against the nearest true glass corner (mm); None
    where that stage has not run (``--task segment_panels``)."""
    path = layout.path("regularize_panels")
    if not path.is_file():
        return None
    panels = PanelSet.load(path).panels
    c = np.array([p.corners for p in panels], float).reshape(-1, 3)
    t = truth.panel_corners().reshape(-1, 3)
    return 1000 * np.linalg.norm(c[:, None] - t[None], axis=2).min(axis=1)


def real_row(src: Path, building: str, data_root: Path, env: dict, label: str | None = None) -> str:
    """The targets' figures on real photos with truth (facade_pipeline/segmentation/real_truth.py), in a
    row named ``label`` (the building's name where None)."""
    subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(src), "--building",
                    building, "--data-root", str(data_root), "--force"], cwd=REPO, env=env, check=True,
                   capture_output=True)
    _doit("regularize_corners", building, data_root, env)
    layout = BuildingLayout(data_root, building)
    s = summary(evaluate_building(layout, src))
    panels = PanelSet.load(layout.path("regularize_panels")).panels
    c = np.array([p.corners for p in panels], float).reshape(-1, 3)
    wall = c @ WORLD_FROM_WALL[:3, :3]  # world -> wall frame (a rotation)
    e3 = grid_corner_errors_m(wall, (0.1032, 0.1532), (0.0932, 0.1432)) * 1000
    scene = ImportedScene.load(layout)
    mp = np.mean([v.camera.width * v.camera.height for v in scene.frontal_views]) / 1e6
    t_rect = read_manifest(layout, "rectify").metrics["seconds_per_view"] / mp
    t_seg = read_manifest(layout, "segment_panels").metrics["seconds_per_view"] / mp
    found = f"{s['found']}/{s['whole_panes']} ({100 * s['found_fraction']:.0f} %)"
    return (f"| {label or building} | {s['photos']} | {found} | "
            f"{s['mask_iou_median']:.3f} / {s['mask_iou_min']:.3f} | {s['corner_error_median_px']:.2f} | "
            f"{s['complete_less_than_half_glass']} of {s['complete_panels']} | {len(panels)} | "
            f"{np.median(e3):.1f} / {e3.max():.1f} | {t_rect:.2f} + {t_seg:.2f} |")


def truth_views(layout: BuildingLayout, src: Path | None = None):
    """(stem, segmentation, truth mask [H, W] bool, pane outlines, photo [H, W, 3] 8-bit) of every frontal
    view with truth: real photos' from ``src`` (gcw_dev's layout), a synthetic building's from its gt/
    (``accuracy.truth_as_real``) where ``src`` is None."""
    scene = ImportedScene.load(layout)
    truth = None if src is not None else SyntheticTruth.load(layout, scene.georef_from_local)
    panes = None if src is None else json.loads((src / "panes.json").read_text())
    for v in scene.frontal_views:
        if truth is not None:
            mask, outlines = truth_as_real(truth, v.stem)
        else:
            m = cv2.imread(str(src / "masks" / f"{v.stem}.png"), cv2.IMREAD_GRAYSCALE)
            if m is None or v.stem not in panes:
                continue
            mask, outlines = m > 127, panes[v.stem]
        seg = ViewSegmentation.load(layout, v.stem, v.camera.width, v.camera.height)
        yield v.stem, seg, mask, outlines, cv2.imread(str(layout.import_frontal_image(v.stem)))


def synthetic_real_row(building: str, layout: BuildingLayout) -> str:
    """A synthetic building's row of the real photos' table (``truth_as_real``: its gt/ as their truth),
    without the 3D columns (the synthetic table has them against the true corners)."""
    per_photo = {stem: evaluate_photo(seg, mask.astype(np.uint8) * 255, outlines)
                 for stem, seg, mask, outlines, _ in truth_views(layout)}
    s = summary(per_photo)
    found = f"{s['found']}/{s['whole_panes']} ({100 * s['found_fraction']:.0f} %)"
    return (f"| {building} (gt/ as the photos' truth) | {s['photos']} | {found} | "
            f"{s['mask_iou_median']:.3f} / {s['mask_iou_min']:.3f} | {s['corner_error_median_px']:.2f} | "
            f"{s['complete_less_than_half_glass']} of {s['complete_panels']} | - | - | - |")


def loss_rows(label: str, layout: BuildingLayout, src: Path | None) -> list[str]:
    """Rows of the losses table: each photo's mask IoU and the IoU it would gain with each class of wrong
    pixel right (``real_truth.mask_losses``), the median offset of the found whole panes' sides and the
    cut panes found, then the mean over the photos."""
    rows, gains, offsets = [], [], []
    cut = np.zeros(2, int)
    for stem, seg, mask, outlines, image in truth_views(layout, src):
        r = mask_losses(seg.mask, mask, outlines, [p.corners_px for p in seg.panels], image)
        clipped = r["clipped_px"] / max(1, r["wrong_px"])
        gains.append([r["iou"]] + [r["gain"][k] for k in LOSS_CLASSES] + [clipped])
        offsets.append(r["offsets_px"].ravel())
        cut += r["cut_panes"]
        off = f"{np.median(r['offsets_px']):+.1f}" if r["offsets_px"].size else "-"
        rows.append(f"| {label} | {stem} | " + " | ".join(f"{g:.3f}" for g in gains[-1][:-1])
                    + f" | {gains[-1][-1]:.2f} | {off} | {r['cut_panes'][0]}/{r['cut_panes'][1]} |")
    g = np.mean(gains, axis=0)
    off = np.concatenate(offsets)
    rows.append(f"| **{label}** | **mean** | " + " | ".join(f"{x:.3f}" for x in g[:-1])
                + f" | {g[-1]:.2f} | {np.median(off):+.1f} ({len(off)} sides) | {cut[0]}/{cut[1]} |")
    return rows


def _doit(task: str, building: str, data_root: Path, env: dict) -> None:
    subprocess.run([sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), task, f"building={building}",
                    f"data_root={data_root}"], cwd=REPO, env=env, check=True, capture_output=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data-root", default="/tmp/bench_segmentation")
    ap.add_argument("--real", type=Path, default=None, help="real photos with truth (gcw_dev's layout)")
    ap.add_argument("--real-building", default="gcw_dev", help="the building (config) they are run as")
    ap.add_argument("--exposures", action="store_true",
                    help="also the real photos at each exposure and white balance of real_truth.EXPOSURES")
    ap.add_argument("--exposure", action="append", default=None, choices=list(EXPOSURES),
                    help="with --exposures, only this one (repeatable; all where not given)")
    ap.add_argument("--task", default="segment_panels", choices=["segment_panels", "regularize_corners"],
                    help="the synthetic buildings' last stage: regularize_corners adds the 3D panels' column")
    ap.add_argument("--losses", action="store_true",
                    help="also what the masks lose, per class of wrong pixel: the real photos as taken and "
                         "real_like (among the buildings)")
    ap.add_argument("buildings", nargs="*",
                    default=["synthetic64", "synthetic64_curved", "demo", "real_like"])
    args = ap.parse_args()
    env = {**os.environ, "TQDM_DISABLE": "1"}
    real = [] if args.real is None else [real_row(args.real.resolve(), args.real_building,
                                                  Path(args.data_root), env)]
    if args.real is not None and args.exposures:
        for i, (name, gains) in enumerate(EXPOSURES.items()):
            if args.exposure and name not in args.exposure:
                continue
            root = Path(args.data_root) / "exposed" / str(i)
            shutil.rmtree(root, ignore_errors=True)
            exposed_copy(args.real.resolve(), root / "photos", gains)
            real.append(real_row(root / "photos", args.real_building, root, env,
                                 f"{args.real_building} at {name}"))
    rows = []
    for b in args.buildings:
        subprocess.run(
            [
                sys.executable,
                "-m",
                "doit",
                "-f",
                str(REPO / "dodo.py"),
                args.task,
                f"building={b}",
                f"data_root={args.data_root}",
            ],
            cwd=REPO,
            env=env,
            check=True,
            capture_output=True,
        )
        rows.append(row(b, BuildingLayout(Path(args.data_root), b)))
    if args.real is not None and "real_like" in args.buildings:
        real.append(synthetic_real_row("real_like", BuildingLayout(Path(args.data_root), "real_like")))
    losses = []
    if args.losses:
        if args.real is not None:
            losses += loss_rows(args.real_building, BuildingLayout(Path(args.data_root), args.real_building),
                                args.real.resolve())
        if "real_like" in args.buildings:
            losses += loss_rows("real_like", BuildingLayout(Path(args.data_root), "real_like"), None)
    command = " ".join(["python benchmarks/bench_segmentation.py", "--data-root", args.data_root]
                       + ([] if args.real is None else ["--real", str(args.real)])
                       + (["--exposures"] if args.exposures else [])
                       + [f"--exposure '{name}'" for name in args.exposure or []]
                       + (["--losses"] if args.losses else [])
                       + ([] if args.task == "segment_panels" else ["--task", args.task]) + args.buildings)
    text = "\n".join([
        "## rectify and segment_panels\n",
        "### Synthetic scenes\n",
        "Every frontal view rectified to a metric, fronto-parallel image of its fitted surface (a plane by "
        "its homography, a cylinder unrolled, both exact maps) and segmented with lengths relative to the "
        "building's panel pitch (which a survey of the views measures first), against "
        "gt/ with reflections on. *Warp residual*: the residual of the degree-7 polynomial recorded beside "
        "the exact map of a cylinder (the paper's warp; it cannot follow the unrolling of curved12's and "
        "oblique's views). *Straightness*: largest deviation of a true edge from a straight line after "
        "rectification. *Corner*: predicted corners away from the border against the nearest true glass "
        "corner projected through the true camera. *IoU*: each predicted panel against the true panel it "
        "overlaps most, min / median (count), whole panels and panels cut by the border apart; the last "
        "IoU is of whole panels against the visible glass. Targets: residual <= 0.5 px, straightness <= 1 "
        "px, corner median <= 1 px and p95 <= 2 px, count exact, IoU >= 0.95. `curved12` is demo with a "
        "12 m radius; `oblique` has frontal views at 1600 x 1200 px turned by up to 35 degrees; `real_like` "
        "has "
        "close-ups through a distorted wide lens at exposures from -1 to +1.5 stops, two units without glass "
        "showing a room, and poles and a crane reflected across the bars. *3D*: with `--task "
        "regularize_corners`, each corner of the 3D panels against the nearest true corner, median / max mm "
        "(panels).\n",
        f"{machine()}",
        f"`{command}`\n",
        "| building | frontal views (size) | warp residual px | straightness px | corner median / p95 / max "
        "px | views with exact count | IoU whole | IoU cut | IoU whole vs visible glass | 3D corner mm | s "
        "per view (rectify + segment) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *rows,
        "",
    ] + ([] if not real else [
        "### Real photos: gcw_dev\n",
        "Eleven posed photos of a 1:25 glass curtain wall with truth (`../shared/real/gcw_dev`, made into "
        "a building by `scripts/make_gcw_building.py`), one config for every photo. *Whole panes found*: "
        "truth outlines with four corners away from the border, found by a complete panel with IoU >= 0.7. "
        "*Corner*: of the found ones, in photo px. *Mask IoU*: `03_segment/masks` against the truth masks. "
        "*3D*: `regularize_corners`' corners against the nominal glass grid in the wall frame (the poses' "
        "own scatter is about 5 mm). Targets: found >= 90 %, IoU median >= 0.90 and min >= 0.75, corner "
        "median <= 3 px, no complete panel under half glass, 3D within 1.5 x 5 mm; rectify <= 2 and "
        "segment_panels <= 5 s per megapixel. Same run as the table above. *at -1 EV* ...: the same photos "
        "taken at another exposure or white balance (each channel's linear light times a gain, clipped and "
        "encoded: `real_truth.exposed_copy`), same config.\n",
        "| building | photos | whole panes found | mask IoU median / min | corner median px | complete "
        "panels under half glass | 3D panels | 3D corner median / max mm | s per MP (rectify + segment) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *real,
        "",
    ]) + ([] if not losses else [
        "### What the glass masks lose\n",
        "Each photo's glass mask (`03_segment/masks`) against its truth, real_like's gt/ taken as the real "
        "photos' truth (`accuracy.truth_as_real`), every wrong pixel in one class "
        "(`real_truth.mask_losses`): truth glass in a pane predicted over less than half its glass (*missed "
        "whole* / *missed cut*: a pane cut by the border), else within 3 px of the truth's outline (*short "
        "of the edge*) or deeper (*inside*); predicted glass in a panel that is less than half glass (*false "
        "panel*: an empty unit, a panel over frames), else within 3 px of the truth's glass (*over the "
        "edge*) or further (*elsewhere*: a panel across a missed bar). Each class's column is the mask IoU "
        "the photo would have with that class right, minus its IoU. *Clipped*: the share of the wrong "
        "pixels whose brightest channel is at 250/255 or more. *Side offset*: the median offset of the "
        "predicted mask's edge from the truth's along the sides of the whole panes found (> 0: beyond "
        "it). *Cut panes*: panes cut by the border predicted over at least half their glass.\n",
        "| building | photo | mask IoU | missed whole | missed cut | short of the edge | inside | false "
        "panel | over the edge | elsewhere | clipped | side offset px | cut panes |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *losses,
        "",
    ]))
    record_results(text)
    print(text)


if __name__ == "__main__":
    main()
