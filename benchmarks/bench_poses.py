"""The frontal views' poses registered to the 3D panels (``regularize_corners``' ``04_regularize/poses.json``)
on buildings already run through regularize_corners (or bake_normals): views refined, the corners'
reprojection error with the imported and the registered poses, on synthetic buildings the poses' error
against the simulator's true ones, and with ``--real DIR`` (a folder laid out as shared/real/gcw_dev) the
glass masks bake_normals cast against the photos' true glass masks. Prints a Markdown table.

    .venv/bin/python benchmarks/bench_poses.py --data-root D [--real ../shared/real/gcw_dev] buildings...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import machine  # noqa: E402

from facade_pipeline.io.images import read_mask  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.manifest import read_manifest  # noqa: E402
from facade_pipeline.scene import ImportedScene  # noqa: E402


def mask_figures(layout: BuildingLayout, real: Path) -> str:
    """Over the UAV views with a true mask in ``real``/masks: the baked glass mask's IoU with the true one
    and the share of its pixels on true glass (the corrected mesh holds only the panels found, so the
    share measures where they land), mean / min."""
    if not layout.manifest("bake_normals").is_file():
        return "- | -"
    iou, share = [], []
    for v in ImportedScene.load(layout).uav_views:
        true = real / "masks" / f"{v.stem}.png"
        if not true.is_file():
            continue
        t = read_mask(true)
        b = read_mask(layout.path("bake_glass_mask", stem=v.stem))
        iou.append((t & b).sum() / max(1, (t | b).sum()))
        share.append((t & b).sum() / max(1, b.sum()))
    if not iou:
        return "- | -"
    return f"{np.mean(iou):.3f} / {np.min(iou):.3f} | {np.mean(share):.3f} / {np.min(share):.3f}"


def row(layout: BuildingLayout, real: Path | None) -> str:
    m = read_manifest(layout, "regularize_corners").metrics
    p, t = m["poses"], m.get("truth", {})
    n = m["n_frontal_views"]
    cells = [layout.building, f"{p['views_refined']} of {n}",
             f"{p['reprojection_median_px_imported']} -> {p['reprojection_median_px']}"]  # fmt: skip
    if "pose_rotation_deg_median" in t:
        cells += [
            f"{t['pose_rotation_deg_median_imported']:.3f} -> {t['pose_rotation_deg_median']:.3f}",
            f"{100 * t['pose_centre_m_median_imported']:.1f} -> {100 * t['pose_centre_m_median']:.1f}",
        ]
    else:
        cells += ["-", "-"]
    cells.append(mask_figures(layout, real) if real is not None else "- | -")
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-root", required=True)
    ap.add_argument("--real", default="", help="a folder with the real photos' true masks (masks/{stem}.png)")
    ap.add_argument("buildings", nargs="+")
    a = ap.parse_args()
    real = Path(a.real) if a.real else None
    print(machine())
    print(
        "| building | frontal views refined | reprojection median px, imported -> registered | pose error "
        "median deg | camera centre error median cm | baked glass mask IoU mean / min | its share on "
        "true glass mean / min |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for b in a.buildings:
        print(row(BuildingLayout(Path(a.data_root), b), real), flush=True)


if __name__ == "__main__":
    main()
