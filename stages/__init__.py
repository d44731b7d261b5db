"""Pipeline stages, one module each. A stage module exposes:

- ``NAME``, ``DOC`` (one line), ``Params`` (a frozen dataclass, read from the config section ``NAME``);
- ``UPSTREAM``: the stages whose outputs it reads (its code version is derived from its imports);
- ``inputs(layout, params)``: the exact files it reads, validated (missing ones raise ``InputError``);
- ``targets(layout, params)``: the outputs whose names are known before it runs;
- ``run(layout, params, settings) -> StageReport``: does the work, writing every output atomically;
  ``settings`` is the ``[run]`` table (``config.RunSettings``: device, logging, checkpoints, overlay
  size), which no ``Params`` holds, so that changing one reruns nothing;
- optionally ``EDITABLE``: layout entries of its outputs that a person may edit (not taken for damage);
- a CLI: ``python -m stages <name> --building NAME`` (or ``python -m stages.<name>``).

doit imports every stage module to build its task list (``doit list`` too), so what a module holds at its
top (the names above, ``Params`` from a light ``params`` module of the library) imports no heavy library
(torch, open3d, pycolmap, OpenCV): ``run``, its helpers and ``inputs`` import the algorithms where they
use them. The stage's code version (``_runner.source_files``) follows those imports too.

``stages._runner.execute`` wraps ``run`` with the contract (manifest last, stale files removed) and is
the one way a stage runs, from doit or from the command line.
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: The DAG in pipeline order. A stage is listed here only once it really exists.
PIPELINE: tuple[str, ...] = (
    "synthesize",
    "import_photogrammetry",
    "rectify",
    "segment_panels",
    "regularize_corners",
    "correct_mesh",
    "bake_normals",
    "train_gs",
    "evaluate",
)


def load_stage(name: str) -> ModuleType:
    if name not in PIPELINE:
        raise KeyError(f"unknown stage {name!r}; stages: {', '.join(PIPELINE)}")
    return importlib.import_module(f"stages.{name}")
