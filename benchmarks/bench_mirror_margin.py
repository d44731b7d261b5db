"""How far the units without glass lie from the glazed ones under the mirror cue (``segmentation.mirror``),
on gcw_dev at every exposure of ``real_truth.EXPOSURES`` and on real_like with six other seeds.

Every building is segmented with no unit judged (``mirror_max_score`` set beyond reach in a config copy),
then each unit's median score over its views is recomputed from the saved panels exactly as
``segment_panels`` computes it, and labelled by the truth: a unit without glass where every panel of it
is under half truth glass, glazed where every panel is at least half glass (a unit whose panels disagree, a
pane cut by the border beside an opening, is counted in neither). Prints a table: per building, the units
scored, the units without glass and those the shipped ``mirror_max_score`` judges no pane, the glazed
units it would drop, the highest glazed unit's score and the lowest unit without glass's.

    python benchmarks/bench_mirror_margin.py --data-root /tmp/mirror --real ../shared/real/gcw_dev
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_segmentation import truth_views  # noqa: E402

from facade_pipeline.config import default_params  # noqa: E402
from facade_pipeline.io.images import read_image  # noqa: E402
from facade_pipeline.io.meshes import read_points  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.manifest import read_manifest  # noqa: E402
from facade_pipeline.rectification.surface_map import ViewRectification  # noqa: E402
from facade_pipeline.segmentation.mirror import MirrorView, facade_foot, unit_medians  # noqa: E402
from facade_pipeline.segmentation.params import SegmentParams  # noqa: E402
from facade_pipeline.segmentation.real_truth import EXPOSURES, exposed_copy, quad_mask  # noqa: E402

#: real_like with other seeds and other units without glass, as (seed, [part, row, col] per unit)
VARIANTS = {
    "rl_v1": (101, [[0, 2, 0], [0, 1, 3], [0, 0, 2]]),
    "rl_v2": (202, [[0, 1, 0], [0, 2, 2], [0, 0, 4]]),
    "rl_v3": (303, [[0, 0, 1], [0, 1, 2], [0, 2, 4]]),
    "rl_v4": (404, [[0, 2, 1], [0, 1, 4], [0, 0, 0]]),
    "rl_v5": (505, [[0, 2, 3], [0, 1, 1], [0, 0, 4]]),
    "rl_v6": (606, [[0, 0, 3], [0, 2, 2], [0, 1, 0]]),
}


def configs(dst: Path) -> Path:
    """A copy of configs/ in which no unit is judged, with the variants' files."""
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(REPO / "configs", dst)
    text = (dst / "default.toml").read_text()
    (dst / "default.toml").write_text(re.sub(r"(?m)^mirror_max_score = \S+", "mirror_max_score = 1e9", text))
    base = (REPO / "configs" / "buildings" / "real_like.toml").read_text()
    for name, (seed, unglazed) in VARIANTS.items():
        text = re.sub(r"(?m)^seed = .*$", f"seed = {seed}", base)
        text = re.sub(r"(?m)^unglazed_units = .*$", f"unglazed_units = {json.dumps(unglazed)}", text)
        (dst / "buildings" / f"{name}.toml").write_text(text)
    return dst


def segment(building: str, data_root: Path, env: dict) -> None:
    print(f"{building} in {data_root}: segment_panels", file=sys.stderr, flush=True)
    subprocess.run([sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), "segment_panels",
                    f"building={building}", f"data_root={data_root}"], cwd=REPO, env=env, check=True,
                   capture_output=True)


def unit_scores(layout: BuildingLayout, src: Path | None) -> tuple[np.ndarray, np.ndarray]:
    """Each unit's median score over the views that score it (``mirror.unit_medians``) and its label: 1
    without glass, 0 glazed, -1 mixed."""
    pitch = read_manifest(layout, "segment_panels").metrics["pitch_m"]
    pitch_m = (pitch["x"], pitch["y"])
    views, complete, opening = [], [], []
    for stem, seg, mask, _, _ in truth_views(layout, src):
        rect = ViewRectification.load(layout.path("rectify_mapping", stem=stem))
        if rect.chart is None or rect.chart.curvature_per_m != 0.0 or not seg.panels:
            continue
        image = read_image(layout.path("rectify_image", stem=stem))
        views.append(MirrorView(stem, rect, image, [np.asarray(p.corners_rectified_px) for p in seg.panels]))
        complete.append(np.array([p.complete for p in seg.panels]))
        H, W = mask.shape
        quads = [quad_mask(p.corners_px, W, H) for p in seg.panels]
        opening.append(np.array([not q.any() or mask[q].mean() < 0.5 for q in quads]))
    ground = facade_foot(read_points(layout.import_coarse_points).points, views[0].rect.chart.up)
    unit, medians = unit_medians(views, complete, pitch_m, ground)
    unit, label = np.concatenate(unit), np.concatenate(opening)
    out, lab = [], []
    for u, (median, _) in medians.items():
        mine = label[unit == u]
        out.append(median)
        lab.append(1 if mine.all() else 0 if not mine.any() else -1)
    return np.array(out), np.array(lab)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data-root", type=Path, required=True)
    ap.add_argument("--real", type=Path, required=True, help="gcw_dev's photos with truth")
    args = ap.parse_args()
    root = args.data_root.resolve()
    env = {**os.environ, "TQDM_DISABLE": "1", "FACADE_CONFIG_DIR": str(configs(root / "configs"))}
    threshold = default_params("segment_panels", SegmentParams).mirror_max_score
    buildings = []
    for i, (name, gains) in enumerate({"as taken": None, **EXPOSURES}.items()):
        r = root / "gcw" / str(i)
        src = args.real.resolve()
        if gains is not None:
            shutil.rmtree(r, ignore_errors=True)
            exposed_copy(src, r / "photos", gains)
            src = r / "photos"
        subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(src),
                        "--building", "gcw_dev", "--data-root", str(r), "--force"], cwd=REPO, env=env,
                       check=True, capture_output=True)
        segment("gcw_dev", r, env)
        buildings.append((f"gcw_dev {name}", BuildingLayout(r, "gcw_dev"), src))
    for name in ["real_like", *VARIANTS]:
        segment(name, root / "sim", env)
        buildings.append((name, BuildingLayout(root / "sim", name), None))
    rows = ["| building | units scored | without glass: judged / all | glazed judged | highest glazed | "
            "lowest without glass |", "| --- | --- | --- | --- | --- | --- |"]
    for label, layout, src in buildings:
        s, lab = unit_scores(layout, src)
        glazed, empty = s[lab == 0], s[lab == 1]
        top = glazed.max() if len(glazed) else float("nan")
        low = empty.min() if len(empty) else float("nan")
        rows.append(f"| {label} | {len(s)} | {int((empty > threshold).sum())} / {len(empty)} | "
                    f"{int((glazed > threshold).sum())} | {top:.3f} | {low:.3f} |")
    print(f"mirror_max_score {threshold}\n")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
