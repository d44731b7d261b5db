"""Do the cameras and the coarse mesh describe one scene? Checked once, at import, where a wrong frame or unit
first shows; downstream it only shows as empty masks and NaN losses.

Three signs, each cheap: the mesh's size against the camera layout (a mesh in millimetres is ~1000x too
big), how many views' rays meet the mesh at all (a model in another world frame, a mesh far away), and the
same for the frontal views separately (a frontal model registered in its own frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster

#: rays per view on a regular grid (columns, rows): enough to find a facade covering a few % of the image
GRID = (16, 12)


@dataclass(frozen=True)
class SceneCheck:
    """What the checks measured."""

    size_ratio: float
    """the mesh's bounding-box diagonal over the cameras' scale (their spread, or their distance to the
    mesh where that is larger): about 0.1-10 for a survey of a building"""
    seeing: dict[str, float]
    """per view stem: the share of its grid rays that meet the mesh"""

    def share_seeing(self, stems: list[str]) -> float:
        """The share of the views ``stems`` with at least one ray on the mesh."""
        return float(np.mean([self.seeing[s] > 0 for s in stems])) if stems else 1.0


def camera_scale(centres: np.ndarray, mesh_vertices: np.ndarray) -> float:
    """The length the camera layout spans: the centres' bounding-box diagonal, or with a single camera its
    distance to the mesh's bounding-box centre (in the model's units). A survey of a building spreads its
    cameras over about the building's size; the distance alone would scale with a mesh's wrong units."""
    if len(centres) > 1:
        spread = float(np.linalg.norm(np.ptp(centres, axis=0)))
        if spread > 0:
            return spread
    mid = 0.5 * (mesh_vertices.min(axis=0) + mesh_vertices.max(axis=0))
    return max(float(np.median(np.linalg.norm(centres - mid, axis=1))), 1e-12)


def check_scene(
    cameras: dict[str, PinholeCamera],
    mesh_vertices: np.ndarray,
    mesh_triangles: np.ndarray,
    layout_keys: list[str] | None = None,
) -> SceneCheck:
    """Measure ``cameras`` ({key: camera}) against the mesh; the camera layout's scale comes from the
    cameras ``layout_keys`` (default: all; the UAV survey, whose spread is the building's size)."""
    v = np.asarray(mesh_vertices, dtype=np.float64)
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    keys = layout_keys if layout_keys else list(cameras)
    centres = np.array([cameras[k].center for k in keys])
    ratio = diag / camera_scale(centres, v)
    caster = MeshRaycaster(v, np.asarray(mesh_triangles))
    seeing = {}
    for stem, cam in cameras.items():
        xs, ys = np.meshgrid(
            (np.arange(GRID[0]) + 0.5) * cam.width / GRID[0],
            (np.arange(GRID[1]) + 0.5) * cam.height / GRID[1],
        )
        o, d = cam.pixel_rays(xs, ys)
        seeing[stem] = float(caster.cast(o, d).hit.mean()) if not caster.empty else 0.0
    return SceneCheck(ratio, seeing)


def units_hint(ratio: float) -> str:
    """What a size ratio far from 1 most likely means."""
    if ratio > 1:
        return (
            f"the mesh is {ratio:.0f}x the size of the camera layout: units? (a mesh in millimetres is 1000x "
            "too large: scale it by 0.001)"
        )
    return (
        f"the mesh is 1/{1 / ratio:.0f} of the size of the camera layout: units? (a mesh in kilometres, or "
        "cameras in millimetres, is 1000x off)"
    )
