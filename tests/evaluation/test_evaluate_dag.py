"""The whole DAG end to end on synthetic64 through the real dodo.py, reaching `evaluate`: metrics.json with
held-out metrics and geometry against gt/, the report pages; a second run executes nothing; a model saved
under variants/ afterwards reruns `evaluate` alone. Training is
shortened in a copied config so that the test stays quick; everything else is synthetic64's own."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from facade_pipeline.config import config_dir
from facade_pipeline.layout import BuildingLayout
from stages import PIPELINE

REPO = Path(__file__).resolve().parents[2]


def _doit(args: list[str], env: dict, root: Path) -> str:
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), *args, f"data_root={root}"]
    out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def _executed(stdout: str) -> list[str]:
    return re.findall(r"^\.  (\S+)", stdout, flags=re.M)


def test_whole_dag_on_synthetic64_reaches_evaluate(tmp_path):
    assert PIPELINE[-1] == "evaluate"
    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    toml = cfg / "buildings" / "synthetic64.toml"
    text = re.sub(r"(?m)^iterations = \d+", "iterations = 20", toml.read_text())
    text = re.sub(r"(?m)^uav_count = \d+", "uav_count = 4", text)  # view 0 held out, 3 to train on
    # a 20-step model is still faint: measure every splat that is at least as opaque as it started
    toml.write_text(
        text + "\n[evaluate]\ngeometry_samples = 4000\ngaussian_min_opacity = 0.05\n"
        'lpips_conventions = ["vgg_3dgs"]\n'
    )
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1", "OMP_NUM_THREADS": "2"}
    root = tmp_path / "data"
    assert _executed(_doit(["building=synthetic64"], env, root)) == list(PIPELINE)
    layout = BuildingLayout(root, "synthetic64")

    m = json.loads(layout.path("eval_metrics").read_text())
    split = json.loads(layout.path("train_split").read_text())
    main = m["variants"]["07_train"]
    assert [v["view"] for v in main["test"]["views"]] == split["test"] != []
    facade = main["test"]["mean"]["facade"]
    assert 5.0 < facade["psnr"] < 60.0 and 0.0 < facade["ssim"] <= 1.0
    for region in ("glass", "frames"):
        assert main["test"]["mean"][region]["psnr"] != facade["psnr"]
    aligned = main["test_aligned"]
    assert [v["view"] for v in aligned["views"]] == split["test"]
    assert all(
        v["alignment"]["align_l1_after"] <= v["alignment"]["align_l1_before"] for v in aligned["views"]
    )
    geo = m["geometry"]
    # the corrected mesh is closer to the true glass than the coarse one (what correct_mesh is for)
    assert geo["corrected_mesh"]["glass_distance_mean_m"] < geo["coarse_mesh"]["glass_distance_mean_m"]
    assert geo["panel_corners"]["corner_error_mean_m"] is not None
    assert main["geometry"]["gaussians_measured"] > 0
    for stem in split["test"]:
        assert layout.path("eval_comparison", variant="07_train", split="test", stem=stem).is_file()

    page = layout.path("eval_report_html").read_text()
    assert "Table 1" in page and page.count("data:image/png;base64,") == len(split["test"])
    # the fly-through: an MP4 beside the report, its looping clip inside it
    from facade_pipeline.evaluation.video import read_mp4

    video = m["video"]
    frames = read_mp4(layout.path("eval_video"))
    assert len(frames) == video["frames"] == 48 and frames[0].shape[1::-1] == tuple(video["size_px"])
    assert "data:image/webp;base64," in page and "href='flythrough.mp4'" in page
    assert "src='comparisons" not in page  # nothing outside the page
    manifest = json.loads(layout.manifest("evaluate").read_text())
    assert manifest["metrics"]["07_train_test_psnr"] == facade["psnr"]
    # train_gs's held-out check and evaluate measure through one core: the same figures (evaluate renders the
    # saved PLY, whose activated values round in float32)
    trained = json.loads(layout.manifest("train_gs").read_text())["metrics"]
    keys = {"facade": "test_psnr", "glass": "test_psnr_glass", "glass_interior": "test_psnr_glass_interior"}
    for region, key in keys.items():
        mean = main["test"]["mean"][region]  # None: no view has the region (glass 2 px inside its edge)
        assert trained[key] == (None if mean is None else pytest.approx(mean["psnr"], abs=1e-3)), key
    assert "PSNR glass interior" in page
    assert manifest["metrics"]["07_train_test_aligned_psnr"] == aligned["mean"]["facade"]["psnr"]
    assert _executed(_doit(["building=synthetic64"], env, root)) == []

    # a model saved under variants/ by a person (or the benchmark) is picked up: evaluate alone reruns
    saved = layout.path("variant_dir", variant="copy")
    saved.mkdir(parents=True)
    for key, name in (
        ("train_ply", "gaussians.ply"),
        ("train_reflection", "reflection.pt"),
        ("train_split", "split.json"),
    ):
        shutil.copy(layout.path(key), saved / name)
    trained_with = json.loads(layout.manifest("train_gs").read_text())["params"]
    (saved / "params.json").write_text(json.dumps(trained_with))
    assert _executed(_doit(["building=synthetic64"], env, root)) == ["evaluate"]
    again = json.loads(layout.path("eval_metrics").read_text())
    copy = again["variants"]["copy"]
    assert copy["test"]["mean"]["facade"]["psnr"] == facade["psnr"]  # the same model renders the same
    # two models: the fly-through shows them side by side, the pipeline's first
    assert again["video"]["variants"] == ["07_train", "copy"]
    assert again["video"]["size_px"][0] > 2 * video["size_px"][0]
