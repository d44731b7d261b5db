"""Real photos of a glass curtain wall with truth (shared/real/gcw_dev): scripts/make_gcw_building.py makes
the building, the DAG runs through regularize_corners with configs/buildings/gcw_dev.toml (one setting for
every photo), and the result is measured against the truth masks, the pane outlines and the nominal grid.
The thresholds guard what the method reaches today; the stricter targets and the figures against them are
in benchmarks/RESULTS.md (bench_segmentation.py --real). Skipped where shared/ is absent."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.segmentation.real_truth import evaluate_building, grid_corner_errors_m, summary
from scripts.make_gcw_building import WORLD_FROM_WALL
from tests.segmentation.conftest import REPO, doit

SRC = REPO.parent / "shared" / "real" / "gcw_dev"
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not (SRC / "cameras.json").is_file(), reason=f"no real photos at {SRC}")]


def _digest(folder) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def gcw(tmp_path_factory):
    root = tmp_path_factory.mktemp("gcw")
    before = _digest(SRC)
    env = {**os.environ, "TQDM_DISABLE": "1"}
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(SRC),
                          "--building", "gcw_dev", "--data-root", str(root)], cwd=REPO, env=env,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    doit(["regularize_corners", "building=gcw_dev"], env, root)
    assert _digest(SRC) == before  # the source folder is only read
    layout = BuildingLayout(root, "gcw_dev")
    return layout, evaluate_building(layout, SRC)


def test_script_writes_raw_as_a_user_would_bring_it(gcw, tmp_path):
    layout, _ = gcw
    n = len(list((SRC / "images").glob("*.jpg")))
    assert len(list(layout.raw_images_dir.iterdir())) == n
    assert len(list(layout.raw_frontal_images_dir.iterdir())) == n
    assert layout.raw_coarse_mesh_candidates[0].is_file() and layout.raw_coarse_points.is_file()
    again = subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(SRC),
                            "--building", "gcw_dev", "--data-root", str(layout.data_root)], cwd=REPO,
                           capture_output=True, text=True)
    assert again.returncode == 2 and "existing raw/" in again.stderr and "Traceback" not in again.stderr


def test_every_photo_is_rectified_by_a_plane_at_its_own_scale(gcw):
    layout, _ = gcw
    m = read_manifest(layout, "rectify").metrics
    assert m["n_plane"] == m["n_views"] == len(list((SRC / "images").glob("*.jpg")))
    cams = json.loads((SRC / "cameras.json").read_text())
    for stem, v in m["views"].items():
        c = cams[stem]
        depth = float(np.asarray(c["cam_from_world"])[2, 3])  # the wall's distance along the optical axis
        gsd = abs(depth) / c["K"][0][0]
        assert 0.7 < v["metres_per_px"] / gsd < 1.5  # oblique views spread the footprint about it


def test_segmentation_against_the_truth(gcw):
    _, per_photo = gcw
    s = summary(per_photo)
    assert s["photos"] == 11
    assert s["found_fraction"] >= 0.9
    assert s["mask_iou_median"] >= 0.75 and s["mask_iou_min"] >= 0.45
    assert s["corner_error_median_px"] <= 3.0
    assert s["complete_less_than_half_glass"] <= 3


def test_3d_panels_against_the_nominal_grid(gcw):
    layout, _ = gcw
    panels = json.loads(layout.path("regularize_panels").read_text())["panels"]
    assert len(panels) >= 4
    world = np.array([p["corners"] for p in panels], float).reshape(-1, 3)
    wall = world @ WORLD_FROM_WALL[:3, :3]  # world -> wall frame (a rotation)
    err = grid_corner_errors_m(wall, (0.1032, 0.1532), (0.0932, 0.1432))
    assert np.median(err) <= 1.5 * 0.005  # 1.5 x the poses' own scatter
