"""Checkpoints: what a trainer's checkpoint holds (``TrainState``, everything a step changes), writing it
atomically (``save_checkpoint``, ``save_torch``) and reading it back (``read_checkpoint``) with the reasons
one is not resumed.

A checkpoint holds everything needed to continue exactly (the model, the optimisers' moments, the one
random generator), the fingerprint of the parameters, inputs and code it was made with, and the parameters
themselves so that a refused checkpoint can say what changed. The file format lives here apart from the
loop so that the loop reads as steps; rebuilding a ``Trainer`` from a state read here is
``trainer.load_checkpoint``.
"""

from __future__ import annotations

import io
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from facade_pipeline.config import to_dict
from facade_pipeline.io.atomic import write_bytes
from facade_pipeline.training.corrections import ViewCorrections
from facade_pipeline.training.densify import DensifyStats
from facade_pipeline.training.model import GaussianModel
from facade_pipeline.training.params import TrainParams

log = logging.getLogger(__name__)
CHECKPOINT_FORMAT = 2


@dataclass
class TrainState:
    """Everything a training step changes, and so everything a checkpoint holds: the splats, the reflection
    module, the per-view pose corrections, their optimisers, the one random generator, the densification
    statistics, the iteration and the training log."""

    model: GaussianModel
    reflection: nn.Module | None
    """the specular term's module (None: no specular term)"""
    corrections: ViewCorrections | None
    """per-view pose corrections (``pose_refinement``), else None"""
    opt: torch.optim.Adam
    opt_refl: torch.optim.Adam | None
    opt_corrections: torch.optim.Adam | None
    generator: torch.Generator
    """every random draw of training (view order, patches, pixel subsets, densification)"""
    stats: DensifyStats
    iteration: int = 0
    log: list[dict[str, Any]] = field(default_factory=list)


def save_checkpoint(state: TrainState, params: TrainParams, path: str | Path, fingerprint: str) -> None:
    """Everything needed to continue exactly, written atomically."""
    s = state
    saved = {
        "format": CHECKPOINT_FORMAT,
        "fingerprint": fingerprint,
        "params": to_dict(params),  # to tell, when it does not match, what changed
        "iteration": s.iteration,
        "model": s.model.state(),
        "opt": s.opt.state_dict(),
        "reflection": None if s.reflection is None else s.reflection.state_dict(),
        "opt_refl": None if s.opt_refl is None else s.opt_refl.state_dict(),
        "corrections": None if s.corrections is None else s.corrections.state_dict(),
        "opt_corrections": None if s.opt_corrections is None else s.opt_corrections.state_dict(),
        "generator": s.generator.get_state(),
        "stats": {"grad_accum": s.stats.grad_accum, "count": s.stats.count},
        "log": s.log,
    }
    save_torch(path, saved)


def save_torch(path: str | Path, obj: Any) -> None:
    """``torch.save`` atomically and reproducibly (through memory: torch names the archive after the file,
    and the temporary name is random)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    write_bytes(path, buf.getvalue())


def read_checkpoint(path: str | Path, p: TrainParams, fingerprint: str) -> dict[str, Any] | None:
    """The state saved at ``path`` (on the CPU), or None when there is none or it belongs to other
    parameters or inputs (its fingerprint differs) or an older format, which the log says (naming the
    parameters that changed when the checkpoint records them). A damaged file is moved aside to
    ``<name>.bad`` (kept for a person to look at) and training starts afresh."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise TypeError(f"a {type(state).__name__}, not a dict")
    except Exception as e:  # torch raises several types for truncated or foreign files
        bad = path.with_name(path.name + ".bad")
        os.replace(path, bad)
        log.warning(
            "%s: unreadable checkpoint (%s: %s), moved to %s; training starts from iteration 0",
            path, type(e).__name__, str(e).splitlines()[0] if str(e) else "", bad.name,
        )  # fmt: skip
        return None
    if state.get("format") != CHECKPOINT_FORMAT or state.get("fingerprint") != fingerprint:
        log.warning(
            "%s: checkpoint of iteration %s not resumed: %s; training starts from iteration 0",
            path, state.get("iteration", "?"), _mismatch(state, p),
        )  # fmt: skip
        return None
    log.info("%s: resuming from the checkpoint of iteration %s", path, state["iteration"])
    return state


def _mismatch(state: dict[str, Any], p: TrainParams) -> str:
    """Why a checkpoint's fingerprint differs, as far as it records: its format, the parameters that
    changed (dotted [train_gs] keys, old -> new, the first few), or else the inputs or the code."""
    if state.get("format") != CHECKPOINT_FORMAT:
        return f"it has format {state.get('format')!r}, this version reads {CHECKPOINT_FORMAT}"
    saved = state.get("params")
    if not isinstance(saved, dict):
        return "it was made with other parameters, inputs or code"
    old, new = _dotted(saved), _dotted(to_dict(p))
    keys = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    changed = [f"{k} {old.get(k, '(none)')!r} -> {new.get(k, '(none)')!r}" for k in keys]
    if not changed:
        return "same parameters, other inputs or code (an upstream output or facade_pipeline changed)"
    more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
    return "other parameters: " + ", ".join(changed[:3]) + more


def _dotted(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in table.items():
        if isinstance(value, dict):
            out |= _dotted(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out
