"""The stage contract, in one place: validate inputs, run, remove stale outputs, write the manifest last.

A run first deletes the stage's manifest and stray temporary files, so a crash, ``kill -9`` or Ctrl-C
at any point leaves no manifest: doit then reruns the stage and no downstream stage reads its outputs.
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import facade_pipeline
from facade_pipeline.config import load_building_config, to_dict
from facade_pipeline.errors import PipelineError
from facade_pipeline.io.atomic import remove_stale_temporaries, write_json
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import build_manifest, git_commit, sources_digest

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
    """Folders the stage owns: stale files there are removed after a successful run."""
    if stage.NAME == "synthesize":
        return [layout.raw_dir, layout.gt_dir]
    return [layout.stage_dir(stage.NAME)]


def load_params(stage: ModuleType, building: str) -> Any:
    return load_building_config(building).section(stage.NAME, stage.Params)


def execute(stage: ModuleType, layout: BuildingLayout, params: Any) -> dict[str, Any]:
    """Run ``stage`` under the contract and return its manifest."""
    manifest_path = layout.manifest(stage.NAME)
    manifest_path.unlink(missing_ok=True)
    folders = output_folders(stage, layout)
    for folder in folders:
        remove_stale_temporaries(folder)
    inputs = stage.inputs(layout, params)
    t0 = time.perf_counter()
    report: StageReport = stage.run(layout, params)
    wall = time.perf_counter() - t0
    outputs = {p.resolve() for p in report.outputs}
    for folder in folders:
        _remove_stale_outputs(folder, outputs | {manifest_path.resolve()})
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports kB
    code = {"git": git_commit(STAGES_DIR.parent), "sources_sha256": sources_digest(source_files(stage))}
    manifest = build_manifest(
        stage.NAME, layout, to_dict(params), inputs, sorted(outputs), report.metrics, code, wall, peak_mb
    )
    write_json(manifest_path, manifest)
    return manifest


def _remove_stale_outputs(folder: Path, keep: set[Path]) -> None:
    """Delete files under ``folder`` that this run did not write (left by an earlier configuration)."""
    if not folder.exists():
        return
    for p in sorted(folder.rglob("*"), reverse=True):
        if p.is_file() and p.resolve() not in keep:
            p.unlink()
        elif p.is_dir() and not any(p.iterdir()):
            p.rmdir()


def main(stage: ModuleType, argv: list[str] | None = None) -> int:
    """The CLI of every stage: ``python -m stages.<name> --building NAME [--data-root DIR]``."""
    parser = argparse.ArgumentParser(prog=f"python -m stages.{stage.NAME}", description=stage.DOC)
    parser.add_argument("--building", default="demo", help="building name (configs/buildings/<name>.toml)")
    parser.add_argument("--data-root", default=None, help="data root (default: $FACADE_DATA_ROOT or ./data)")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=os.environ.get("FACADE_LOG_LEVEL", "INFO"), format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        layout = BuildingLayout.for_building(args.building, args.data_root)
        params = load_params(stage, args.building)
        manifest = execute(stage, layout, params)
    except PipelineError as e:
        print(f"{stage.NAME}: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{stage.NAME}: interrupted; no manifest written, the stage will rerun", file=sys.stderr)
        return 130
    summary = ", ".join(f"{k}={v}" for k, v in manifest["metrics"].items() if not isinstance(v, dict | list))
    print(
        f"{stage.NAME}: {len(manifest['outputs'])} outputs in {manifest['wall_time_s']:.1f} s"
        + (f" ({summary})" if summary else "")
    )
    return 0
