"""A small synthetic64 building, made once per session: synthesize (fewer UAV views), import, 03_segment
files from ground truth (tests/meshing/segment_from_gt.py), then the three 3D stages."""

from __future__ import annotations

import dataclasses

import pytest

from facade_pipeline.config import load_building_config
from facade_pipeline.layout import BuildingLayout
from stages import _runner
from tests.meshing.segment_from_gt import write_segment_from_gt

MY_STAGES = ("regularize_corners", "correct_mesh", "bake_normals")


def stage_module(name: str):
    import importlib

    return importlib.import_module(f"stages.{name}")


def params_of(name: str, building: str = "synthetic64", **changes):
    stage = stage_module(name)
    p = load_building_config(building).section(name, stage.Params)
    return dataclasses.replace(p, **changes) if changes else p


def run_stage(name: str, layout: BuildingLayout, **changes) -> dict:
    return _runner.execute(stage_module(name), layout, params_of(name, layout.building, **changes))


@pytest.fixture(scope="session")
def built64(tmp_path_factory):
    """synthetic64 with 4 UAV views at 64 px, through bake_normals; returns its layout."""
    layout = BuildingLayout(tmp_path_factory.mktemp("meshing") / "data", "synthetic64")
    syn = params_of("synthesize")
    syn = dataclasses.replace(syn, cameras=dataclasses.replace(syn.cameras, uav_count=4))
    _runner.execute(stage_module("synthesize"), layout, syn)
    run_stage("import_photogrammetry", layout)
    write_segment_from_gt(layout, noise_px=0.3, seed=1)
    for name in MY_STAGES:
        run_stage(name, layout)
    return layout
