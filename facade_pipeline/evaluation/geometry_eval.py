"""Geometry of a synthetic building's reconstruction against its truth (gt/ is read here, for evaluation
only): surface distance (m) on glass and on frames and the normal error (deg) on glass of the coarse mesh,
the corrected mesh and the trained Gaussians; the 3D panel corner error (m) and its image size (px).

Meshes are sampled by area (``meshing.metrics.surface_errors``); Gaussians are points (their centres) with
normals (the splat's third rotation axis), weighted equally, those below an opacity threshold left out
(they do not render). A sample is attributed to glass or frames by which true surface is nearer and
compared with that surface; samples farther than ``max_match_m`` from both (environment, ghosts) are counted
as unmatched. Local frame (01_import), metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.frames import invert_rigid
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.meshing.metrics import corner_errors, surface_errors
from facade_pipeline.panels3d.model import PanelSet
from facade_pipeline.synthetic.truth import read_truth_mesh, read_truth_panels


@dataclass(frozen=True)
class Truth:
    """The true glass and frame surfaces and panel corners [P, 4, 3], moved into the local frame."""

    glass: MeshRaycaster
    frames: MeshRaycaster
    panel_corners: np.ndarray
    body: MeshRaycaster | None = None
    """the building body behind the facade, left out of the mesh errors (None: not in gt/)"""


def load_truth(glass_mesh: Path, frame_mesh: Path, panels_json: Path, georef_from_local: np.ndarray,
               body_mesh: Path | None = None) -> Truth:
    """Read gt/ (world = georeferenced frame) into the pipeline's local frame (``synthetic.truth``)."""
    local_from_georef = invert_rigid(np.asarray(georef_from_local, np.float64))
    glass, frames = (MeshRaycaster(*read_truth_mesh(p, local_from_georef)) for p in (glass_mesh, frame_mesh))
    panels = read_truth_panels(panels_json, local_from_georef)
    corners = np.array([p["corners"] for p in panels], np.float64).reshape(-1, 4, 3)
    body = None if body_mesh is None else MeshRaycaster(*read_truth_mesh(body_mesh, local_from_georef))
    return Truth(glass, frames, corners, body)


def point_errors(points: np.ndarray, normals: np.ndarray, truth: Truth, max_match_m: float) -> dict[str, Any]:
    """The ``surface_errors`` figures for oriented points [N, 3] + [N, 3] (Gaussians) instead of a mesh.
    Normal error is unsigned (a splat has two faces)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    gp, _, gn = truth.glass.closest(pts)
    fp, _, _ = truth.frames.closest(pts)
    dg, df = np.linalg.norm(pts - gp, axis=1), np.linalg.norm(pts - fp, axis=1)
    on_glass, on_frame = (dg <= df) & (dg <= max_match_m), (df < dg) & (df <= max_match_m)
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(nrm * gn, axis=1)), 0.0, 1.0)))

    def stats(x: np.ndarray) -> tuple[float | None, float | None]:
        return (
            (round(float(np.mean(x)), 5), round(float(np.percentile(x, 95)), 5)) if len(x) else (None, None)
        )

    out: dict[str, Any] = {}
    out["glass_distance_mean_m"], out["glass_distance_p95_m"] = stats(dg[on_glass])
    out["frame_distance_mean_m"], out["frame_distance_p95_m"] = stats(df[on_frame])
    out["glass_normal_error_mean_deg"], out["glass_normal_error_p95_deg"] = stats(ang[on_glass])
    out["samples_unmatched"] = int(len(pts) - on_glass.sum() - on_frame.sum())
    return out


def mesh_errors(
    vertices: np.ndarray,
    triangles: np.ndarray,
    truth: Truth,
    n_samples: int,
    max_match_m: float,
    seed: int = 0,
) -> dict[str, Any]:
    """Surface distance and normal error of a mesh against the truth (``meshing.metrics.surface_errors``)."""
    return surface_errors(vertices, triangles, truth.glass, truth.frames, n_samples, max_match_m, seed,
                          other=truth.body)


def corner_error_px(panels: PanelSet, truth: Truth, cameras: list[PinholeCamera]) -> dict[str, Any]:
    """Panel corner error in pixels: each panel matched to the true panel with the nearest centre, both
    projected into every camera that sees all eight corners in front of it and inside the image; mean and
    max over those corners and cameras (None when no camera sees a panel whole)."""
    if not panels.panels or len(truth.panel_corners) == 0:
        return {"corner_error_mean_px": None, "corner_error_max_px": None}
    centres = truth.panel_corners.mean(axis=1)
    errs = []
    for p in panels.panels:
        true = truth.panel_corners[int(np.argmin(np.linalg.norm(centres - p.center, axis=1)))]
        for cam in cameras:
            uv, z = cam.project(np.concatenate([p.corners, true]))
            inside = (
                (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            )
            if inside.all():
                errs.append(np.linalg.norm(uv[:4] - uv[4:], axis=1))
    if not errs:
        return {"corner_error_mean_px": None, "corner_error_max_px": None}
    e = np.concatenate(errs)
    return {
        "corner_error_mean_px": round(float(e.mean()), 4),
        "corner_error_max_px": round(float(e.max()), 4),
    }


def panel_corner_errors(panels: PanelSet, truth: Truth, cameras: list[PinholeCamera]) -> dict[str, Any]:
    """3D corner error (m, ``meshing.metrics.corner_errors``) and its image size (px) in ``cameras``."""
    return {
        **corner_errors(panels, truth.panel_corners),
        **corner_error_px(panels, truth, cameras),
        "panels": len(panels.panels),
        "true_panels": len(truth.panel_corners),
    }
