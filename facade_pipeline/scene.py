"""``ImportedScene``: the typed hand-off written by ``import_photogrammetry`` and read by every later stage.

All geometry is in the local frame (z up, metres, near the origin); ``georef_from_local`` takes it back
to the coordinates of the user's photogrammetry.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.io.atomic import read_json, write_json
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest

Role = Literal["uav", "frontal"]


@dataclass(frozen=True)
class View:
    """One undistorted view: its name in the user's COLMAP model, its image in 01_import/, its camera."""

    name: str
    stem: str
    role: Role
    camera: PinholeCamera
    image: str  # relative to the building folder

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "stem": self.stem,
            "role": self.role,
            "image": self.image,
            "camera": self.camera.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> View:
        return cls(d["name"], d["stem"], d["role"], PinholeCamera.from_dict(d["camera"]), d["image"])


@dataclass(frozen=True)
class ImportedScene:
    views: tuple[View, ...]
    georef_from_local: np.ndarray  # [4, 4] float64
    up_axis_method: str
    points_source: str

    @property
    def uav_views(self) -> tuple[View, ...]:
        return tuple(v for v in self.views if v.role == "uav")

    @property
    def frontal_views(self) -> tuple[View, ...]:
        return tuple(v for v in self.views if v.role == "frontal")

    def save(self, path: str | Path) -> None:
        write_json(
            path,
            {
                "georef_from_local": self.georef_from_local.tolist(),
                "up_axis_method": self.up_axis_method,
                "points_source": self.points_source,
                "views": [v.to_dict() for v in self.views],
            },
        )

    @classmethod
    def load(cls, layout: BuildingLayout) -> ImportedScene:
        """Read the scene of a completed import (its manifest must exist)."""
        read_manifest(layout, "import_photogrammetry")
        path = layout.import_scene
        return read_json(path, "an imported scene (JSON) written by import_photogrammetry", lambda d: cls(
            tuple(View.from_dict(v) for v in d["views"]),
            np.array(d["georef_from_local"]),
            d["up_axis_method"],
            d["points_source"],
        ))  # fmt: skip
