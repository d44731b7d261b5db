"""Every number of every config section is declared with its allowed range; the shipped configs keep to
them, and a value outside one (or a min above its max) is a ConfigError naming the key and the file."""

from __future__ import annotations

import dataclasses
import shutil
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_origin

import pytest

from facade_pipeline.batch.params import BatchSettings
from facade_pipeline.config import (
    SYNTHETIC_TABLES,
    BuildingParams,
    PosInt,
    Range,
    RunSettings,
    available_buildings,
    config_dir,
    load_building_config,
)
from facade_pipeline.errors import ConfigError
from stages import PIPELINE, load_stage


def _sections() -> list[tuple[str, type]]:
    stages = [(name, load_stage(name).Params) for name in PIPELINE]
    return [("building", BuildingParams), ("run", RunSettings), ("batch", BatchSettings), *stages]


def unranged_numbers(tp: Any, key: str) -> list[str]:
    """The keys under ``tp`` (a config dataclass or a field's type) whose int or float has no ``Range``:
    through nested dataclasses, unions, tuples and Optional."""
    if dataclasses.is_dataclass(tp):
        hints = typing.get_type_hints(tp, include_extras=True)
        return [k for f in dataclasses.fields(tp) for k in unranged_numbers(hints[f.name], f"{key}.{f.name}")]
    origin = get_origin(tp)
    if origin is Annotated:
        inner, *extras = get_args(tp)
        if inner in (int, float):
            return [] if any(isinstance(e, Range) for e in extras) else [key]
        return unranged_numbers(inner, key)
    if origin is Literal:
        return []
    if origin is not None:  # a union, tuple[...], Optional
        return [k for arg in get_args(tp) if arg is not Ellipsis for k in unranged_numbers(arg, key)]
    if tp is int or tp is float:
        return [key]
    return []


def test_every_number_of_every_section_has_a_range():
    missing = [k for name, cls in _sections() for k in unranged_numbers(cls, name)]
    assert not missing, f"numbers declared without a Range (use PosInt, Fraction, ...): {missing}"


@dataclass(frozen=True)
class _Inner:
    ok: PosInt
    size_m: tuple[float, float]


@dataclass(frozen=True)
class _Outer:
    mode: Literal["a", "b"]
    scale: float | Literal["auto"]
    parts: tuple[_Inner, ...]
    count: int | None = None
    flag: bool = False


def test_the_walk_finds_numbers_without_a_range():
    assert unranged_numbers(_Outer, "x") == ["x.scale", "x.parts.size_m", "x.parts.size_m", "x.count"]
    assert unranged_numbers(_Inner, "y") == ["y.size_m", "y.size_m"]


@pytest.mark.parametrize("building", available_buildings())
def test_every_building_loads_every_section(building):
    cfg = load_building_config(building)
    for name, cls in _sections():
        if name in SYNTHETIC_TABLES and cfg.building.kind != "synthetic":
            assert name not in cfg.tables  # simulator keys only where there is a simulator
            continue
        cfg.section(name, cls)


@pytest.fixture
def write_building(tmp_path):
    """Writes ``configs/buildings/bad.toml`` (a synthetic building for a simulator table) beside a copy of
    default.toml and synthetic.toml; returns its path."""
    d = tmp_path / "configs"
    (d / "buildings").mkdir(parents=True)
    for name in ("default.toml", "synthetic.toml"):
        shutil.copy(config_dir() / name, d / name)

    def write(table: str, lines: str) -> Path:
        p = d / "buildings" / "bad.toml"
        kind = "synthetic" if table.split(".")[0] in SYNTHETIC_TABLES else "real"
        p.write_text(f'[building]\nkind = "{kind}"\ndescription = "x"\n\n[{table}]\n{lines}\n')
        return p

    return write


BAD_VALUES = [
    # (table, lines of the table, key the error names, a fragment of the message)
    ("train_gs", "iterations = -5", "train_gs.iterations", ">= 1"),
    ("train_gs", "patch_px = -32", "train_gs.patch_px", ">= 0"),
    ("train_gs.densify", "max_gaussians = -1", "train_gs.densify.max_gaussians", ">= 1"),
    ("run", "checkpoint_every = -1", "run.checkpoint_every", ">= 0"),
    ("run", "overlay_scale = 0.0", "run.overlay_scale", "> 0"),
    ("segment_panels", "upsample = 0", "segment_panels.upsample", ">= 1"),
    ("rectify.warp", "degree = -1", "rectify.warp.degree", ">= 1"),
    ("bake_normals", "chunk_rays = 0", "bake_normals.chunk_rays", ">= 1"),
    ("synthesize.render", "chunk_rays = 0", "synthesize.render.chunk_rays", ">= 1"),
    ("train_gs", "lowpass_sigma_px = -1.0", "train_gs.lowpass_sigma_px", "> 0"),
    ("train_gs", "lowpass_sigma_px = 0.0", "train_gs.lowpass_sigma_px", "> 0"),
    ("train_gs", "init_reflectivity_glass = 1.5", "train_gs.init_reflectivity_glass", "<= 1"),
    ("synthesize.coarse", "glass_hole_fraction = 1.5", "synthesize.coarse.glass_hole_fraction", "<= 1"),
    ("segment_panels.grid", "sigma_frac = nan", "segment_panels.grid.sigma_frac", "found nan"),
    ("train_gs", "lowpass_sigma_px = inf", "train_gs.lowpass_sigma_px", "> 0, found inf"),
    ("train_gs.lr", "position_init = -inf", "train_gs.lr.position_init", "found -inf"),
    ("rectify", "occlusion_margin = -inf", "rectify.occlusion_margin", ">= 0 (or inf)"),
    ("rectify", "max_view_angle_deg = 90.0", "rectify.max_view_angle_deg", "< 90"),
    ("rectify", "metres_per_px = -0.01", "rectify.metres_per_px", "> 0"),
    ("correct_mesh", "panel_color = [0.3, 1.5, 0.8]", "correct_mesh.panel_color[1]", "<= 1"),
    ("train_gs", "sh_degree = 4", "train_gs.sh_degree", "<= 3"),
    ("evaluate.align", "steps = -1", "evaluate.align.steps", ">= 0"),
    # a min above its max
    ("segment_panels.grid", "min_pitch = 7.0", "segment_panels.grid.min_pitch", "max_pitch"),
    ("segment_panels.grid", "min_bar = 0.5", "segment_panels.grid.min_bar", "max_bar"),
    ("synthesize.environment", "building_width_m = [28.0, 14.0]", "synthesize.environment.building_width_m",
     "low <= high"),
    ("synthesize.environment", "tree_height_m = [9.0, 5.0]", "synthesize.environment.tree_height_m",
     "low <= high"),
]


@pytest.mark.parametrize(("table", "lines", "key", "fragment"), BAD_VALUES, ids=[c[1] for c in BAD_VALUES])
def test_a_value_out_of_range_names_key_file_and_range(write_building, table, lines, key, fragment):
    path = write_building(table, lines)
    section = table.split(".")[0]
    cfg = load_building_config("bad", path.parents[1])
    with pytest.raises(ConfigError) as e:
        cfg.section(section, dict(_sections())[section])
    message = str(e.value)
    assert f"'{key}'" in message and str(path) in message and fragment in message, message
    assert "\n" not in message


def test_the_bounds_themselves_are_allowed(write_building):
    """Closed ends are in range: a fraction of 0 and of 1, a count of 0; inf where a limit may be off."""
    lines = "init_reflectivity = 1.0\ninit_reflectivity_glass = 0.0\nmlp_max_pixels = 0"
    path = write_building("train_gs", lines)
    cfg = load_building_config("bad", path.parents[1])
    p = cfg.section("train_gs", load_stage("train_gs").Params)
    assert (p.init_reflectivity, p.init_reflectivity_glass, p.mlp_max_pixels) == (1.0, 0.0, 0)
    path = write_building("rectify", "occlusion_margin = inf")
    cfg = load_building_config("bad", path.parents[1])
    assert cfg.section("rectify", load_stage("rectify").Params).occlusion_margin == float("inf")
