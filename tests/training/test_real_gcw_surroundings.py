"""The reflection proxy's surroundings on real photos (shared/real/gcw_dev): the converter's point cloud
holds points triangulated from the photos, most of them the reflections' virtual points behind the glass;
the trainer's proxy mirrors them back in front of the wall and has surroundings there. The converter makes
the same files from the same photos and writes nothing outside its data root. Skipped where shared/ is
absent."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from facade_pipeline.io.colmap import read_reconstruction
from facade_pipeline.io.meshes import read_points
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.shading.surroundings import glass_plane, surroundings_points
from facade_pipeline.training.params import INIT_BOUNDS_MARGIN, facade_size
from facade_pipeline.training.render import splatting_rasterizer
from facade_pipeline.training.trainer import build_trainer
from scripts.make_gcw_building import WORLD_FROM_WALL
from tests.conftest import GCW_SRC, REPO

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not (GCW_SRC / "cameras.json").is_file(),
                                                   reason=f"no real photos at {GCW_SRC}")]



def _triangulated(layout: BuildingLayout) -> np.ndarray:
    """[N, 3] the points of the UAV model (those the converter triangulated), world frame."""
    rec = read_reconstruction(layout.raw_sparse_dir)
    return np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)


def test_the_converter_triangulates_the_reflections_behind_the_wall(gcw_dev):
    layout, _ = gcw_dev
    xyz = _triangulated(layout)
    assert len(xyz) >= 30
    # in the coarse point cloud beside the points sampled on the wall
    cloud = np.asarray(read_points(layout.raw_coarse_points).points)
    assert len(cloud) == 20000 + len(xyz)
    def ordered(a):
        return a[np.lexsort(a.T[::-1])]

    np.testing.assert_allclose(ordered(cloud[-len(xyz):]), ordered(xyz), atol=1e-5)
    # the wall frame's z points into the wall (0 on the glass): most points lie behind it, the virtual points
    # of the reflections, some of them a metre and more (the trees' and buildings' images)
    z = (xyz @ np.linalg.inv(WORLD_FROM_WALL)[:3, :3].T)[:, 2]
    assert np.mean(z > 0.02) > 0.7
    assert np.quantile(z, 0.9) > 0.5


def test_the_proxy_has_the_surroundings_in_front_of_the_wall(gcw_train_data):
    layout, p, data = gcw_train_data
    tr = build_trainer(p, data, splatting_rasterizer("auto", p.lowpass_sigma_px))
    surroundings = tr.state.reflection.proxy.surroundings
    top = surroundings.heights[1].numpy()
    assert (top > 0).sum() >= 20  # what train_gs reports as proxy_surroundings_cells
    # every cell on the cameras' side of the glass: the mirrored points, none of the virtual ones behind it
    init = data.init
    eyes = np.array([v.camera.center for v in data.views])
    plane = glass_plane(init.mesh_vertices, init.mesh_triangles, init.mesh_glass, eyes)
    assert plane is not None
    i, j = np.nonzero(top > 0)
    n = top.shape[0]
    xy = np.array(surroundings.eye_xy) + (np.stack([i, j], 1) - 0.5 * n + 0.5) * surroundings.cell_m
    centres = np.column_stack([xy, np.full(len(xy), plane.origin[2])])
    assert (plane.signed_distance(centres) > 0).all()
    # the points behind the glass that the proxy mirrored are the converter's triangulated ones
    margin = INIT_BOUNDS_MARGIN * facade_size(data.bounds)
    _, moved = surroundings_points(init.points, init.mesh_vertices, init.mesh_triangles, init.mesh_glass,
                                   [v.camera for v in data.views], margin)
    assert 0.7 * len(_triangulated(layout)) <= moved <= len(_triangulated(layout))


def test_the_converter_is_deterministic_and_writes_only_its_data_root(gcw_dev, tmp_path):
    layout, env = gcw_dev
    root = tmp_path / "root"
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(GCW_SRC),
                          "--building", "again", "--data-root", str(root)], cwd=cwd, env=env,
                         capture_output=True, text=True)  # fmt: skip
    assert out.returncode == 0, out.stderr
    again = BuildingLayout(root, "again")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cwd", "root"]
    assert not any(cwd.iterdir())
    assert [p.name for p in root.iterdir()] == ["again"]
    assert sorted(p.name for p in again.raw_dir.iterdir()) == sorted(p.name for p in layout.raw_dir.iterdir())
    for name in ("coarse_points.ply", "coarse_mesh.ply"):
        assert (again.raw_dir / name).read_bytes() == (layout.raw_dir / name).read_bytes(), name
    for f in sorted(layout.raw_sparse_dir.iterdir()):
        assert (again.raw_sparse_dir / f.name).read_bytes() == f.read_bytes(), f.name
