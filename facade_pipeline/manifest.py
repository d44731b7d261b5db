"""Stage manifests: the record a stage writes last, after all its outputs.

A manifest lists the parameters, every input and output with its SHA-256, the code version, wall time,
peak memory and the stage's metrics. Its presence is what makes a stage's outputs trustworthy: a stage
deletes its old manifest before it starts, so an interrupted run leaves none.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from facade_pipeline import __version__
from facade_pipeline.errors import InputError, UpstreamMissingError
from facade_pipeline.layout import BuildingLayout, entry_regex

MANIFEST_VERSION = 1


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def sources_digest(files: list[Path]) -> str:
    """One SHA-256 over the given source files (names and contents), the stage's code version."""
    h = hashlib.sha256()
    for f in sorted(files):
        h.update(f.as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def git_commit(repo: Path) -> str | None:
    """The checkout's commit, with ``-dirty`` when it has local changes; None outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "-C", str(repo), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        )
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


@dataclass(frozen=True)
class Manifest:
    """A stage's manifest as read back from disk. Paths are relative to the building folder."""

    stage: str
    path: Path
    params: dict[str, Any]
    inputs: dict[str, str]
    outputs: dict[str, str]
    metrics: dict[str, Any]
    data: dict[str, Any]

    def output_paths(self, layout: BuildingLayout) -> list[Path]:
        return [layout.root / rel for rel in self.outputs]


def build_manifest(
    stage: str,
    layout: BuildingLayout,
    params: dict[str, Any],
    inputs: list[Path],
    outputs: list[Path],
    metrics: dict[str, Any],
    code: dict[str, Any],
    wall_time_s: float,
    peak_memory_mb: float,
) -> dict[str, Any]:
    """The manifest dict, hashing every input and output file. A metric that is not a finite number (it
    could not be computed: no pixels, no panels) is recorded as null, with the reason in
    ``undefined_metrics``; JSON has no NaN, and a reader must not mistake it for a value."""
    metrics, undefined = finite_or_null(metrics)
    return {
        "manifest_version": MANIFEST_VERSION,
        "stage": stage,
        "building": layout.building,
        "params": params,
        "inputs": {layout.relative(p): sha256_file(p) for p in sorted(set(inputs))},
        "outputs": {layout.relative(p): sha256_file(p) for p in sorted(set(outputs))},
        "output_stats": {layout.relative(p): _stat(p) for p in sorted(set(outputs))},
        "code": {"package_version": __version__, "python": platform.python_version(), **code},
        "wall_time_s": round(wall_time_s, 3),
        "peak_memory_mb": round(peak_memory_mb, 1),
        "metrics": metrics,
        "undefined_metrics": undefined,
    }


def finite_or_null(value: Any, where: str = "") -> tuple[Any, dict[str, str]]:
    """``value`` with every NaN or infinite number replaced by None, and {dotted path: reason} of those."""
    if isinstance(value, dict):
        out, undefined = {}, {}
        for k, v in value.items():
            out[k], u = finite_or_null(v, f"{where}.{k}" if where else str(k))
            undefined.update(u)
        return out, undefined
    if isinstance(value, list | tuple):
        out_list, undefined = [], {}
        for i, v in enumerate(value):
            x, u = finite_or_null(v, f"{where}[{i}]")
            out_list.append(x)
            undefined.update(u)
        return out_list, undefined
    if isinstance(value, float) and not math.isfinite(value):
        return None, {where: f"not computable ({value}): no samples it could be measured on"}
    return value, {}


def _stat(path: Path) -> dict[str, int]:
    st = os.stat(path)
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}


def damaged_outputs(
    layout: BuildingLayout, stage: str, full_hash: bool = False, editable: tuple[str, ...] = ()
) -> list[str]:
    """Outputs of ``stage``'s manifest that are missing or no longer what the stage wrote: a file whose
    size or modification time differs from the record is hashed (``full_hash``: every file is), and it
    counts if its hash differs. Files of the layout entries in ``editable`` (a mask a person may fix by
    hand) only count when they are missing. A manifest that exists but cannot be read is itself damaged
    (its path is returned); a missing one means the stage has not completed: nothing to report."""
    try:
        m = read_manifest(layout, stage)
    except UpstreamMissingError:
        return []
    except InputError:
        return [layout.relative(layout.manifest(stage))]
    stats = m.data.get("output_stats")
    stats = stats if isinstance(stats, dict) else {}
    skip = [entry_regex(k) for k in editable]
    bad = []
    for rel, digest in m.outputs.items():
        path = layout.root / rel
        if any(r.match(rel) for r in skip) and path.is_file():
            continue
        try:
            now = _stat(path)
        except OSError:
            bad.append(rel)
            continue
        recorded = stats.get(rel)
        if full_hash or now != recorded:
            size = recorded.get("size", now["size"]) if isinstance(recorded, dict) else now["size"]
            if now["size"] != size or sha256_file(path) != digest:
                bad.append(rel)
    return bad


def rerun_reason(
    layout: BuildingLayout, stage: str, full_hash: bool = False, editable: tuple[str, ...] = ()
) -> str | None:
    """Why ``stage`` must run again although doit's record says it is up to date, in one line (its
    manifest is damaged, or outputs changed since it wrote them); None when nothing is wrong."""
    bad = damaged_outputs(layout, stage, full_hash, editable)
    if not bad:
        return None
    manifest = layout.manifest(stage)
    if bad == [layout.relative(manifest)]:
        try:
            read_manifest(layout, stage)
        except InputError as e:
            return f"{stage}: {e}; running the stage again to rewrite it"
    more = f" and {len(bad) - 1} more output(s)" if len(bad) > 1 else ""
    return f"{stage}: {layout.root / bad[0]}{more} missing or changed since its manifest; running it again"


def read_manifest(layout: BuildingLayout, stage: str) -> Manifest:
    """Read ``stage``'s manifest; a missing one means the stage has not completed, one that does not parse
    or lacks its tables (``InputError``) cannot be trusted."""
    path = layout.manifest(stage)
    if not path.is_file():
        raise UpstreamMissingError(
            path, f"the manifest of a completed '{stage}' stage (run `doit {stage}`)", "no manifest"
        )
    expected = f"a '{stage}' stage manifest (JSON with params, inputs, outputs, metrics)"
    try:
        data = json.loads(path.read_text())
        m = Manifest(stage, path, data["params"], data["inputs"], data["outputs"], data["metrics"], data)
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise InputError(path, expected, f"{type(e).__name__}: {e}") from None
    tables = {"params": m.params, "inputs": m.inputs, "outputs": m.outputs, "metrics": m.metrics}
    wrong = [k for k, v in tables.items() if not isinstance(v, dict)]
    wrong += [k for k in ("inputs", "outputs") if k not in wrong and not all(
        isinstance(a, str) and isinstance(b, str) for a, b in tables[k].items())]  # fmt: skip
    if data.get("stage", stage) != stage:
        wrong.append(f"stage {data.get('stage')!r}")
    if wrong:
        raise InputError(path, expected, f"a damaged manifest ({', '.join(wrong)})")
    return m
