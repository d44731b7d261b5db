"""gt/ read into the local frame (synthetic/truth.py): a truth written at UTM-sized coordinates comes back
near the origin with its distances kept to micrometres (float32 alone would have ~0.5 m steps there),
normals turned with the frame, cameras moved with it; bad panels are named."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.geometry.frames import invert_rigid, transform_points
from facade_pipeline.io.colmap import ColmapView, write_pinhole_model
from facade_pipeline.io.exr import write_exr
from facade_pipeline.io.images import write_mask
from facade_pipeline.io.meshes import make_mesh, write_mesh
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.synthetic.truth import SyntheticTruth

SQUARE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
TRIANGLES = np.array([[0, 1, 2], [0, 2, 3]])


def _georef_from_local() -> np.ndarray:
    """A quarter turn about z and a UTM-sized offset."""
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [4.5e5, 5.4e6, 300.0]
    return T


def _write_gt(layout: BuildingLayout, georef_from_local: np.ndarray) -> PinholeCamera:
    """gt/ of one square glass panel (local z = 0 plane) and frames beside it, written in the georeferenced
    frame; returns the frontal camera in the local frame."""
    to_world = lambda p: transform_points(georef_from_local, p)  # noqa: E731
    write_mesh(layout.gt("glass_mesh"), make_mesh(to_world(SQUARE), TRIANGLES))
    write_mesh(layout.gt("frame_mesh"), make_mesh(to_world(SQUARE + [1.5, 0, 0]), TRIANGLES))
    panels = {
        "panels": [{"part": "a", "part_index": 0, "row": 0, "col": 0, "corners": to_world(SQUARE).tolist()}]
    }
    layout.gt("panels").write_text(json.dumps(panels))
    world_from_facade = georef_from_local @ np.eye(4)
    parts = [
        {
            "index": 0,
            "kind": "cylindrical",
            "world_from_facade": world_from_facade.tolist(),
            "axis_point": to_world(np.array([[0.5, -25.0, 0.0]]))[0].tolist(),
            "axis_direction": [0, 0, 1.0],
        }
    ]
    layout.gt("scene").write_text(json.dumps({"parts": parts}))
    normal = np.zeros((4, 5, 3), np.float32)
    normal[..., :] = georef_from_local[:3, :3] @ [0, 0, 1.0]  # local +z, written in the world frame
    write_exr(layout.gt("normal_map", "uav_0"), {"N": normal, "valid": np.ones((4, 5), np.float32)})
    write_mask(layout.gt("glass_mask", "uav_0"), np.eye(4, 5, dtype=bool))
    cam = PinholeCamera(
        intrinsics(60.0, 60.0, 2.5, 2.0), look_at([0.5, 0.5, 3.0], [0.5, 0.5, 0.0], [0, 1.0, 0]), 5, 4
    )
    cam_from_world = cam.cam_from_world @ invert_rigid(georef_from_local)
    world_cam = PinholeCamera(cam.K, cam_from_world, 5, 4)
    write_pinhole_model(layout.gt("frontal_sparse_dir"), [ColmapView("frontal_0.png", world_cam)])
    return cam


def test_truth_comes_back_in_the_local_frame_with_its_precision(tmp_path):
    layout = BuildingLayout(tmp_path, "b")
    G = _georef_from_local()
    cam = _write_gt(layout, G)
    truth = SyntheticTruth.load(layout, G)
    v, f = truth.mesh("glass_mesh")
    np.testing.assert_allclose(v, SQUARE, atol=1e-9)
    closest, _, _ = truth.raycaster("glass_mesh").closest(np.array([[0.5, 0.5, 0.01]]))
    assert abs(np.linalg.norm(closest[0] - [0.5, 0.5, 0.01]) - 0.01) < 1e-5
    np.testing.assert_allclose(truth.panel_corners(), SQUARE[None], atol=1e-9)
    assert truth.panels()[0]["part_index"] == 0
    part = truth.scene_parts()[0]
    np.testing.assert_allclose(part["world_from_facade"], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(part["axis_point"], [0.5, -25.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(part["axis_direction"], [0, 0, 1.0], atol=1e-12)
    n, valid = truth.normal_map("uav_0")
    assert valid.all() and np.allclose(n, [0, 0, 1.0], atol=1e-6)
    assert truth.mask("glass", "uav_0").sum() == 4
    local = truth.frontal_camera("frontal_0")
    np.testing.assert_allclose(local.cam_from_world, cam.cam_from_world, atol=1e-6)
    with pytest.raises(InputError, match="frontal_1"):
        truth.frontal_camera("frontal_1")


def test_missing_or_bad_truth_is_named(tmp_path):
    layout = BuildingLayout(tmp_path, "b")
    with pytest.raises(InputError, match="gt: expected the ground truth"):
        SyntheticTruth.load(layout, np.eye(4))
    _write_gt(layout, np.eye(4))
    assert SyntheticTruth.available(layout, "panels", "glass_mesh")
    assert not SyntheticTruth.available(layout, "facade_mesh")
    layout.gt("panels").write_text(json.dumps({"panels": [{"corners": [[0, 0, 0]]}]}))
    with pytest.raises(InputError, match="panels.json"):
        SyntheticTruth.load(layout, np.eye(4)).panel_corners()
