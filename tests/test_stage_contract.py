"""The stage contract: a killed or interrupted stage never leaves an output a later run would trust."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from facade_pipeline.config import config_dir
from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import TMP_PREFIX, atomic_path, read_json, write_json, write_text
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from tests.helpers import make_raw, synthetic_reconstruction

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def real_building(tmp_path):
    """A 'real' building with enough images that the import takes a moment."""
    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    (cfg / "buildings" / "killme.toml").write_text('[building]\nkind = "real"\ndescription = "test"\n')
    layout = BuildingLayout(tmp_path / "data", "killme")
    rec = synthetic_reconstruction(n_images=40, width=480, height=360, params=(600.0, 240.0, 180.0, 0.05))
    make_raw(layout, rec=rec)
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    return layout, env


def _start(layout, env):
    cmd = [sys.executable, "-m", "stages.import_photogrammetry", "--building", layout.building,
           "--data-root", str(layout.data_root)]
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_sigint)  # fmt: skip


def _default_sigint() -> None:
    """In the child: SIGINT as a terminal delivers it. A shell's background job (``cmd &``) starts with
    SIGINT ignored, which its children inherit, and Python then installs no KeyboardInterrupt for it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_for_first_output(layout, proc, timeout=60.0):
    """Wait until this run has written an output (newer than its start) and has not finished."""
    folder = layout.stage_dir("import_photogrammetry") / "images"
    t0 = time.time()
    while time.time() - t0 < timeout:
        if folder.exists() and any(p.stat().st_mtime >= t0 for p in folder.iterdir() if p.exists()):
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.002)
    raise AssertionError("the stage wrote nothing")


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_killed_stage_leaves_no_manifest_and_reruns(real_building, sig):
    layout, env = real_building
    # a complete earlier run: its manifest must not survive a rerun that is killed midway
    first = _start(layout, env)
    assert first.wait(120) == 0, first.communicate()
    assert read_manifest(layout, "import_photogrammetry")
    proc = _start(layout, env)
    _wait_for_first_output(layout, proc)
    proc.send_signal(sig)
    rc = proc.wait(60)
    assert rc != 0
    if sig == signal.SIGINT:
        assert "interrupted" in proc.stderr.read()
    assert not layout.manifest("import_photogrammetry").exists()
    # the next run cleans stray temporaries and completes
    again = _start(layout, env)
    assert again.wait(120) == 0, again.communicate()
    m = read_manifest(layout, "import_photogrammetry")
    assert len([k for k in m.outputs if k.startswith("01_import/images/")]) == 40
    assert not list(layout.stage_dir("import_photogrammetry").rglob(TMP_PREFIX + "*"))


def test_atomic_writer_keeps_old_file_on_error(tmp_path):
    p = tmp_path / "out.txt"
    write_text(p, "old")
    with pytest.raises(RuntimeError), atomic_path(p) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash while writing")
    assert p.read_text() == "old"
    assert [q.name for q in tmp_path.iterdir()] == ["out.txt"]


@pytest.mark.parametrize(
    ("text", "found"),
    [
        (None, "no file"),
        ('{"version": 1, "views": [', "JSONDecodeError"),
        ('{"version": 2, "views": []}', "version 2"),
        ('{"version": 1}', "KeyError"),
        ('{"version": 1, "views": 3}', "TypeError"),
    ],
)
def test_a_damaged_json_record_is_one_error_naming_its_file(tmp_path, text, found):
    p = tmp_path / "poses.json"
    if text is not None:
        p.write_text(text)
    with pytest.raises(InputError) as e:
        read_json(p, "views (JSON)", lambda d: list(d["views"]), version=1)
    assert str(p) in str(e.value) and found in str(e.value) and "views (JSON)" in str(e.value)
    write_json(p, {"version": 1, "views": [1, 2]})
    assert read_json(p, "views (JSON)", lambda d: list(d["views"]), version=1) == [1, 2]


def test_cli_reports_bad_input_in_one_line(real_building):
    layout, env = real_building
    next(layout.raw_images_dir.iterdir()).unlink()
    proc = _start(layout, env)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if "import_photogrammetry:" in ln]
    assert len(lines) == 1 and "raw/images/" in lines[0] and "expected" in lines[0]


def test_atomic_outputs_get_the_usual_file_mode(tmp_path):
    old = os.umask(0o022)
    try:
        write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644


def test_a_stage_code_version_covers_the_modules_its_functions_import():
    """Stage modules import the heavy algorithms inside ``run`` and its helpers (doit imports every stage to
    list the tasks); their code version still covers those modules, so editing one reruns the stage."""
    from stages import load_stage
    from stages._runner import PACKAGE_DIR, source_files

    train = set(source_files(load_stage("train_gs")))
    assert PACKAGE_DIR / "training" / "render.py" in train  # imported in run()
    assert PACKAGE_DIR / "bake" / "maps.py" in train  # imported in a helper of inputs()
    assert PACKAGE_DIR / "meshing" / "clean.py" not in train  # import_photogrammetry's alone
    assert PACKAGE_DIR / "meshing" / "clean.py" in set(source_files(load_stage("import_photogrammetry")))
