"""Tiny synthetic scenes for the simulator's tests: synthetic64's config with fewer, smaller views."""

from __future__ import annotations

import dataclasses

import pytest

from facade_pipeline.config import load_building_config
from facade_pipeline.synthetic.params import SynthesizeParams
from facade_pipeline.synthetic.simulate import build_simulator


def shipped(building: str) -> SynthesizeParams:
    return load_building_config(building).section("synthesize", SynthesizeParams)


def tiny(building: str = "synthetic64", uav_count: int = 3, size_px: int = 48, **changes) -> SynthesizeParams:
    """A shipped synthetic scene made smaller; ``changes`` replace top-level fields. Frontal views take the
    UAV views' size and sampling (the shipped frontal resolution and supersampling are reset to 0)."""
    p = shipped(building)
    cams = dataclasses.replace(
        p.cameras,
        uav_count=uav_count,
        width_px=size_px,
        height_px=size_px,
        frontal_width_px=0,
        frontal_height_px=0,
    )
    coarse = dataclasses.replace(
        p.coarse, environment_points=1000, ghost_points_per_part=200, sparse_points=200
    )
    render = dataclasses.replace(p.render, frontal_supersample=0)
    return dataclasses.replace(p, cameras=cams, coarse=coarse, render=render, **changes)


def without(p: SynthesizeParams, effect: str) -> SynthesizeParams:
    assert effect in p.effects
    return dataclasses.replace(p, effects=tuple(e for e in p.effects if e != effect))


def with_effects(p: SynthesizeParams, *effects: str) -> SynthesizeParams:
    return dataclasses.replace(p, effects=tuple(dict.fromkeys(p.effects + effects)))


def replace_in(p: SynthesizeParams, table: str, **changes) -> SynthesizeParams:
    """``p`` with fields of one nested table (``facade``, ``cameras``...) replaced."""
    return dataclasses.replace(p, **{table: dataclasses.replace(getattr(p, table), **changes)})


@pytest.fixture(scope="module")
def planar_sim():
    return build_simulator(tiny())


@pytest.fixture(scope="module")
def curved_sim():
    return build_simulator(tiny("synthetic64_curved"))
