"""The pipeline DAG for doit. Task creators only build metadata; every stage runs through its own CLI.

    doit                                   # the whole DAG for the default building (demo)
    doit train_gs building=shatin          # one stage and everything it needs
    doit list building=synthetic64         # the stages, in pipeline order
    doit -s import_photogrammetry building=shatin   # one stage alone, upstream not checked
    doit building=shatin data_root=/mnt/uav

Each stage task declares: the exact files it reads as ``file_dep`` (computed by a hidden ``_inputs:<stage>``
task through doit's ``calc_dep``, from raw/ and the upstream manifests, since they are only known once the
upstream stage ran), its own source files, its targets (the outputs known in advance and its manifest), and
``config_changed`` of its parameters. doit's state is kept per building in ``<building>/.doit.db``.
"""

from __future__ import annotations

import sys

from doit import get_var
from doit.exceptions import TaskFailed
from doit.tools import config_changed

from facade_pipeline.config import load_building_config, to_dict
from facade_pipeline.errors import PipelineError
from facade_pipeline.layout import BuildingLayout
from stages import PIPELINE, load_stage
from stages._runner import source_files

BUILDING = get_var("building", "demo")
DATA_ROOT = get_var("data_root", None)
LAYOUT = BuildingLayout.for_building(BUILDING, DATA_ROOT)
CONFIG = load_building_config(BUILDING)
SYNTHETIC = CONFIG.building.kind == "synthetic"
STAGES = [name for name in PIPELINE if SYNTHETIC or name != "synthesize"]

LAYOUT.root.mkdir(parents=True, exist_ok=True)
DOIT_CONFIG = {
    "dep_file": str(LAYOUT.doit_db),
    "backend": "sqlite3",
    "default_tasks": STAGES,
    "verbosity": 2,  # stages draw progress bars on stderr
    "sort": "definition",  # `doit list` in pipeline order
}


# stages whose inputs include a folder a person adds files to, so the list of files must be made anew each run
RESCANNED = ("import_photogrammetry", "evaluate")


def _inputs_action(stage, params):
    """calc_dep action: the files the stage will read, now that its upstream ran."""

    def compute():
        try:
            return {"file_dep": [str(p) for p in stage.inputs(LAYOUT, params)]}
        except PipelineError as e:
            return TaskFailed(f"{stage.NAME}: {e}")

    return compute


def _stage_tasks(name):
    stage = load_stage(name)
    params = CONFIG.section(name, stage.Params)
    command = [
        sys.executable,
        "-m",
        f"stages.{name}",
        "--building",
        BUILDING,
        "--data-root",
        str(LAYOUT.data_root),
    ]
    upstream = list(stage.UPSTREAM) + (
        ["synthesize"] if SYNTHETIC and name == "import_photogrammetry" else []
    )
    yield {
        "basename": f"_inputs:{name}",
        "doc": f"(hidden) list the files {name} reads",
        "actions": [_inputs_action(stage, params)],
        "file_dep": [str(LAYOUT.manifest(u)) for u in upstream],
        # folders a person adds files to are rescanned on every run (it costs milliseconds): raw/ (the
        # first stage) and variants/ (trained models that evaluate compares)
        "uptodate": [False] if name in RESCANNED else [],
        "verbosity": 0,
    }
    yield {
        "basename": name,
        "doc": stage.DOC,
        "actions": [command],
        "calc_dep": [f"_inputs:{name}"],
        "file_dep": [str(p) for p in source_files(stage)] + [str(LAYOUT.manifest(u)) for u in upstream],
        "targets": [str(p) for p in stage.targets(LAYOUT, params)] + [str(LAYOUT.manifest(name))],
        "uptodate": [config_changed(to_dict(params))],
        "clean": True,
    }


def task_pipeline():
    for name in STAGES:
        yield from _stage_tasks(name)
