"""A building without frontal views (a third-party survey) is a first-class case: the whole DAG runs, the
coarse mesh stands in for the facade, training learns from the pixels it covers, and the manifests and
the report say that no panels corrected the mesh. Frontal views that yield no panel at all stop the run
with one line instead, unless the config says to go on.

The scene is synthetic64's raw/ copied into a building of kind "real" (its frontal views removed)."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from facade_pipeline.bake.maps import BakedPrior
from facade_pipeline.config import config_dir
from facade_pipeline.io.images import read_mask
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.scene import ImportedScene
from tests.helpers import as_real_building

REPO = Path(__file__).resolve().parents[1]


def _doit(args, env, root, check=True):
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), *args, f"data_root={root}"]
    out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    if check:
        assert out.returncode == 0, out.stdout + out.stderr
    return out


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """(data root, env, configs folder) with synthetic64's raw/ made and its config copied as a real one."""
    tmp = tmp_path_factory.mktemp("nofrontal")
    cfg = tmp / "configs"
    shutil.copytree(config_dir(), cfg)
    text = (cfg / "buildings" / "synthetic64.toml").read_text()
    text = re.sub(r"(?m)^uav_count = \d+", "uav_count = 4", text)  # view 0 held out, 3 to train on
    (cfg / "buildings" / "synthetic64.toml").write_text(text)
    real = as_real_building(text)
    real = re.sub(r"(?m)^iterations = \d+", "iterations = 20", real)
    real += '\n[evaluate]\nlpips_conventions = ["vgg_3dgs"]\n'
    (cfg / "buildings" / "survey.toml").write_text(real)
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    root = tmp / "data"
    _doit(["synthesize", "building=synthetic64"], env, root)
    return root, env, cfg


def _building(survey, name: str, frontal: bool) -> BuildingLayout:
    root, _, cfg = survey
    shutil.copy(cfg / "buildings" / "survey.toml", cfg / "buildings" / f"{name}.toml")
    layout = BuildingLayout(root, name)
    shutil.copytree(BuildingLayout(root, "synthetic64").raw_dir, layout.raw_dir)
    if not frontal:
        shutil.rmtree(layout.raw_dir / "frontal")
    return layout


def test_no_frontal_views_runs_the_whole_dag_without_mesh_correction(survey):
    root, env, _ = survey
    layout = _building(survey, "nofrontal", frontal=False)
    _doit(["building=nofrontal"], env, root)
    assert "no frontal views" in read_manifest(layout, "regularize_corners").metrics["note"]
    assert "no mesh correction" in read_manifest(layout, "correct_mesh").metrics["note"]
    # the coarse mesh's pixels are the facade: every UAV view that sees it trains on them
    stems = [v.stem for v in ImportedScene.load(layout).uav_views]
    covered = [BakedPrior.load(layout, s, None, ("facade_mask",)).facade.mean() for s in stems]
    assert min(covered) > 0.05, covered
    train = read_manifest(layout, "train_gs").metrics
    assert train["n_views_without_facade"] == 0
    assert train["final_train_psnr"] is not None and math.isfinite(train["final_train_psnr"])
    assert math.isfinite(train["test_psnr"])
    metrics = json.loads(layout.path("eval_metrics").read_text())
    assert any("no mesh correction" in n for n in metrics["notes"])
    assert "no mesh correction" in layout.path("eval_report_html").read_text()
    # how often training logs changes no result: nothing reruns
    toml = survey[2] / "buildings" / "nofrontal.toml"
    assert "log_every = 25" in toml.read_text()
    toml.write_text(toml.read_text().replace("log_every = 25", "log_every = 5"))
    out = _doit(["building=nofrontal"], env, root)
    assert not re.findall(r"^\.  (\S+)", out.stdout, flags=re.M), out.stdout


def test_frontal_views_without_any_panel_stop_with_one_line_unless_allowed(survey):
    root, env, cfg = survey
    layout = _building(survey, "blank", frontal=True)
    # every frontal view painted over: no frame, no glass
    from facade_pipeline.io.images import read_image, write_image

    for p in layout.raw_frontal_images_dir.iterdir():
        img = read_image(p)
        img[:] = 128
        write_image(p, img)
    out = _doit(["correct_mesh", "building=blank"], env, root, check=False)
    assert out.returncode == 2, out.stdout + out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.startswith("regularize_corners:")]
    assert len(lines) == 1 and "Traceback" not in out.stderr
    assert "03_segment: expected glass panels in the 4 frontal views" in lines[0]
    assert "require_panels = false" in lines[0]
    toml = cfg / "buildings" / "blank.toml"
    toml.write_text(toml.read_text() + "\n[regularize_corners]\nrequire_panels = false\n")
    _doit(["correct_mesh", "building=blank"], env, root)
    assert "require_panels = false" in read_manifest(layout, "regularize_corners").metrics["note"]


def test_a_panel_mask_painted_all_white_is_one_line_not_ignored(survey):
    """The README calls the mask authoritative: a mask whose frames were painted over cannot say where the
    panels are, and the run says so instead of keeping the panels it had."""
    root, env, _ = survey
    layout = _building(survey, "white", frontal=True)
    _doit(["segment_panels", "building=white"], env, root)
    from facade_pipeline.io.images import write_mask

    mask_path = sorted(layout.path("segment_mask", stem="x").parent.glob("*.png"))[0]
    write_mask(mask_path, read_mask(mask_path) | True)
    out = _doit(["regularize_corners", "building=white"], env, root, check=False)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stdout + out.stderr
    line = next(ln for ln in out.stderr.splitlines() if ln.startswith("regularize_corners:"))
    assert mask_path.name in line and "frames painted over" in line
    # deleting the edited mask is a way back: segment_panels writes it anew and the run completes
    mask_path.unlink()
    _doit(["regularize_corners", "building=white"], env, root)
