"""The per-view loops of rectify, segment_panels and bake_normals, and evaluate's renders, fanned out over
processes or a Dask cluster, write byte for byte what the serial loop writes."""

from __future__ import annotations

import dataclasses
import os

import pytest
import torch

from facade_pipeline.batch.fanout import SCHEDULER_ENV, map_views, shared
from facade_pipeline.config import load_building_config
from facade_pipeline.layout import BuildingLayout
from stages import _runner, load_stage

FANNED = ("rectify", "segment_panels", "bake_normals", "evaluate")
#: short enough for a test: a few training steps, a short fly-through, a short alignment of each view
SHORT = {
    "train_gs": {"iterations": 20},
    "evaluate": {"lpips_conventions": ("vgg_3dgs",)},
    "evaluate.video": {"frames": 4},
    "evaluate.align": {"steps": 8},
}


def _square(x: int) -> int:
    return x * x


def test_map_views_keeps_the_order_and_reports_each_view(tmp_path):
    seen = []
    assert map_views(_square, range(7), workers=1, done=seen.append) == [x * x for x in range(7)]
    assert seen == [x * x for x in range(7)]
    seen.clear()
    assert map_views(_square, range(7), workers=3, done=seen.append) == [x * x for x in range(7)]
    assert seen == [x * x for x in range(7)]


def _pid(_) -> int:
    return os.getpid()


def test_views_kept_in_the_stage_process_go_neither_to_processes_nor_to_a_cluster(monkeypatch):
    monkeypatch.setenv(SCHEDULER_ENV, "tcp://127.0.0.1:9")  # nothing listens there: a call would fail
    assert map_views(_pid, range(4), workers=2, spread=False) == [os.getpid()] * 4


def test_shared_loads_once_until_the_file_changes(tmp_path):
    f = tmp_path / "a.txt"
    f.write_text("one")
    calls = []

    def load(path):
        calls.append(path)
        return path.read_text()

    assert shared(load, f) == "one" and shared(load, f) == "one" and len(calls) == 1
    f.write_text("three")  # another size
    assert shared(load, f) == "three" and len(calls) == 2


def _execute(name, layout, **run):
    cfg = load_building_config(layout.building)
    stage = load_stage(name)
    params = cfg.section(name, stage.Params)
    for key, value in SHORT.get(f"{name}.video", {}).items():
        params = dataclasses.replace(params, video=dataclasses.replace(params.video, **{key: value}))
    for key, value in SHORT.get(f"{name}.align", {}).items():
        params = dataclasses.replace(params, align=dataclasses.replace(params.align, **{key: value}))
    params = dataclasses.replace(params, **SHORT.get(name, {}))
    settings = dataclasses.replace(cfg.run, **run)
    return _runner.execute(stage, layout, params, settings)["outputs"]


@pytest.mark.slow
def test_fanned_out_views_are_byte_identical_to_the_serial_loop(tmp_path, monkeypatch):
    """Also where the workers' own thread count differs from the stage's (a Dask worker runs one OpenMP
    thread by default; the stage here runs two): evaluate's renders run on the stage's count."""
    from distributed import LocalCluster

    layout = BuildingLayout(tmp_path / "data", "synthetic64")
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        serial = {}
        for name in ("synthesize", "import_photogrammetry", *FANNED[:2], "regularize_corners", "correct_mesh",
                     FANNED[2], "train_gs", FANNED[3]):
            outputs = _execute(name, layout)
            if name in FANNED:
                serial[name] = outputs
        assert sum("08_evaluate/renders" in f for f in serial["evaluate"]) > 0
        for name in FANNED:
            assert _execute(name, layout, view_workers=2) == serial[name], name
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
            monkeypatch.setenv(SCHEDULER_ENV, c.scheduler_address)
            for name in FANNED:
                assert _execute(name, layout) == serial[name], name
    finally:
        torch.set_num_threads(threads)
