"""The fly-through's paths: the orbit, and the path through named views (a Catmull-Rom spline through their
centres, a rotation spline through their orientations) that meets each view exactly at its key frame,
moves without jumps and has the frames asked for; ``[evaluate.video] path`` is checked like every key."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facade_pipeline.config import from_dict, load_building_config
from facade_pipeline.errors import ConfigError
from facade_pipeline.evaluation.video import (
    VideoParams,
    catmull_rom,
    key_frames,
    orbit_path,
    video_path,
    views_path,
)
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at

K = intrinsics(60.0, 60.0, 40.0, 30.0)


def _views() -> list[tuple[str, PinholeCamera]]:
    """Six UAV-like views of a facade in the plane y = 0, from 8 to 12 m in front, looking at points on it."""
    eyes = [(-6, -10, 3), (-2, -12, 5), (3, -9, 4), (7, -11, 6), (9, -8, 2), (4, -12, 8)]
    targets = [(-2, 0, 4), (0, 0, 5), (2, 0, 3), (4, 0, 5), (5, 0, 4), (1, 0, 6)]
    return [
        (f"uav_{i:04d}", PinholeCamera(K, look_at(np.array(e, float), np.array(t, float)), 80, 60))
        for i, (e, t) in enumerate(zip(eyes, targets, strict=True))
    ]


def _params(**kw) -> VideoParams:
    table = {"frames": 40, "fps": 8, "scale": 1.0, "path": "orbit"}
    return from_dict(VideoParams, table | kw, "evaluate.video")


def _turn_deg(a: PinholeCamera, b: PinholeCamera) -> float:
    r = Rotation.from_matrix(a.cam_from_world[:3, :3] @ b.cam_from_world[:3, :3].T)
    return float(np.degrees(r.magnitude()))


@pytest.mark.parametrize("names", [["uav_0001", "uav_0003", "uav_0004", "uav_0000"],
                                   ["uav_0002", "uav_0005"],
                                   ["uav_0000", "uav_0003", "uav_0000"]])  # fmt: skip
def test_the_path_meets_each_named_view_at_its_key_frame(names):
    views = dict(_views())
    path = video_path(_params(frames=37, path=names), list(views.items()))
    assert len(path) == 37
    keys = [views[n] for n in names]
    at = [i for i, cam in enumerate(path) if any(np.allclose(cam.cam_from_world, k.cam_from_world,
                                                              atol=1e-9) for k in keys)]  # fmt: skip
    assert at[0] == 0 and at[-1] == 36 and len(at) == len(names)  # met once each, in order, ends included
    for i, key in zip(at, keys, strict=True):
        assert np.allclose(path[i].cam_from_world, key.cam_from_world, atol=1e-9)
        assert np.allclose(path[i].K, key.K) and (path[i].width, path[i].height) == (key.width, key.height)


def test_the_path_moves_without_jumps():
    """Steps between frames stay near their mean in position and in turn: no jump at a view, no stop."""
    views = dict(_views())
    path = views_path([views[n] for n in ("uav_0000", "uav_0002", "uav_0003", "uav_0005", "uav_0001")], 80)
    centres = np.array([c.center for c in path])
    step = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert step.max() < 2.0 * step.mean() and step.min() > 0.2 * step.mean()
    # the speed changes gradually: neighbouring steps differ by a small part of a step
    assert np.abs(np.diff(step)).max() < 0.25 * step.mean()
    turns = np.array([_turn_deg(a, b) for a, b in zip(path[:-1], path[1:], strict=True)])
    assert turns.max() < 3.0 * turns.mean() + 1e-6 and turns.max() < 5.0  # deg per frame
    total = sum(_turn_deg(a, b) for a, b in zip(path[:-1], path[1:], strict=True))
    direct = sum(_turn_deg(views[a], views[b]) for a, b in
                 (("uav_0000", "uav_0002"), ("uav_0002", "uav_0003"), ("uav_0003", "uav_0005"),
                  ("uav_0005", "uav_0001")))  # fmt: skip
    assert total < 1.5 * direct  # no detour spins between the views


def test_catmull_rom_against_references():
    """Evenly spaced points on a line, timed by distance, give the line at constant speed (the reference:
    linear interpolation); on any points the spline passes through them at their knots."""
    pts = np.array([[0.0, 0, 0], [1, 2, 0], [2, 4, 0], [3, 6, 0]])
    knots = np.array([0.0, 1, 2, 3]) * np.sqrt(5)
    t = np.linspace(0, knots[-1], 31)
    expect = np.stack([np.interp(t, knots, pts[:, d]) for d in range(3)], axis=1)
    assert np.allclose(catmull_rom(pts, knots, t), expect, atol=1e-12)
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(6, 3))
    knots = np.cumsum(rng.uniform(0.2, 2.0, size=6))
    assert np.allclose(catmull_rom(pts, knots, knots), pts, atol=1e-12)
    # C1: the velocity from either side of an inner knot agrees
    eps = 1e-6
    for k in knots[1:-1]:
        left = (catmull_rom(pts, knots, [k])[0] - catmull_rom(pts, knots, [k - eps])[0]) / eps
        right = (catmull_rom(pts, knots, [k + eps])[0] - catmull_rom(pts, knots, [k])[0]) / eps
        assert np.allclose(left, right, atol=1e-4)


def test_key_frames_are_in_order_and_one_apart_at_least():
    assert list(key_frames(np.array([0.0, 1.0, 2.0, 3.0]), 10)) == [0, 3, 6, 9]
    assert list(key_frames(np.array([0.0, 5.0, 5.0 + 1e-9, 6.0]), 4)) == [0, 1, 2, 3]
    assert list(key_frames(np.array([0.0, 9.0, 10.0]), 11)) == [0, 9, 10]


def test_orbit_is_the_default_and_zero_frames_is_no_video():
    views = _views()
    p = _params(frames=12)
    assert p.path == "orbit"
    got = video_path(p, views)
    want = orbit_path([c for _, c in views], 12)
    assert len(got) == 12 and all(np.array_equal(a.cam_from_world, b.cam_from_world) for a, b in
                                  zip(got, want, strict=True))  # fmt: skip
    assert video_path(_params(frames=0, path=["uav_9999", "uav_0000"]), views) == []


def test_an_unknown_view_is_one_line_naming_the_key_and_the_views():
    with pytest.raises(ConfigError) as e:
        video_path(_params(path=["uav_0001", "uav_0042"]), _views())
    text = str(e.value)
    assert "\n" not in text and "evaluate.video.path" in text and "'uav_0042'" in text
    assert all(f"uav_{i:04d}" in text for i in range(6))


def test_path_values_are_checked_like_every_key():
    with pytest.raises(ConfigError, match=r"evaluate\.video\.path"):
        _params(path="spiral")
    with pytest.raises(ConfigError, match=r"at least two views"):
        _params(path=["uav_0001"])
    with pytest.raises(ConfigError, match=r"evaluate\.video\.frames"):
        _params(frames=2, path=["uav_0001", "uav_0002", "uav_0003"])
    with pytest.raises(ConfigError, match=r"evaluate\.video\.path\[1\]"):
        _params(path=["uav_0001", 3])
    assert _params(path=["uav_0001", "uav_0002"]).path == ("uav_0001", "uav_0002")


def test_a_building_file_sets_the_path(tmp_path):
    import shutil

    from facade_pipeline.config import config_dir

    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    toml = cfg / "buildings" / "synthetic64.toml"
    toml.write_text(toml.read_text() + '\n[evaluate.video]\npath = ["uav_0002", "uav_0000"]\n')
    assert load_building_config("synthetic64", cfg).section("evaluate.video", VideoParams).path == (
        "uav_0002", "uav_0000")  # fmt: skip
    assert load_building_config("synthetic64").section("evaluate.video", VideoParams).path == "orbit"
    toml.write_text(toml.read_text().replace('["uav_0002", "uav_0000"]', '["uav_0002"]'))
    with pytest.raises(ConfigError) as e:
        load_building_config("synthetic64", cfg).section("evaluate.video", VideoParams)
    assert str(e.value).startswith(str(toml)) and "evaluate.video.path" in str(e.value)
