"""The stage contract, in one place: validate inputs, run, remove stale outputs, write the manifest last.

A run first deletes the stage's manifest and stray temporary files, so a crash, ``kill -9`` or Ctrl-C
at any point leaves no manifest: doit then reruns the stage and no downstream stage reads its outputs.
A stage whose result a person reads directly (``REMOVE_TARGETS_FIRST``: evaluate's report) loses those
files even before its manifest. The outputs a rerun deletes are exactly those its last manifest listed.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import facade_pipeline
from facade_pipeline.config import RunSettings, default_run_settings, load_building_config, to_dict
from facade_pipeline.errors import InputError, PipelineError
from facade_pipeline.io.atomic import remove_stale_temporaries, write_json
from facade_pipeline.io.lock import acquire, release
from facade_pipeline.layout import DATA_ROOT_ENV, BuildingLayout
from facade_pipeline.manifest import build_manifest, git_commit, read_manifest, sources_digest
from facade_pipeline.threads import policy_in_place, thread_policy

PACKAGE_DIR = Path(facade_pipeline.__file__).resolve().parent
STAGES_DIR = Path(__file__).resolve().parent
log = logging.getLogger("facade_pipeline.stages")


@dataclass
class StageReport:
    """What ``run`` returns: every file it wrote and the metrics for the manifest."""

    outputs: list[Path]
    metrics: dict[str, Any] = field(default_factory=dict)


def source_files(stage: ModuleType) -> list[Path]:
    """The stage's code version: its own module, this runner, and every ``facade_pipeline`` module they
    import, followed transitively (plus the C/C++ sources in a ``csrc/`` folder beside an imported module).
    Derived from the imports, so editing a module that a stage does not use never reruns it."""
    todo = [Path(stage.__file__).resolve(), Path(__file__).resolve()]
    seen: set[Path] = set()
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        csrc = path.parent / "csrc"
        if csrc.is_dir():
            seen.update(
                q.resolve() for q in csrc.rglob("*") if q.suffix in (".c", ".cc", ".cpp", ".h", ".hpp")
            )
        todo += _imported_package_files(path)
    return sorted(seen)


def _imported_package_files(path: Path) -> list[Path]:
    """Files of ``facade_pipeline`` (and its package ``__init__``s) that the module at ``path`` imports."""
    import ast

    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import inside the package
                pkg = path.parent.relative_to(PACKAGE_DIR.parent).parts[
                    : len(path.parent.relative_to(PACKAGE_DIR.parent).parts) - node.level + 1
                ]
                base = ".".join((*pkg, base)) if base else ".".join(pkg)
            names += [base] + [f"{base}.{a.name}" for a in node.names]
    files = []
    for name in names:
        parts = name.split(".")
        if parts[0] != PACKAGE_DIR.name:
            continue
        for i in range(1, len(parts) + 1):
            stem = PACKAGE_DIR.parent.joinpath(*parts[:i])
            for candidate in (stem.with_suffix(".py"), stem / "__init__.py"):
                if candidate.is_file():
                    files.append(candidate.resolve())
    return files


def output_folders(stage: ModuleType, layout: BuildingLayout) -> list[Path]:
    """Folders the stage writes into (they may hold a person's own files too, which are left alone)."""
    if stage.NAME == "synthesize":
        return [layout.raw_dir, layout.gt_dir]
    return [layout.stage_dir(stage.NAME)]


def load_params(stage: ModuleType, building: str) -> Any:
    return load_building_config(building).section(stage.NAME, stage.Params)


def load_settings(building: str) -> RunSettings:
    return load_building_config(building).run


def execute(
    stage: ModuleType, layout: BuildingLayout, params: Any, settings: RunSettings | None = None
) -> dict[str, Any]:
    """Run ``stage`` under the contract and return its manifest. ``settings``: the ``[run]`` table (how it
    runs; default.toml's when None), kept out of the manifest's parameters as out of doit's."""
    settings = settings or default_run_settings()
    folders = output_folders(stage, layout)
    for folder in folders:
        _check_reachable(folder)
    if getattr(stage, "REMOVE_TARGETS_FIRST", False):
        for path in stage.targets(layout, params):
            path.unlink(missing_ok=True)
    manifest_path = layout.manifest(stage.NAME)
    record = layout.previous_outputs(stage.NAME)
    previous = _previous_outputs(layout, stage.NAME)
    if previous:
        # the list outlives the manifest deleted next, so a run interrupted before it completes still
        # knows what the last completed run wrote
        write_json(record, {"stage": stage.NAME, "outputs": sorted(previous)})
    manifest_path.unlink(missing_ok=True)
    for folder in folders:
        remove_stale_temporaries(folder)
    inputs = stage.inputs(layout, params)
    t0 = time.perf_counter()
    report: StageReport = stage.run(layout, params, settings)
    wall = time.perf_counter() - t0
    outputs = {layout.relative(p) for p in report.outputs}
    _remove_stale_outputs(layout, folders, previous - outputs)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports kB
    code = {"git": git_commit(STAGES_DIR.parent), "sources_sha256": sources_digest(source_files(stage))}
    manifest = build_manifest(
        stage.NAME,
        layout,
        to_dict(params),
        inputs,
        [layout.root / rel for rel in sorted(outputs)],
        report.metrics,
        code,
        wall,
        peak_mb,
    )
    write_json(manifest_path, manifest)
    record.unlink(missing_ok=True)
    return manifest


def _check_reachable(folder: Path) -> None:
    """A stage folder that is a symlink to a folder that is not there (a disk that is not mounted) stops
    the stage before any work, rather than at its first write, maybe hours later."""
    if folder.is_symlink() and not folder.exists():
        raise InputError(
            folder,
            "a stage folder, or a symlink to a folder that exists",
            f"a symlink to {os.readlink(folder)}, which does not exist (a disk that is not mounted?): "
            "mount it, or delete the symlink to write here",
        )


def _previous_outputs(layout: BuildingLayout, stage: str) -> set[str]:
    """What the last completed run listed as its outputs: its manifest's list, and the list a rerun that
    was interrupted kept of it. None when neither is readable (nothing is deleted then)."""
    listed: set[str] = set()
    try:
        listed |= set(read_manifest(layout, stage).outputs)
    except PipelineError:
        pass
    try:
        kept = json.loads(layout.previous_outputs(stage).read_text())["outputs"]
        listed |= {rel for rel in kept if isinstance(rel, str)}
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return listed


def _remove_stale_outputs(layout: BuildingLayout, folders: list[Path], stale: set[str]) -> None:
    """Delete the files an earlier run of this stage listed and this one did not write (left by another
    configuration). Nothing else in its folders is touched (a person's notes, a copy they made of an
    output, a folder that is a symlink to another disk), and a listed path outside them (a hand-edited
    manifest) is ignored."""
    inside = [layout.relative(f) + "/" for f in folders]
    for rel in sorted(stale, reverse=True):
        normal = os.path.normpath(rel)
        if normal != rel or not rel.startswith(tuple(inside)):
            continue
        path = layout.root / rel
        if not path.is_file() and not path.is_symlink():
            continue
        path.unlink()
        # folders the stage made and left empty go too; the stage's own folder stays (it may be a symlink)
        parent = path.parent
        while parent not in folders and parent != layout.root and not any(parent.iterdir()):
            parent.rmdir()
            parent = parent.parent


def main(stage: ModuleType, argv: list[str] | None = None) -> int:
    """The CLI of every stage: ``python -m stages <name> --building NAME [--data-root DIR]`` (also reached as
    ``python -m stages.<name>``, which starts again through ``python -m stages`` to set the thread policy
    before any numerical library loads)."""
    if argv is None and not policy_in_place():
        env = {**os.environ, **thread_policy(os.environ)}
        os.execve(sys.executable, [sys.executable, "-m", "stages", stage.NAME, *sys.argv[1:]], env)
    parser = argparse.ArgumentParser(prog=f"python -m stages {stage.NAME}", description=stage.DOC)
    parser.add_argument("--building", default="demo", help="building name (configs/buildings/<name>.toml)")
    parser.add_argument("--data-root", default=None, help="data root (default: $FACADE_DATA_ROOT or ./data)")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=os.environ.get("FACADE_LOG_LEVEL", "INFO"), format="%(levelname)s %(name)s: %(message)s"
    )
    lock = None
    try:
        layout = BuildingLayout.for_building(args.building, args.data_root)
        # what the stage looks up beside the buildings (the LPIPS weights' cache) is in this data root too
        os.environ[DATA_ROOT_ENV] = str(layout.data_root)
        params = load_params(stage, args.building)
        settings = load_settings(args.building)
        lock = acquire(layout.lock) if layout.root.is_dir() else None
        manifest = execute(stage, layout, params, settings)
    except PipelineError as e:
        print(f"{stage.NAME}: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        # the machine, not the data: a full disk, a read-only folder, a vanished mount
        print(
            f"{stage.NAME}: {_os_error_line(e)}; no manifest written, the stage will rerun", file=sys.stderr
        )
        return 2
    except KeyboardInterrupt:
        print(f"{stage.NAME}: interrupted; no manifest written, the stage will rerun", file=sys.stderr)
        return 130
    finally:
        release(lock)
    summary = ", ".join(f"{k}={v}" for k, v in manifest["metrics"].items() if not isinstance(v, dict | list))
    print(
        f"{stage.NAME}: {len(manifest['outputs'])} outputs in {manifest['wall_time_s']:.1f} s"
        + (f" ({summary})" if summary else "")
    )
    return 0


def _os_error_line(e: OSError) -> str:
    """One line for an ``OSError``: the file, what went wrong and, for writes, the free space there."""
    where = e.filename or (str(e).split(":", 1)[0] if str(e).startswith("/") else None)
    what = e.strerror or str(e)
    line = f"{where}: {what}" if where and where not in what else what
    if where:
        folder = Path(where).parent
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        try:
            free = shutil.disk_usage(folder).free / 2**20
            writable = os.access(folder, os.W_OK)
            line += f" ({free:.0f} MiB free in {folder}{'' if writable else ', not writable'})"
        except OSError:
            pass
    return line
