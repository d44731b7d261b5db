"""A user's models in the wrong frame or unit stop the import with one line naming the file and the likely
cause; before these checks every stage ran on and train_gs trained on empty masks at psnr=nan.

The scene is synthetic64's raw/ (made by ``synthesize``) copied into a building of kind "real"."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from facade_pipeline.config import config_dir, default_params
from facade_pipeline.errors import InputError
from facade_pipeline.io.meshes import make_mesh, read_mesh, write_mesh
from facade_pipeline.layout import BuildingLayout
from stages import import_photogrammetry as imp
from stages._runner import execute
from tests.helpers import tree_digest

REPO = Path(__file__).resolve().parents[2]
PARAMS = default_params("import_photogrammetry", imp.Params)


@pytest.fixture(scope="module")
def synthetic_raw(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("scene_checks")
    cfg = tmp / "configs"
    shutil.copytree(config_dir(), cfg)
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), "synthesize", "building=synthetic64",
           f"data_root={tmp / 'data'}"]  # fmt: skip
    out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    return BuildingLayout(tmp / "data", "synthetic64").raw_dir


@pytest.fixture
def user(tmp_path, synthetic_raw) -> BuildingLayout:
    layout = BuildingLayout(tmp_path / "data", "user")
    shutil.copytree(synthetic_raw, layout.raw_dir)
    return layout


def _mesh_scaled(layout: BuildingLayout, scale: float, shift=(0.0, 0.0, 0.0)) -> None:
    path = layout.raw_coarse_mesh_candidates[0]
    mesh = read_mesh(path)
    v = np.asarray(mesh.vertices) * scale + np.asarray(shift)
    write_mesh(path, make_mesh(v, np.asarray(mesh.triangles)))


def _frontal_moved(layout: BuildingLayout, scale: float, yaw_deg: float, shift) -> None:
    rec = pycolmap.Reconstruction(str(layout.raw_frontal_sparse_dir))
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(R), np.asarray(shift, dtype=float)))
    rec.write(str(layout.raw_frontal_sparse_dir))


CASES = [
    ("mesh in millimetres", lambda lay: _mesh_scaled(lay, 1000.0), "coarse_mesh.ply",
     ["the size of the camera layout: units?", "millimetres"]),
    ("mesh in kilometres", lambda lay: _mesh_scaled(lay, 0.001), "coarse_mesh.ply",
     ["1/", "units?", "kilometres"]),
    ("mesh 500 m from the cameras", lambda lay: _mesh_scaled(lay, 1.0, (500.0, 0.0, 0.0)), "coarse_mesh.ply",
     ["UAV cameras see", "world frame"]),
    ("frontal model rotated 45 deg and moved 40 m", lambda lay: _frontal_moved(lay, 1.0, 45.0, (40.0, 0, 0)),
     "raw/frontal/sparse/0", ["none of", "frontal views sees the coarse mesh"]),
    ("frontal model at scale 0.01", lambda lay: _frontal_moved(lay, 0.01, 0.0, (0, 0, 0)),
     "raw/frontal/sparse/0", ["none of", "frontal views sees the coarse mesh"]),
]  # fmt: skip


@pytest.mark.parametrize(("case", "damage", "file_part", "words"), CASES, ids=[c[0] for c in CASES])
def test_wrong_frame_or_unit_is_one_clear_line(user, case, damage, file_part, words):
    damage(user)
    before = tree_digest(user.raw_dir)
    with pytest.raises(InputError) as e:
        execute(imp, user, PARAMS)
    msg = str(e.value)
    assert file_part in msg and "expected" in msg and all(w in msg for w in words), msg
    assert "\n" not in msg
    assert tree_digest(user.raw_dir) == before and not user.manifest("import_photogrammetry").exists()


def test_a_consistent_scene_passes_and_says_what_it_measured(user):
    m = execute(imp, user, PARAMS)["metrics"]
    assert 1 / 5 < m["mesh_size_ratio"] < 5
    assert m["uav_views_seeing_mesh"] >= 0.9 and m["frontal_views_seeing_mesh"] == 1.0
