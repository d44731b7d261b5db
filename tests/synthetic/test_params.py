"""The [synthesize] config: every shipped scene loads, and bad values raise ConfigError naming the key."""

from __future__ import annotations

import dataclasses
import shutil

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


def test_demo_declares_every_effect_and_both_kinds():
    p = shipped("demo")
    assert set(p.effects) == set(ALL_EFFECTS)
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
    shutil.copy(config_dir() / "default.toml", tmp_path / "default.toml")
    (tmp_path / "buildings").mkdir()
    (tmp_path / "buildings" / "bad.toml").write_text(
        '[building]\nkind = "synthetic"\n[synthesize.cameras]\nfov_deg = "wide"\n'
    )
    with pytest.raises(ConfigError) as e:
        load_building_config("bad", tmp_path).section("synthesize", SynthesizeParams)
    assert "synthesize.cameras.fov_deg" in str(e.value) and "bad.toml" in str(e.value)
    (tmp_path / "buildings" / "bad.toml").write_text("[synthesize.cameras]\nfov = 50.0\n")
    with pytest.raises(ConfigError, match=r"synthesize\.cameras\.fov"):
        load_building_config("bad", tmp_path)


def test_frontal_distance_too_small_for_a_panel_is_a_config_error():
    from facade_pipeline.synthetic.simulate import planned_frontal_views

    p = replace_in(shipped("synthetic64"), "cameras", frontal_distance_m=1.0)
    with pytest.raises(ConfigError, match="frontal_distance_m"):
        planned_frontal_views(p)


def test_a_tree_hiding_a_frontal_view_is_a_config_error():
    from facade_pipeline.synthetic.cameras import check_frontal_views
    from facade_pipeline.synthetic.render import SceneArrays, Tracer
    from facade_pipeline.synthetic.scene import build_scene
    from facade_pipeline.synthetic.simulate import planned_frontal_views
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
