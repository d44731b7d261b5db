"""Each frontal view's pose registered to the 3D panels (``panels3d.poses``): on a drawn facade whose views'
true poses are known and whose imported poses are noised, the refinement finds the true poses; a view
with too few corners keeps its imported pose and says why; the registered scene gives a UAV view that is
the same photo as a frontal view that view's pose; on gcw_dev's real photos the corners' reprojection
error falls."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.panels3d.model import Panel, PanelSet, PartSurface
from facade_pipeline.panels3d.poses import (
    MIN_CORNERS,
    RegisteredPoses,
    ViewPose,
    match_corners,
    pose_error,
    refine_pose,
    reprojection_px,
)

PITCH_S, PITCH_Z, GLASS = 3.0, 3.5, 0.8  # panel pitch along the facade and up (m), glass fraction of it


def facade_panels(rows: int = 4, cols: int = 6) -> PanelSet:
    """A planar facade in the plane y = 0 (outward -y), rows x cols panels."""
    normal = np.array([0.0, -1.0, 0.0])
    surf = PartSurface("planar", [0.0, 0.0, 0.0], normal)
    panels = []
    for r in range(rows):
        for c in range(cols):
            s0, s1 = c * PITCH_S, c * PITCH_S + GLASS * PITCH_S
            z0, z1 = r * PITCH_Z, r * PITCH_Z + GLASS * PITCH_Z
            corners = surf.points(np.array([[s0, z0, 0], [s1, z0, 0], [s1, z1, 0], [s0, z1, 0]], float))
            panels.append(Panel(0, r, c, corners, normal, 0.0))
    return PanelSet((surf,), tuple(panels))


def true_camera(eye) -> PinholeCamera:
    """A 1024 x 768 view of the facade's middle from ``eye``."""
    target = np.array([7.5, 0.0, 6.0])
    return PinholeCamera(intrinsics(900.0, 900.0, 512.0, 384.0), look_at(eye, target), 1024, 768)


def observed_quads(panels: PanelSet, cam: PinholeCamera, rng, noise_px: float) -> list[np.ndarray]:
    """Each panel's corners as the true camera sees them, with Gaussian noise (px), inside the image."""
    out = []
    for p in panels.panels:
        uv, z = cam.project(p.corners)
        if (z > 0).all() and (uv >= 0).all() and (uv < [cam.width, cam.height]).all():
            out.append(uv + rng.normal(0.0, noise_px, uv.shape))
    return out


def noised(cam: PinholeCamera, rng, turn_deg: float, move_m: float) -> PinholeCamera:
    """``cam`` turned by ``turn_deg`` about a random axis and moved by ``move_m`` in a random direction."""
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(np.radians(turn_deg) * axis / np.linalg.norm(axis)).as_matrix()
    d = rng.normal(size=3)
    T = cam.cam_from_world.copy()
    centre = cam.center + move_m * d / np.linalg.norm(d)
    T[:3, :3] = R @ T[:3, :3]
    T[:3, 3] = -T[:3, :3] @ centre
    return replace(cam, cam_from_world=T)


@pytest.mark.parametrize("eye", [(7.5, -18.0, 6.0), (3.0, -15.0, 4.0), (12.0, -20.0, 9.0)])
def test_refinement_recovers_the_true_pose_from_a_noised_one(eye):
    rng = np.random.default_rng(1)
    panels = facade_panels()
    truth = true_camera(np.array(eye))
    quads = observed_quads(panels, truth, rng, noise_px=0.3)
    imported = noised(truth, rng, turn_deg=0.4, move_m=0.15)  # several pixels at this distance
    ok = np.ones((len(quads), 4), bool)
    px, world = match_corners(quads, ok, panels, imported)
    assert len(px) == 4 * len(quads) >= 4 * 12  # every corner matched to its own panel
    r = refine_pose(imported, px, world, "v")
    assert r.refined and r.reason == ""
    turn0, move0 = pose_error(imported.cam_from_world, truth.cam_from_world)
    turn, move = pose_error(r.cam_from_world, truth.cam_from_world)
    # 0.3 px of corner noise over 50-90 corners: a few hundredths of a degree and centimetres (the planar
    # grid's rotation and translation trade against each other), from 0.4 deg and 15 cm
    assert turn < 0.05 and move < 0.03, (turn, move)
    assert turn < turn0 / 8 and move < move0 / 5
    assert r.reprojection_px < 0.6 and r.reprojection_imported_px > 3 * r.reprojection_px
    moved = replace(imported, cam_from_world=r.cam_from_world)
    assert np.isclose(r.reprojection_px, np.median(reprojection_px(moved, px, world)))


def test_a_wrong_corner_does_not_pull_the_pose():
    rng = np.random.default_rng(2)
    panels = facade_panels()
    truth = true_camera(np.array([7.5, -18.0, 6.0]))
    quads = observed_quads(panels, truth, rng, noise_px=0.3)
    quads[3] = quads[3] + [[0.0, 0.0], [25.0, 0.0], [0.0, 0.0], [0.0, 0.0]]  # one corner 25 px off
    imported = noised(truth, rng, turn_deg=0.3, move_m=0.1)
    px, world = match_corners(quads, np.ones((len(quads), 4), bool), panels, imported)
    r = refine_pose(imported, px, world)
    turn, move = pose_error(r.cam_from_world, truth.cam_from_world)
    assert r.refined and r.inliers == r.corners - 1
    assert turn < 0.05 and move < 0.03, (turn, move)


def test_a_view_with_too_few_corners_keeps_its_pose_and_says_why():
    rng = np.random.default_rng(3)
    panels = facade_panels()
    truth = true_camera(np.array([7.5, -18.0, 6.0]))
    quads = observed_quads(panels, truth, rng, noise_px=0.3)[:1]  # one panel: four corners
    imported = noised(truth, rng, turn_deg=0.4, move_m=0.15)
    px, world = match_corners(quads, np.ones((1, 4), bool), panels, imported)
    r = refine_pose(imported, px, world, "v")
    assert not r.refined and r.corners == 4 < MIN_CORNERS
    assert np.array_equal(r.cam_from_world, imported.cam_from_world)
    assert "fewer than" in r.reason and "4 matched" in r.reason
    none = refine_pose(imported, np.zeros((0, 2)), np.zeros((0, 3)), "w")
    assert not none.refined and "0 matched" in none.reason and np.isnan(none.reprojection_px)


def test_corners_on_one_line_keep_the_pose():
    rng = np.random.default_rng(4)
    panels = facade_panels()
    truth = true_camera(np.array([7.5, -18.0, 6.0]))
    imported = noised(truth, rng, turn_deg=0.2, move_m=0.05)
    world = np.stack([p.corners[0] for p in panels.panels if p.row == 1])  # bottom-left corners of a row
    world = np.concatenate([world, world + [0.0, 0.0, 1e-3]])
    px, _ = truth.project(world)
    r = refine_pose(imported, px, world)
    assert not r.refined and "one line" in r.reason


def test_unmatched_quads_are_left_out():
    rng = np.random.default_rng(5)
    panels = facade_panels()
    truth = true_camera(np.array([7.5, -18.0, 6.0]))
    quads = observed_quads(panels, truth, rng, noise_px=0.3)
    stray = quads[0] + [[0.0, 150.0]] * 4  # half a pitch down: between two panels' rows
    px, world = match_corners([*quads, stray], np.ones((len(quads) + 1, 4), bool), panels, truth)
    assert len(px) == 4 * len(quads)
    only_two = np.zeros((len(quads), 4), bool)
    only_two[:, :2] = True  # a quad's corners not on the border: the bottom two (cut by the border above)
    px, world = match_corners(quads, only_two, panels, truth)
    assert len(px) == 2 * len(quads) and np.median(reprojection_px(truth, px, world)) < 1.0


def test_poses_round_trip_and_a_damaged_file_names_itself(tmp_path):
    v = ViewPose("a", np.eye(4), True, "", 20, 19, 4.5, 0.7, 0.3, 0.01)
    w = ViewPose("b", np.eye(4), False, "3 matched panel corners, fewer than 8", 3, 0, np.nan, np.nan)
    p = tmp_path / "poses.json"
    RegisteredPoses((v, w)).save(p)
    back = RegisteredPoses.load(p)
    assert back.views[0].to_dict() == v.to_dict()
    assert back.views[1].reason == w.reason and np.isnan(back.views[1].reprojection_px)
    s = back.summary()
    assert s["views_refined"] == 1 and s["views_as_imported"] == {"b": w.reason}
    d = json.loads(p.read_text())
    d["views"][0]["cam_from_world"] = [[float("nan")] * 4] * 4
    p.write_text(json.dumps(d))
    with pytest.raises(InputError, match="poses.json"):
        RegisteredPoses.load(p)
    p.write_text("{")
    with pytest.raises(InputError, match="poses.json"):
        RegisteredPoses.load(p)
