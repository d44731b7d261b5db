"""The real building's training settings are a compute budget's, not the building's: gcw_dev.toml sets no
``[train_gs]`` key outside its ``[budget.<name>]`` tables (every length of training follows from the scene,
``training.params``), and its CPU budget is the one a fresh shell trains with."""

from __future__ import annotations

import tomllib

from facade_pipeline.config import config_dir, load_building_config
from facade_pipeline.training.params import TrainParams


def _table(path, name: str) -> dict:
    with open(path, "rb") as f:
        return tomllib.load(f).get(name, {})


def test_gcw_dev_sets_no_training_key_beyond_its_budgets():
    path = config_dir() / "buildings" / "gcw_dev.toml"
    assert _table(path, "train_gs") == {}
    budgets = _table(path, "budget")
    assert "train_gs" in budgets["cpu"]


def test_gcw_dev_trains_at_its_cpu_budget_unless_another_is_chosen(monkeypatch):
    monkeypatch.delenv("FACADE_BUDGET", raising=False)
    cpu = load_building_config("gcw_dev").section("train_gs", TrainParams)
    monkeypatch.setenv("FACADE_BUDGET", "gpu")
    gpu = load_building_config("gcw_dev").section("train_gs", TrainParams)
    default = load_building_config("demo").section("train_gs", TrainParams)
    assert (cpu.iterations, cpu.patch_px, cpu.max_view_pixels) == (300, 128, 49152)
    # without the CPU budget: default.toml's training, as every building without a budget of its own
    assert (gpu.iterations, gpu.patch_px, gpu.max_view_pixels) == (default.iterations, 0, 0)
    assert gpu.reflection == default.reflection and gpu.densify == default.densify
