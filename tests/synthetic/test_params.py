"""The [synthesize] config: every shipped scene loads, and bad values raise ConfigError naming the key."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from facade_pipeline.config import config_dir, from_dict, load_building_config, to_dict
from facade_pipeline.errors import ConfigError
from facade_pipeline.synthetic.params import ALL_EFFECTS, SynthesizeParams
from tests.synthetic.conftest import replace_in, shipped


@pytest.mark.parametrize("building", ["synthetic64", "synthetic64_curved", "demo"])
def test_shipped_scenes_load(building):
    p = shipped(building)
    assert load_building_config(building).building.kind == "synthetic"
    assert set(p.effects) <= set(ALL_EFFECTS)
    assert from_dict(SynthesizeParams, to_dict(p)) == p  # a manifest's params rebuild the same scene


#: the effects of frontal photos taken on site, which real_like declares and demo (UAV-first) does not
REAL_LIKE_EFFECTS = {"exposure_spread", "lens_distortion", "unglazed_units", "masts_and_cranes"}


def test_demo_and_real_like_declare_every_effect_and_demo_both_kinds():
    p = shipped("demo")
    assert set(p.effects) == set(ALL_EFFECTS) - REAL_LIKE_EFFECTS
    assert REAL_LIKE_EFFECTS <= set(shipped("real_like").effects)
    assert {part.kind for part in p.parts} == {"planar", "cylindrical"}


def _table(**changes):
    t = to_dict(shipped("synthetic64"))
    for key, value in changes.items():
        *path, last = key.split(".")
        node = t
        for k in path:
            node = node[int(k)] if k.isdigit() else node[k]
        node[last] = value
    return t


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        ("parts.0.kind", "cylindrical", "synthesize.effects"),
        ("parts.0.radius_m", 5.0, "synthesize.parts[0].radius_m"),
        ("parts.0.cols", 40, "synthesize.parts[0].cols"),
        ("facade.glass_reflectivity", 1.5, "synthesize.facade.glass_reflectivity"),
        ("render.supersample", 0, "synthesize.render.supersample"),
        ("cameras.uav_azimuth_deg", 95.0, "synthesize.cameras.uav_azimuth_deg"),
        ("effects", ["fresnel", "fresnel"], "synthesize.effects"),
        ("effects", ["curved"], "synthesize.effects"),
        ("environment.tree_height_m", [9.0, 5.0], "synthesize.environment.tree_height_m"),
        ("cameras.frontal_width_px", -1, "synthesize.cameras.frontal_width_px"),
        ("render.frontal_supersample", -1, "synthesize.render.frontal_supersample"),
    ],
)
def test_inconsistent_values_name_the_key(key, value, named):
    with pytest.raises(ConfigError) as e:
        from_dict(SynthesizeParams, _table(**{key: value}), "synthesize")
    assert named in str(e.value)


def test_curved_part_needs_the_curved_effect():
    p = shipped("synthetic64_curved")
    with pytest.raises(ConfigError, match="'curved'"):
        dataclasses.replace(p, effects=tuple(e for e in p.effects if e != "curved"))


def test_cylinder_radius_must_exceed_the_body_depth():
    p = shipped("synthetic64_curved")
    part = dataclasses.replace(p.parts[0], radius_m=p.facade.body_depth_m / 2)
    with pytest.raises(ConfigError, match=r"synthesize\.parts\[0\]\.radius_m"):
        dataclasses.replace(p, parts=(part,))


def test_unknown_effect_and_wrong_type_name_the_key():
    with pytest.raises(ConfigError, match=r"synthesize\.effects\[0\]"):
        from_dict(SynthesizeParams, _table(effects=["mirror_ball"]), "synthesize")
    with pytest.raises(ConfigError, match=r"synthesize\.facade\.frame_width_m"):
        from_dict(SynthesizeParams, _table(**{"facade.frame_width_m": "wide"}), "synthesize")


def test_bad_building_file_is_reported_with_its_key(tmp_path):
    for name in ("default.toml", "synthetic.toml"):
        shutil.copy(config_dir() / name, tmp_path / name)
    (tmp_path / "buildings").mkdir()
    (tmp_path / "buildings" / "bad.toml").write_text(
        '[building]\nkind = "synthetic"\n[synthesize.cameras]\nfov_deg = "wide"\n'
    )
    with pytest.raises(ConfigError) as e:
        load_building_config("bad", tmp_path).section("synthesize", SynthesizeParams)
    assert "synthesize.cameras.fov_deg" in str(e.value) and "bad.toml" in str(e.value)
    text = '[building]\nkind = "synthetic"\n[synthesize.cameras]\nfov = 50.0\n'
    (tmp_path / "buildings" / "bad.toml").write_text(text)
    with pytest.raises(ConfigError, match=r"synthesize\.cameras\.fov"):
        load_building_config("bad", tmp_path)


def test_frontal_distance_too_small_for_a_panel_is_a_config_error():
    from facade_pipeline.synthetic.cameras import planned_frontal_views

    p = replace_in(shipped("synthetic64"), "cameras", frontal_distance_m=1.0)
    with pytest.raises(ConfigError, match="frontal_distance_m"):
        planned_frontal_views(p)


def test_a_tree_hiding_a_frontal_view_is_a_config_error():
    from facade_pipeline.synthetic.cameras import check_frontal_views, planned_frontal_views
    from facade_pipeline.synthetic.render import SceneArrays, Tracer
    from facade_pipeline.synthetic.scene import build_scene
    from tests.synthetic.conftest import tiny

    for distance, hidden in (((12.0, 20.0), False), ((2.0, 4.0), True)):
        p = replace_in(
            tiny(), "environment", tree_count=30, tree_distance_m=distance, tree_height_m=(6.0, 8.0)
        )
        scene = build_scene(p)
        tracer = Tracer(scene.mesh)
        views = planned_frontal_views(p)
        if hidden:
            with pytest.raises(ConfigError, match="frontal view"):
                check_frontal_views(views, scene.panels, tracer, SceneArrays.of(scene))
        else:
            check_frontal_views(views, scene.panels, tracer, SceneArrays.of(scene))


def test_frontal_views_have_their_own_resolution():
    """Frontal views default to the UAV size (0); set, they get it with the same horizontal field of view
    (a finer pixel), and every panel of each view's block still fits (planning raises otherwise)."""
    from facade_pipeline.synthetic.cameras import planned_frontal_views

    zero = {"cameras.frontal_width_px": 0, "cameras.frontal_height_px": 0, "render.frontal_supersample": 0}
    p = from_dict(SynthesizeParams, _table(**zero))
    assert p.cameras.frontal_size_px == (p.cameras.width_px, p.cameras.height_px)
    base = planned_frontal_views(p)
    assert {(v.camera.width, v.camera.height) for v in base} == {(p.cameras.width_px, p.cameras.height_px)}
    big = planned_frontal_views(
        from_dict(
            SynthesizeParams, _table(**{"cameras.frontal_width_px": 160, "cameras.frontal_height_px": 120})
        )
    )
    assert {(v.camera.width, v.camera.height) for v in big} == {(160, 120)}
    assert big[0].camera.K[0, 0] == pytest.approx(160 / p.cameras.width_px * base[0].camera.K[0, 0])
    assert p.render.supersample_for("frontal") == p.render.supersample  # frontal_supersample 0
    odd = from_dict(SynthesizeParams, _table(**{"render.frontal_supersample": 3})).render
    assert (odd.supersample_for("frontal"), odd.supersample_for("uav")) == (3, p.render.supersample)


def test_oblique_frontal_views_of_the_shipped_scene():
    """`oblique` turns its frontal views by up to 35 deg of yaw and of pitch from the facade's normal, spread
    over both signs, and renders them at 1600 x 1200 with frame bars of 20-60 px."""
    from facade_pipeline.synthetic.cameras import planned_frontal_views

    p = shipped("oblique")
    views = planned_frontal_views(p)
    assert {(v.camera.width, v.camera.height) for v in views} == {(1600, 1200)}
    yaws, pitches, bars = [], [], []
    for v in views:
        fwd = v.camera.forward
        view_dir = -fwd  # from the target toward the eye
        yaws.append(np.degrees(np.arctan2(view_dir[0], view_dir[1])))  # both parts face +y (facing_deg 90)
        pitches.append(np.degrees(np.arcsin(view_dir[2])))
        depth = p.cameras.frontal_distance_m  # along the view direction to the block centre
        bars.append(p.facade.frame_width_m * v.camera.K[0, 0] / depth)
    yaws, pitches = np.array(yaws), np.array(pitches)
    assert np.abs(pitches).max() <= 35.0 + 1e-6 and (pitches > 10).any() and (pitches < -10).any()
    curved = np.array([v.block[0] == 1 for v in views])
    assert np.abs(yaws[~curved]).max() <= 35.0 + 1e-6 and (yaws[~curved] > 10).any()
    assert (yaws[~curved] < -10).any()
    assert 20 <= min(bars) * np.cos(np.radians(35)) and max(bars) <= 60


def test_oblique_direction_is_the_normal_at_zero_and_keeps_the_eye_above_ground():
    from facade_pipeline.synthetic.cameras import oblique_direction

    n = np.array([0.0, 1.0, 0.0])
    assert np.allclose(oblique_direction(n, 3, (0.0, 0.0), np.zeros(3), 9.0, 2.0), n)
    for k in range(20):
        d = oblique_direction(n, k, (35.0, 35.0), np.array([0.0, 0.0, 5.0]), 9.0, 2.0)
        assert abs(np.linalg.norm(d) - 1.0) < 1e-12 and 5.0 + 9.0 * d[2] >= 2.0
        assert np.degrees(np.arccos(d @ n)) <= 50.0  # yaw and pitch of 35 deg each at most
