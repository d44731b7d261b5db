"""Drive the real dodo.py: list order, a second run executes nothing, a hand edit or a parameter change
reruns exactly what depends on it, ``-s`` runs one stage alone."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from facade_pipeline.config import config_dir
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from stages import PIPELINE
from tests.helpers import make_raw

REPO = Path(__file__).resolve().parents[1]
#: These tests target the first stages only (`doit import_photogrammetry ...` runs it and what it needs), so
#: they stay fast; tests/evaluation runs the whole DAG end to end.
IMPORT = "import_photogrammetry"


def doit(args, env, data_root):
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), *args, f"data_root={data_root}"]
    out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def executed(stdout: str) -> list[str]:
    """Task names doit reports as run ('.  name'), not up to date ('-- name')."""
    return re.findall(r"^\.  (\S+)", stdout, flags=re.M)


@pytest.fixture
def real(tmp_path):
    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    (cfg / "buildings" / "testreal.toml").write_text('[building]\nkind = "real"\ndescription = "test"\n')
    layout = BuildingLayout(tmp_path / "data", "testreal")
    make_raw(layout, frontal=True)
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    return layout, env, cfg


def test_list_shows_existing_stages_in_pipeline_order(real):
    layout, env, _ = real
    out = doit(["list", "building=testreal"], env, layout.data_root)
    names = [line.split()[0] for line in out.splitlines() if line.strip()]
    assert names == [s for s in PIPELINE if s != "synthesize"]
    assert all(
        len(line.split(None, 1)) == 2 for line in out.splitlines() if line.strip()
    )  # each has a description
    out = doit(["list", "building=synthetic64"], env, layout.data_root)
    assert [line.split()[0] for line in out.splitlines() if line.strip()] == list(PIPELINE)


def test_second_run_executes_nothing_and_edits_rerun_dependants(real):
    layout, env, cfg = real
    root = layout.data_root
    assert executed(doit([IMPORT, "building=testreal"], env, root)) == [IMPORT]
    assert (layout.root / ".doit.db").exists()  # doit's state is per building
    assert executed(doit([IMPORT, "building=testreal"], env, root)) == []
    # (b) a file the stage read, edited by hand: the stage reruns
    img = next(layout.raw_images_dir.iterdir())
    img.write_bytes(img.read_bytes())  # same content: nothing to do
    assert executed(doit([IMPORT, "building=testreal"], env, root)) == []
    from facade_pipeline.io.images import read_image, write_image

    pixels = read_image(img)
    pixels[0, 0] = 255 - pixels[0, 0]
    write_image(img, pixels)
    assert executed(doit([IMPORT, "building=testreal"], env, root)) == [IMPORT]
    # (c) one parameter changed: that stage reruns
    (cfg / "buildings" / "testreal.toml").write_text(
        '[building]\nkind = "real"\ndescription = "test"\n[import_photogrammetry]\norigin_rounding_m = 10.0\n'
    )
    assert executed(doit([IMPORT, "building=testreal"], env, root)) == [IMPORT]
    assert executed(doit([IMPORT, "building=testreal"], env, root)) == []
    # (d) one stage alone, forced after `doit forget`
    doit(["forget", "import_photogrammetry", "building=testreal"], env, root)
    assert executed(doit(["-s", "import_photogrammetry", "building=testreal"], env, root)) == [
        "import_photogrammetry"
    ]


def test_manifest_deleted_means_rerun(real):
    layout, env, _ = real
    doit([IMPORT, "building=testreal"], env, layout.data_root)
    layout.manifest(IMPORT).unlink()
    assert executed(doit([IMPORT, "building=testreal"], env, layout.data_root)) == [IMPORT]


def test_synthetic_building_hand_edit_reruns_only_downstream(tmp_path):
    """On synthetic64: an image that `synthesize` wrote, edited by hand, reruns `import_photogrammetry` only;
    a synthesize parameter reruns both."""
    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    root = tmp_path / "data"
    layout = BuildingLayout(root, "synthetic64")
    assert executed(doit([IMPORT, "building=synthetic64"], env, root)) == ["synthesize", IMPORT]
    assert executed(doit([IMPORT, "building=synthetic64"], env, root)) == []
    from facade_pipeline.io.images import read_image, write_image

    img = sorted(layout.raw_images_dir.iterdir())[0]
    pixels = read_image(img)
    pixels[:4, :4] = 0
    write_image(img, pixels)
    assert executed(doit([IMPORT, "building=synthetic64"], env, root)) == [IMPORT]
    toml = cfg / "buildings" / "synthetic64.toml"
    toml.write_text(re.sub(r"(?m)^seed = \d+", "seed = 12345", toml.read_text()))
    assert executed(doit([IMPORT, "building=synthetic64"], env, root)) == ["synthesize", IMPORT]


def test_listing_the_tasks_imports_no_heavy_library(tmp_path):
    """``doit list`` builds task metadata only: it must not pay for torch, open3d, pycolmap or OpenCV, and
    the pipeline's modules change no environment variable at import."""
    script = (
        "import os, sys, runpy; before = dict(os.environ); sys.argv = ['doit', '-f', sys.argv[1], 'list', "
        "'building=synthetic64', 'data_root=' + sys.argv[2]]\n"
        "try:\n    runpy.run_module('doit', run_name='__main__')\n"
        "except SystemExit as e:\n    assert not e.code, e.code\n"
        "heavy = sorted(m for m in ('torch', 'open3d', 'pycolmap', 'cv2') if m in sys.modules)\n"
        "changed = sorted(k for k in set(os.environ) | set(before) if os.environ.get(k) != before.get(k))\n"
        "print('HEAVY', heavy, 'ENV', changed)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script, str(REPO / "dodo.py"), str(tmp_path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "HEAVY [] ENV []" in out.stdout, out.stdout


def test_a_run_setting_reruns_nothing(real):
    """[run] (device, backend, logging, checkpoints, overlay size) is in no stage's parameters, so doit's
    config_changed never sees it: rectify, which draws its overlay at run.overlay_scale, stays up to date."""
    layout, env, cfg = real
    root = layout.data_root
    assert executed(doit(["rectify", "building=testreal"], env, root)) == [IMPORT, "rectify"]
    (cfg / "buildings" / "testreal.toml").write_text(
        '[building]\nkind = "real"\ndescription = "test"\n'
        '[run]\noverlay_scale = 2.0\ndevice = "auto"\nlog_every = 7\ncheckpoint_every = 3\n'
    )
    assert executed(doit(["rectify", "building=testreal"], env, root)) == []
    # a parameter of the same stage does rerun it
    (cfg / "buildings" / "testreal.toml").write_text(
        '[building]\nkind = "real"\ndescription = "test"\n[rectify]\nmax_size_factor = 3.0\n'
    )
    assert executed(doit(["rectify", "building=testreal"], env, root)) == ["rectify"]


def test_a_rerun_that_writes_the_same_outputs_stops_the_cascade(real):
    """Early cutoff: a stage forced to rerun (`doit forget`) writes a new manifest (another wall time) with
    the same output hashes; the stages after it depend on those hashes, not on the manifest's bytes, so only
    it reruns."""
    layout, env, _ = real
    root = layout.data_root
    assert executed(doit(["rectify", "building=testreal"], env, root)) == [IMPORT, "rectify"]
    before = layout.manifest(IMPORT).read_bytes()
    outputs = read_manifest(layout, IMPORT).outputs
    doit(["forget", IMPORT, "building=testreal"], env, root)
    assert executed(doit(["rectify", "building=testreal"], env, root)) == [IMPORT]
    assert layout.manifest(IMPORT).read_bytes() != before  # a new manifest ...
    assert read_manifest(layout, IMPORT).outputs == outputs  # ... listing the same outputs
    # an upstream output that does change reruns the stages after it
    img = next(layout.raw_images_dir.iterdir())
    from facade_pipeline.io.images import read_image, write_image

    pixels = read_image(img)
    pixels[0, 0] = 255 - pixels[0, 0]
    write_image(img, pixels)
    assert executed(doit(["rectify", "building=testreal"], env, root)) == [IMPORT, "rectify"]
