"""The ground truth of a synthetic building (``gt/``, written by ``synthesize``) read into the pipeline's
local frame, for metrics only: no stage reads it to build its outputs.

gt/ is in the simulator's world frame, which is the georeferenced frame of ``raw/``; the pipeline works in
the local frame of ``01_import`` (``georef_from_local`` of ``01_import/scene.json``). Every reader of gt/
(the stages' truth metrics, ``evaluation``, ``segmentation.accuracy``, the benchmarks and tests) goes
through ``SyntheticTruth`` (or, given files rather than a building, ``read_truth_mesh`` and
``read_truth_panels``), so points, normals and cameras are moved the same way everywhere. Only the
formats' own tests (tests/synthetic) read gt/ as written.

This module imports the core (io, geometry, layout, scene) only, so any algorithm package may use it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.frames import invert_rigid, transform_points
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.io.colmap import pinhole_camera, read_reconstruction
from facade_pipeline.io.exr import read_exr
from facade_pipeline.io.images import read_mask
from facade_pipeline.io.meshes import read_mesh
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.scene import ImportedScene

TruthMesh = Literal["facade_mesh", "glass_mesh", "frame_mesh", "body_mesh"]
TruthMask = Literal["facade", "glass", "frame"]


def read_truth_mesh(path: str | Path, local_from_georef: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A true mesh of gt/ moved into the local frame: vertices [V, 3] float64 (m), triangles [F, 3]."""
    m = read_mesh(path)
    return transform_points(local_from_georef, np.asarray(m.vertices)), np.asarray(m.triangles)


def read_truth_panels(path: str | Path, local_from_georef: np.ndarray) -> list[dict]:
    """The entries of gt/panels.json with their ``corners`` ([4, 3] float64) moved into the local frame;
    the other keys (part, part_index, row, col, ...) as written."""
    try:
        panels = json.loads(Path(path).read_text())["panels"]
        for p in panels:
            p["corners"] = transform_points(local_from_georef, np.array(p["corners"], float).reshape(4, 3))
    except (OSError, ValueError, KeyError, TypeError) as e:
        expected = "gt panels {panels: [{corners: [4 x 3]}]}"
        raise InputError(path, expected, f"{type(e).__name__}: {e}") from None
    return panels


@dataclass(frozen=True, eq=False)
class SyntheticTruth:
    """gt/ of one synthetic building, read on demand and moved into the local frame by
    ``local_from_georef`` [4, 4] (the inverse of the imported scene's ``georef_from_local``)."""

    layout: BuildingLayout
    local_from_georef: np.ndarray

    @classmethod
    def load(cls, layout: BuildingLayout, georef_from_local: np.ndarray | None = None) -> SyntheticTruth:
        """The truth of ``layout``'s building; ``georef_from_local`` defaults to that of
        ``01_import/scene.json``. Raises ``InputError`` naming gt/ when the building has no truth."""
        if not layout.gt_dir.is_dir():
            raise InputError(layout.gt_dir, "the ground truth of a synthetic building (synthesize)", "none")
        if georef_from_local is None:
            georef_from_local = ImportedScene.load(layout).georef_from_local
        return cls(layout, invert_rigid(np.asarray(georef_from_local, np.float64)))

    @staticmethod
    def available(layout: BuildingLayout, *entries: str) -> bool:
        """Whether the building's gt/ has these files (``panels``, ``glass_mesh``, ...)."""
        return all(layout.gt(k).is_file() for k in entries)

    def mesh(self, key: TruthMesh) -> tuple[np.ndarray, np.ndarray]:
        """Vertices [V, 3] (local frame, m) and triangles [F, 3] of a true mesh."""
        return read_truth_mesh(self.layout.gt(key), self.local_from_georef)

    def raycaster(self, key: TruthMesh) -> MeshRaycaster:
        """A true mesh ready for distance queries and ray casting (local frame)."""
        return MeshRaycaster(*self.mesh(key))

    def panels(self) -> list[dict]:
        """gt/panels.json's panels, corners [4, 3] in the local frame (``read_truth_panels``)."""
        return read_truth_panels(self.layout.gt("panels"), self.local_from_georef)

    def panel_corners(self) -> np.ndarray:
        """The true panel corners [P, 4, 3] (local frame, m), in gt/panels.json's order."""
        return np.array([p["corners"] for p in self.panels()], np.float64).reshape(-1, 4, 3)

    def scene_parts(self) -> list[dict]:
        """The facade parts of gt/scene.json with their placement in the local frame: ``world_from_facade``
        (then local from facade), and a cylinder's ``axis_point`` and ``axis_direction``."""
        T = self.local_from_georef
        parts = json.loads(self.layout.gt("scene").read_text())["parts"]
        for part in parts:
            part["world_from_facade"] = (T @ np.asarray(part["world_from_facade"], np.float64)).tolist()
            if "axis_point" in part:
                part["axis_point"] = transform_points(T, np.asarray(part["axis_point"], np.float64)[None])[0]
                part["axis_direction"] = T[:3, :3] @ np.asarray(part["axis_direction"], np.float64)
        return parts

    def normal_map(self, stem: str) -> tuple[np.ndarray, np.ndarray]:
        """View ``stem``'s true normals [H, W, 3] float64 (local frame: turned with the frame) and where
        they are valid [H, W] bool."""
        n = read_exr(self.layout.gt("normal_map", stem))
        return n["N"] @ self.local_from_georef[:3, :3].T, n["valid"] > 0.5

    def mask(self, kind: TruthMask, stem: str) -> np.ndarray:
        """View ``stem``'s true ``kind`` pixels [H, W] bool (images have no frame)."""
        return read_mask(self.layout.gt(f"{kind}_mask", stem))

    def frontal_camera(self, stem: str) -> PinholeCamera:
        """The true camera of frontal view ``stem`` (gt/frontal/sparse/0, without pose noise), local frame."""
        rec = read_reconstruction(self.layout.gt("frontal_sparse_dir"))
        im = next((i for i in rec.images.values() if i.name.rsplit(".", 1)[0] == stem), None)
        if im is None:
            raise InputError(self.layout.gt("frontal_sparse_dir"), f"an image named {stem}.*", "none")
        world = pinhole_camera(rec.cameras[im.camera_id], im.cam_from_world())
        cam_from_local = world.cam_from_world @ invert_rigid(self.local_from_georef)
        return PinholeCamera(world.K, cam_from_local, world.width, world.height)
