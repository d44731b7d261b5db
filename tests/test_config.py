"""The config system: every building loads, every parameter is commented, bad keys and types are errors."""

from __future__ import annotations

import dataclasses
import re
import shutil
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pytest

from facade_pipeline.config import (
    MACHINE_TABLES,
    RunSettings,
    available_buildings,
    config_dir,
    from_dict,
    load_building_config,
)
from facade_pipeline.errors import ConfigError
from stages import PIPELINE, load_stage

EXPECTED_BUILDINGS = {"demo", "synthetic64", "synthetic64_curved", "shatin", "hkust_library"}


def test_shipped_buildings_load_every_existing_stage():
    assert EXPECTED_BUILDINGS <= set(available_buildings())
    for building in available_buildings():
        cfg = load_building_config(building)
        for name in PIPELINE:
            if name == "synthesize" and cfg.building.kind != "synthetic":
                continue
            stage = load_stage(name)
            params = cfg.section(name, stage.Params)
            assert params.__dataclass_params__.frozen


def test_paper_settings_on_the_paper_buildings():
    for building in ("shatin", "hkust_library"):
        t = load_building_config(building).tables["train_gs"]
        mlp = t["reflection"]["mlp"]
        assert t["iterations"] == 200_000 and t["reflection"]["model"] == "mlp"
        assert (mlp["fourier_levels"], mlp["depth"], mlp["width"], mlp["skip"]) == (12, 8, 512, True)
        assert (t["lambda_normal"], t["lambda_normal_prior"]) == (0.05, 1.0)
        assert (t["lambda_hf_start"], t["lambda_hf_end"], t["hf_tau_start"], t["hf_tau_end"]) == (
            1,
            10,
            0.2,
            0.09,
        )


@pytest.mark.parametrize("name", ["default.toml", "synthetic.toml"])
def test_every_default_parameter_has_a_comment(name):
    for i, line in enumerate((config_dir() / name).read_text().splitlines(), 1):
        if re.match(r"^\s*[A-Za-z_][A-Za-z0-9_]*\s*=", line):
            assert "#" in line.split("=", 1)[1], f"{name}:{i} has no comment: {line}"


@pytest.fixture
def cfg_dir(tmp_path):
    d = tmp_path / "configs"
    shutil.copytree(config_dir(), d)
    return d


def _write(d: Path, building: str, text: str) -> Path:
    p = d / "buildings" / f"{building}.toml"
    p.write_text(text)
    return p


def test_unknown_key_names_key_and_file(cfg_dir):
    p = _write(
        cfg_dir,
        "typo",
        '[building]\nkind = "real"\ndescription = "x"\n[import_photogrammetry]\nup_axiz = "+z"\n',
    )
    with pytest.raises(ConfigError) as e:
        load_building_config("typo", cfg_dir)
    assert "up_axiz" in str(e.value) and str(p) in str(e.value)


def test_wrong_type_names_key_and_file(cfg_dir):
    p = _write(
        cfg_dir,
        "bad",
        '[building]\nkind = "real"\ndescription = "x"\n[import_photogrammetry]\norigin_rounding_m = "far"\n',
    )
    cfg = load_building_config("bad", cfg_dir)
    stage = load_stage("import_photogrammetry")
    with pytest.raises(ConfigError) as e:
        cfg.section("import_photogrammetry", stage.Params)
    assert "origin_rounding_m" in str(e.value) and str(p) in str(e.value) and "'far'" in str(e.value)


def test_bad_choice_and_unknown_building(cfg_dir):
    _write(cfg_dir, "bad", '[building]\nkind = "imaginary"\ndescription = "x"\n')
    with pytest.raises(ConfigError, match="kind"):
        _ = load_building_config("bad", cfg_dir).building
    with pytest.raises(ConfigError, match="nosuch"):
        load_building_config("nosuch", cfg_dir)


def test_toml_syntax_error_names_file(cfg_dir):
    p = _write(cfg_dir, "broken", "[building\nkind=")
    with pytest.raises(ConfigError) as e:
        load_building_config("broken", cfg_dir)
    assert str(p) in str(e.value)


@dataclass(frozen=True)
class _Inner:
    size_m: tuple[float, float]


@dataclass(frozen=True)
class _Outer:
    mode: Literal["a", "b"]
    parts: tuple[_Inner, ...]
    count: int = 3


def test_from_dict_nested_and_strict():
    o = from_dict(_Outer, {"mode": "a", "parts": [{"size_m": [1, 2.5]}]})
    assert o == _Outer("a", (_Inner((1.0, 2.5)),), 3)
    for bad, key in [
        ({"mode": "c", "parts": []}, "mode"),
        ({"mode": "a", "parts": [{"size_m": [1]}]}, "parts[0].size_m"),
        ({"mode": "a", "parts": [], "count": 1.5}, "count"),
        ({"mode": "a", "parts": [], "count": True}, "count"),
        ({"mode": "a"}, "parts"),
    ]:
        with pytest.raises(ConfigError, match=re.escape(key)):
            from_dict(_Outer, bad)


def test_a_nested_section_by_its_dotted_name(cfg_dir):
    """``evaluate.align`` is the [evaluate.align] table, as in the whole [evaluate] section; a building's
    value wins; a name with no such table is one error naming it."""
    from facade_pipeline.training.params import AlignParams

    _write(cfg_dir, "nested", '[building]\nkind = "real"\ndescription = "x"\n[evaluate.align]\nsteps = 7\n')
    cfg = load_building_config("nested", cfg_dir)
    align = cfg.section("evaluate.align", AlignParams)
    assert align.steps == 7 and align == cfg.section("evaluate", load_stage("evaluate").Params).align
    with pytest.raises(ConfigError, match=r"\[evaluate.nosuch\]"):
        cfg.section("evaluate.nosuch", AlignParams)


@pytest.mark.parametrize(("section", "key", "replacement"), [
    ("segment_panels.grid", "max_bar_px", "segment_panels.grid.max_bar"),
    ("segment_panels.grid", "min_bar_m", "segment_panels.grid.min_bar"),
    ("segment_panels", "min_partial_px", "segment_panels.min_partial"),
    ("rectify.warp", "planar_shift_px", "rectify.metres_per_px"),
    ("train_gs", "device", "run.device"),
    ("train_gs", "raster_backend", "run.raster_backend"),
    ("train_gs", "log_every", "run.log_every"),
    ("train_gs", "checkpoint_every", "run.checkpoint_every"),
    ("evaluate", "device", "run.device"),
    ("rectify", "overlay_scale", "run.overlay_scale"),
    ("segment_panels", "overlay_scale", "run.overlay_scale"),
    ("correct_mesh", "target_normal_error_deg", "benchmarks/bench_bake.py"),
    ("regularize_corners", "depth_refinement", "coarse points' mode"),
    ("rectify.fit", "ransac_iterations", "a constant in facade_pipeline/rectification/cylinder.py"),
])
def test_an_old_key_names_its_replacement(cfg_dir, section, key, replacement):
    _write(cfg_dir, "old", f'[building]\nkind = "real"\n\n[{section}]\n{key} = 10\n')
    with pytest.raises(ConfigError) as e:
        load_building_config("old", cfg_dir)
    msg = str(e.value)
    assert f"{section}.{key}" in msg and replacement in msg and "old.toml" in msg


@pytest.mark.parametrize(("key", "replacement"), [
    ("reflection_model", "train_gs.reflection.model"),
    ("mlp_width", "train_gs.reflection.mlp.width"),
    ("fourier_levels", "train_gs.reflection.mlp.fourier_levels"),
    ("mlp_proxy_channels", "train_gs.reflection.proxy.channels"),
    ("envmap_height_px", "train_gs.reflection.envmap.height_px"),
    ("mlp_self_hits", "removed"),
    ("mlp_proxy_surroundings", "surroundings"),
    ("near_m", "splatting/types.py"),
    ("lambda_dssim", "training/losses.py"),
    ("exposure", "ExposureParams"),
])
def test_an_old_train_gs_key_names_its_replacement(cfg_dir, key, replacement):
    _write(cfg_dir, "old", f'[building]\nkind = "real"\n\n[train_gs]\n{key} = 10\n')
    with pytest.raises(ConfigError) as e:
        load_building_config("old", cfg_dir)
    msg = str(e.value)
    assert f"train_gs.{key}" in msg and replacement in msg and "old.toml" in msg and "\n" not in msg
def test_simulator_keys_only_in_a_synthetic_building(cfg_dir):
    """synthetic.toml lies under a synthetic building's file and no real one's; a real building that sets
    a simulator key is one line naming its file and the kind it needs."""
    p = _write(cfg_dir, "realsim", '[building]\nkind = "real"\n[synthesize.cameras]\nuav_count = 5\n')
    with pytest.raises(ConfigError) as e:
        load_building_config("realsim", cfg_dir)
    msg = str(e.value)
    assert str(p) in msg and 'kind = "synthetic"' in msg and "'synthesize'" in msg and "\n" not in msg
    p = _write(cfg_dir, "realsim", '[building]\nkind = "real"\n[correct_mesh]\nmetric_samples = 5\n')
    with pytest.raises(ConfigError, match=r"correct_mesh\.metric_samples.*real building"):
        load_building_config("realsim", cfg_dir)
    correct_mesh = load_stage("correct_mesh").Params
    assert load_building_config("shatin").section("correct_mesh", correct_mesh).metric_samples is None
    _write(cfg_dir, "sim", '[building]\nkind = "synthetic"\n[synthesize.cameras]\nuav_count = 5\n')
    sim = load_building_config("sim", cfg_dir)
    assert sim.tables["synthesize"]["cameras"]["uav_count"] == 5  # the building wins
    assert sim.tables["synthesize"]["seed"] == 0  # synthetic.toml's, under it
    assert "synthesize" not in load_building_config("shatin").tables


def test_a_bad_simulator_default_names_synthetic_toml(cfg_dir):
    from facade_pipeline.synthetic.params import SynthesizeParams

    text = (cfg_dir / "synthetic.toml").read_text().replace("uav_count = 20", "uav_count = 0")
    (cfg_dir / "synthetic.toml").write_text(text)
    _write(cfg_dir, "sim", '[building]\nkind = "synthetic"\n')
    with pytest.raises(ConfigError) as e:
        load_building_config("sim", cfg_dir).section("synthesize", SynthesizeParams)
    assert "synthetic.toml" in str(e.value) and "uav_count" in str(e.value)


def test_run_settings_are_their_own_table(cfg_dir):
    """[run] is read into RunSettings and is no stage's parameter (so it can rerun nothing)."""
    _write(cfg_dir, "gpu", '[building]\nkind = "real"\n[run]\ndevice = "auto"\nlog_every = 7\n')
    run = load_building_config("gpu", cfg_dir).run
    assert (run.device, run.log_every) == ("auto", 7)
    assert run.checkpoint_every == load_building_config("shatin").run.checkpoint_every  # default.toml's
    run_keys = {f.name for f in dataclasses.fields(RunSettings)}
    for name in PIPELINE:
        assert not run_keys & {f.name for f in dataclasses.fields(load_stage(name).Params)}, name


#: the most keys a real building's config may have (default.toml's leaves; synthetic.toml's are not seen):
#: a config a user can read through (two pixel budgets, of the trained views and of the alignment's fit;
#: the processes a stage's per-view loop may use; whether train_gs compiles its step on a GPU; the weight of
#: the facade's pull toward opaque; the score above which a unit is no pane, ``mirror_max_score``)
KEY_BUDGET = 126


def _leaf_keys(table: dict) -> int:
    return sum(_leaf_keys(v) if isinstance(v, dict) else 1 for v in table.values())


def test_a_real_building_sees_at_most_the_key_budget():
    cfg = load_building_config("shatin")
    assert cfg.building.kind == "real" and len(cfg.files) == 2  # default.toml and its own file only
    per_table = {
        name: _leaf_keys(t) if isinstance(t, dict) else 1
        for name, t in cfg.default_tables.items()
        if name not in MACHINE_TABLES  # the machines', which a building's file may not set
    }
    count = sum(per_table.values())
    assert "synthesize" not in per_table
    assert count <= KEY_BUDGET, f"a real building sees {count} keys, more than {KEY_BUDGET}: {per_table}"


def test_every_replaced_key_is_gone_from_the_defaults():
    """An old key that default.toml or synthetic.toml still had would be refused from every building."""
    from facade_pipeline.config import RENAMED

    for name in ("default.toml", "synthetic.toml"):
        tables = tomllib.loads((config_dir() / name).read_text())
        for key in RENAMED:
            node = tables
            for part in key.split("."):
                node = node.get(part) if isinstance(node, dict) else None
            assert node is None, f"{name} still defines {key}"


def test_the_gpu_budget_is_one_switch(monkeypatch):
    """``FACADE_BUDGET=gpu`` trains demo at the defaults' budget (their steps, whole images, the paper's
    MLP) with demo's own departures kept; unset, demo keeps the CPU budget that `make run` trains."""
    default = tomllib.loads((config_dir() / "default.toml").read_text())["train_gs"]
    monkeypatch.delenv("FACADE_BUDGET", raising=False)
    cpu = load_building_config("demo").tables["train_gs"]
    assert (cpu["iterations"], cpu["patch_px"], cpu["reflection"]["mlp"]["width"]) == (700, 128, 256)
    monkeypatch.setenv("FACADE_BUDGET", "gpu")
    gpu = load_building_config("demo").tables["train_gs"]
    assert (gpu["iterations"], gpu["patch_px"]) == (default["iterations"], 0)
    assert gpu["reflection"]["mlp"] == default["reflection"]["mlp"]
    assert cpu["pose_refinement"] is gpu["pose_refinement"] is True
    monkeypatch.setenv("FACADE_BUDGET", "cpu")
    assert load_building_config("demo").tables["train_gs"] == cpu


def test_a_bad_budget_names_the_variable_or_the_key(cfg_dir, monkeypatch):
    monkeypatch.setenv("FACADE_BUDGET", "tpu")
    with pytest.raises(ConfigError, match=r"\$FACADE_BUDGET one of cpu, gpu, found 'tpu'"):
        load_building_config("demo", cfg_dir)
    monkeypatch.delenv("FACADE_BUDGET")
    real = '[building]\nkind = "real"\ndescription = "x"\n'
    p = _write(cfg_dir, "typo", real + "[budget.gpu.train_gs]\niteratoins = 5\n")
    with pytest.raises(ConfigError, match="unknown key 'budget.gpu.train_gs.iteratoins'") as e:
        load_building_config("typo", cfg_dir)  # an unused budget's typo shows too
    assert str(p) in str(e.value)
    _write(cfg_dir, "typo", real + "[budget.fast.train_gs]\niterations = 5\n")
    with pytest.raises(ConfigError, match=r"name one of cpu, gpu, found \[budget.fast\]"):
        load_building_config("typo", cfg_dir)
    _write(cfg_dir, "ok", real + "[train_gs]\niterations = 7\n[budget.gpu.train_gs]\niterations = 5\n")
    assert load_building_config("ok", cfg_dir).tables["train_gs"]["iterations"] == 7
    monkeypatch.setenv("FACADE_BUDGET", "gpu")
    assert load_building_config("ok", cfg_dir).tables["train_gs"]["iterations"] == 5
