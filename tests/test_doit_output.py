"""What a person sees in the terminal while ``doit`` runs: a stage's progress bar drawn live, with the time
left, and a bad input as one line naming the file or key (exit code 2) that a rerun after the fix gets past.

The scene is synthetic64's raw/ (made by ``synthesize``) copied into buildings of kind "real"."""

from __future__ import annotations

import os
import re
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from facade_pipeline.config import config_dir
from facade_pipeline.io.images import read_image, write_image
from facade_pipeline.io.meshes import make_mesh, read_mesh, write_mesh
from facade_pipeline.layout import BuildingLayout
from tests.helpers import as_real_building

REPO = Path(__file__).resolve().parents[1]
IMPORT = "import_photogrammetry"
#: a tqdm line with a time estimate: "12/14 [00:02<00:00, ...": elapsed < remaining, both known
ESTIMATE = re.compile(rb"\d+/\d+ \[\d\d:\d\d<\d\d:\d\d")


def _doit_command(args, root):
    return [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), *args, f"data_root={root}"]


def _doit(args, env, root):
    return subprocess.run(_doit_command(args, root), cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=900)  # fmt: skip


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """(data root, env, configs folder) with synthetic64's raw/ made by a doit run."""
    tmp = tmp_path_factory.mktemp("doit_output")
    cfg = tmp / "configs"
    shutil.copytree(config_dir(), cfg)
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    out = _doit(["synthesize", "building=synthetic64"], env, tmp / "data")
    assert out.returncode == 0, out.stdout + out.stderr
    return tmp / "data", env, cfg


def test_a_stages_progress_bar_is_live_with_the_time_left(tmp_path):
    """The stage writes to the terminal itself: its bar arrives while doit still runs, not when it ends."""
    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    env = {k: v for k, v in os.environ.items() if k != "TQDM_DISABLE"}
    env["FACADE_CONFIG_DIR"] = str(cfg)
    command = _doit_command(["synthesize", "building=synthetic64"], tmp_path / "data")
    proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    seen, live = b"", None
    deadline = time.monotonic() + 600
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([proc.stderr], [], [], 1.0)
            if not ready:
                if proc.poll() is not None:
                    break
                continue
            chunk = os.read(proc.stderr.fileno(), 65536)
            if not chunk:
                break
            seen += chunk
            if live is None and ESTIMATE.search(seen):
                live = proc.poll() is None  # read before the process ended
    finally:
        proc.stderr.close()
        code = proc.wait(timeout=600)
    assert code == 0, seen.decode(errors="replace")
    assert live is True, seen.decode(errors="replace")
    assert b"synthesize:" in seen and b"view/s" in seen


def _mesh_in_millimetres(layout: BuildingLayout) -> None:
    path = layout.raw_coarse_mesh_candidates[0]
    mesh = read_mesh(path)
    write_mesh(path, make_mesh(np.asarray(mesh.vertices) * 1000.0, np.asarray(mesh.triangles)))


def _image_deleted(layout: BuildingLayout) -> None:
    sorted(layout.raw_images_dir.iterdir())[0].unlink()


def _image_cropped(layout: BuildingLayout) -> None:
    path = sorted(layout.raw_images_dir.iterdir())[0]
    write_image(path, read_image(path)[:40, :50])


def _pose_nan(layout: BuildingLayout) -> None:
    rec = pycolmap.Reconstruction(str(layout.raw_sparse_dir))
    frame = rec.frames[next(iter(rec.images.values())).frame_id]
    frame.rig_from_world = pycolmap.Rigid3d(frame.rig_from_world.rotation, np.array([np.inf, 0.0, 0.0]))
    rec.write(str(layout.raw_sparse_dir))


def _model_truncated(layout: BuildingLayout) -> None:
    path = layout.raw_sparse_dir / "images.bin"
    path.write_bytes(path.read_bytes()[:100])


def _config_out_of_range(cfg: Path, name: str) -> None:
    toml = cfg / "buildings" / f"{name}.toml"
    toml.write_text(toml.read_text() + "\n[import_photogrammetry]\nmax_size_ratio = -1.0\n")


#: (case, what is damaged: "raw" or "config", the damage, what the line names)
CASES = [
    ("image deleted", "raw", _image_deleted, "raw/images/"),
    ("image cropped", "raw", _image_cropped, "raw/images/"),
    ("pose Inf", "raw", _pose_nan, "raw/sparse/0"),
    ("model truncated", "raw", _model_truncated, "raw/sparse/0"),
    ("mesh in millimetres", "raw", _mesh_in_millimetres, "coarse_mesh.ply"),
    ("key out of range", "config", _config_out_of_range, "import_photogrammetry.max_size_ratio"),
]


@pytest.mark.parametrize(("case", "where", "damage", "names"), CASES, ids=[c[0] for c in CASES])
def test_bad_input_under_doit_is_one_line_and_a_rerun_after_the_fix_completes(
    synthetic, case, where, damage, names
):
    root, env, cfg = synthetic
    name = "user_" + re.sub(r"\W", "_", case)
    real = as_real_building((cfg / "buildings" / "synthetic64.toml").read_text())
    (cfg / "buildings" / f"{name}.toml").write_text(real)
    layout = BuildingLayout(root, name)
    pristine = BuildingLayout(root, "synthetic64").raw_dir
    shutil.copytree(pristine, layout.raw_dir)
    damage(layout) if where == "raw" else damage(cfg, name)

    out = _doit([IMPORT, f"building={name}"], env, root)
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert out.returncode == 2, out.stdout + out.stderr
    assert len(lines) == 1 and names in lines[0], out.stderr
    assert "TaskError" not in out.stdout + out.stderr and "####" not in out.stdout, out.stdout

    # the fix: the user's files put back (or the config line taken out); the run then completes
    if where == "raw":
        shutil.rmtree(layout.raw_dir)
        shutil.copytree(pristine, layout.raw_dir)
    else:
        (cfg / "buildings" / f"{name}.toml").write_text(real)
    out = _doit([IMPORT, f"building={name}"], env, root)
    assert out.returncode == 0, out.stdout + out.stderr
    assert layout.manifest(IMPORT).is_file()
