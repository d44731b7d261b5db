"""data_layout.md and facade_pipeline/layout.py describe the same artefacts."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from facade_pipeline.layout import ENTRIES, STAGE_DIRS, BuildingLayout, resolve_data_root
from stages import PIPELINE

DOC = Path(__file__).resolve().parents[1] / "data_layout.md"


def _doc_tables() -> tuple[set[str], dict[str, str]]:
    patterns, stages = set(), {}
    section = None
    for line in DOC.read_text().splitlines():
        if line.startswith("## "):
            section = line[3:].strip()
        cells = re.findall(r"\|\s*`([^`]+)`\s*\|", line)
        if not line.startswith("| `"):
            continue
        if section == "Files":
            patterns.add(cells[0])
        elif section == "Stage folders":
            stages[cells[0]] = re.findall(r"`([^`]+)`", line)[1]
    return patterns, stages


def test_every_layout_entry_is_documented_and_back():
    documented, _ = _doc_tables()
    assert documented == set(ENTRIES.values())


def test_stage_folders_documented_in_order():
    _, stages = _doc_tables()
    assert stages == STAGE_DIRS
    assert list(STAGE_DIRS.values()) == sorted(STAGE_DIRS.values())  # numbered in pipeline order
    real = [s for s in PIPELINE if s != "synthesize"]
    assert real == list(STAGE_DIRS)[: len(real)]  # existing stages are a prefix of the design's order


def test_paths_are_built_under_the_building(tmp_path):
    layout = BuildingLayout(tmp_path, "b1")
    assert layout.raw_image("x.jpg") == tmp_path / "b1/raw/images/x.jpg"
    assert layout.manifest("import_photogrammetry") == tmp_path / "b1/01_import/manifest.json"
    assert layout.manifest("synthesize") == tmp_path / "b1/gt/manifest.json"
    assert layout.gt("normal_map", "uav_0001") == tmp_path / "b1/gt/normals/uav_0001.exr"
    assert layout.relative(layout.import_image("a/b")) == "01_import/images/a/b.png"


def test_data_root_resolution(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("FACADE_DATA_ROOT", raising=False)
    assert resolve_data_root() == tmp_path / "data"
    monkeypatch.setenv("FACADE_DATA_ROOT", str(tmp_path / "env"))
    assert resolve_data_root() == tmp_path / "env"
    assert resolve_data_root(tmp_path / "explicit") == tmp_path / "explicit"


@pytest.mark.parametrize("bad", ["", "../up", "a/b", "with space"])
def test_bad_building_names_rejected(tmp_path, bad):
    with pytest.raises(ValueError):
        BuildingLayout(tmp_path, bad)
