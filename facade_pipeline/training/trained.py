"""The ``train_gs`` hand-off: where a trained model lies and what produced it (``TrainedModelFiles``).

A trained model is three files in the ``train_gs`` formats: the Gaussians (3DGS-style PLY with reflectivity
and F0), the reflection module's record (``shading.reflection.reflection_record``) and the train/test split
(view stems, and the training views' exposure gains when training estimated or learnt them); plus the
``train_gs`` parameters it was trained with (``to_dict`` form). The pipeline's model is ``07_train/``, whose
parameters its manifest records; more models (a baseline, an ablation) may be saved under
``variants/<name>/`` with a ``params.json`` beside them and are evaluated beside it. ``save`` is the one
writer of these files and ``TrainedModelFiles`` the one way to find them; rendering them is
``evaluation.render_views.load_trained``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from torch import nn

from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import write_json
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.shading.reflection import ReflectionModel, reflection_record
from facade_pipeline.training.checkpoints import save_torch
from facade_pipeline.training.model import GaussianModel
from facade_pipeline.training.ply import write_ply

#: the files of a saved variant, in the order of ``TrainedModelFiles``' fields
VARIANT_FILES = ("gaussians.ply", "reflection.pt", "split.json", "params.json")
#: the name the pipeline's own model (07_train) goes by in the evaluation
PIPELINE_MODEL = "07_train"


@dataclass(frozen=True)
class TrainedModelFiles:
    """Where a trained model lies and the ``train_gs`` parameters (plain dict) it was trained with.
    ``params_file`` is where the parameters are saved beside the model (None: the manifest holds them)."""

    name: str
    ply: Path
    reflection: Path
    split: Path
    params: dict[str, Any]
    params_file: Path | None = None

    @property
    def files(self) -> list[Path]:
        """The files the model is read from (what a stage that reads it depends on)."""
        return [self.ply, self.reflection, self.split]

    @classmethod
    def pipeline(cls, layout: BuildingLayout, params: dict[str, Any] | None = None) -> TrainedModelFiles:
        """``07_train/`` of ``layout``, with ``params`` (None: those its ``train_gs`` manifest records)."""
        params = read_manifest(layout, "train_gs").params if params is None else params
        paths = (layout.path(k) for k in ("train_ply", "train_reflection", "train_split"))
        return cls(PIPELINE_MODEL, *paths, params)

    @classmethod
    def variant(cls, folder: Path, params: dict[str, Any], name: str | None = None) -> TrainedModelFiles:
        """A variant to be saved in ``folder`` (its parameters go to ``params.json`` there)."""
        ply, refl, split, pfile = (folder / f for f in VARIANT_FILES)
        return cls(name or folder.name, ply, refl, split, params, pfile)

    @classmethod
    def from_dir(cls, folder: Path, name: str | None = None) -> TrainedModelFiles:
        """A variant saved in ``folder`` (its ``params.json`` holds the parameters)."""
        files = [folder / f for f in VARIANT_FILES]
        for f in files:
            if not f.is_file():
                raise InputError(f, "a file of a saved trained variant", "no file")
        try:
            params = json.loads(files[3].read_text())
        except ValueError as e:
            raise InputError(files[3], "train_gs parameters as JSON", str(e)) from None
        return cls.variant(folder, params, name)

    def split_stems(self) -> dict[str, list[str]]:
        """``{"train": [...], "test": [...]}``: the view stems of the split it was trained on."""
        try:
            d = json.loads(self.split.read_text())
            return {"train": list(d["train"]), "test": list(d["test"])}
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputError(
                self.split, "a JSON split {train: [...], test: [...]}", f"{type(e).__name__}: {e}"
            ) from None

    def save(
        self,
        model: GaussianModel,
        reflection: nn.Module | None,
        strategy: ReflectionModel,
        bounds: tuple[np.ndarray, np.ndarray],
        split: dict[str, Any],
    ) -> list[Path]:
        """Write the model in the ``train_gs`` formats, each file atomically: the PLY, the reflection
        record (facade ``bounds`` [lo, hi] in m), ``split`` (``train``/``test`` stems, optionally
        ``exposure_gain``) and, for a variant, the parameters. Returns the files written."""
        self.ply.parent.mkdir(parents=True, exist_ok=True)
        write_ply(self.ply, model)
        save_torch(self.reflection, reflection_record(strategy, bounds, reflection))
        write_json(self.split, split)
        written = [self.ply, self.reflection, self.split]
        if self.params_file is not None:
            write_json(self.params_file, self.params)
            written.append(self.params_file)
        return written
