"""Geometry metrics against a synthetic building's truth (gt/ is read for metrics only, never to drive an
algorithm): surface distance from a mesh to the true facade on glass and on frames (mean and 95th
percentile, m) and the normal angle error on glass (deg), and the 3D panel corner error (m).

Points are sampled uniformly by area on the mesh under test; each sample is attributed to glass or to the
frames by which true surface is nearer, and compared with that surface's nearest point. Normal angles are
unsigned (a triangle wound the other way has the same error): facing is checked where it matters, in the
baked normal maps. Local frame, metres.
"""

from __future__ import annotations

import numpy as np

from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.panels3d.model import PanelSet


def sample_surface(
    vertices: np.ndarray, triangles: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points [n, 3] uniformly by area on a mesh and the unit normals [n, 3] of their triangles
    (degenerate triangles have zero area and are never drawn)."""
    p = np.asarray(vertices, np.float64)[np.asarray(triangles, np.int64)]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = np.linalg.norm(cross, axis=1)
    tri = rng.choice(len(p), size=n, p=area / area.sum())
    a, b = rng.uniform(size=(2, n))
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    pts = p[tri, 0] + a[:, None] * (p[tri, 1] - p[tri, 0]) + b[:, None] * (p[tri, 2] - p[tri, 0])
    return pts, cross[tri] / area[tri, None]


def surface_errors(
    vertices: np.ndarray,
    triangles: np.ndarray,
    glass: MeshRaycaster,
    frames: MeshRaycaster,
    n_samples: int,
    max_match_m: float,
    seed: int = 0,
    other: MeshRaycaster | None = None,
) -> dict[str, float | None]:
    """Distances (m) from ``n_samples`` points of the mesh to the true glass and frames (``glass``,
    ``frames``), split by the nearer of the two; samples farther than ``max_match_m`` from both are left
    out (counted), and so are samples nearer to ``other`` (the true surfaces that are not facade: the
    building body's roof, which a coarse mesh holds too) than to both (counted apart). Normal error (deg)
    on glass samples."""
    pts, nrm = sample_surface(vertices, triangles, n_samples, np.random.default_rng(seed))
    gp, _, gn = glass.closest(pts)
    fp, _, _ = frames.closest(pts)
    dg, df = np.linalg.norm(pts - gp, axis=1), np.linalg.norm(pts - fp, axis=1)
    facade = np.ones(len(pts), bool)
    if other is not None:
        op, _, _ = other.closest(pts)
        facade = np.linalg.norm(pts - op, axis=1) >= np.minimum(dg, df)
    on_glass = facade & (dg <= df) & (dg <= max_match_m)
    on_frame = facade & (df < dg) & (df <= max_match_m)
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(nrm * gn, axis=1)), 0.0, 1.0)))

    def stats(x: np.ndarray) -> tuple[float | None, float | None]:  # None (JSON null) without samples
        return (float(np.mean(x)), float(np.percentile(x, 95))) if len(x) else (None, None)

    out: dict[str, float | None] = {}
    out["glass_distance_mean_m"], out["glass_distance_p95_m"] = stats(dg[on_glass])
    out["frame_distance_mean_m"], out["frame_distance_p95_m"] = stats(df[on_frame])
    out["glass_normal_error_mean_deg"], out["glass_normal_error_p95_deg"] = stats(ang[on_glass])
    out["samples_off_facade"] = int((~facade).sum())
    out["samples_unmatched"] = int(n_samples - on_glass.sum() - on_frame.sum() - (~facade).sum())
    return {k: (round(v, 5) if isinstance(v, float) else v) for k, v in out.items()}


def corner_errors(panels: PanelSet, true_corners: np.ndarray) -> dict[str, float | None]:
    """3D corner error (m) of each panel against the true panel [P, 4, 3] whose centre is nearest."""
    if not panels.panels or len(true_corners) == 0:
        return {"corner_error_mean_m": None, "corner_error_max_m": None}
    centres = true_corners.mean(axis=1)
    errs = []
    for p in panels.panels:
        k = int(np.argmin(np.linalg.norm(centres - p.center, axis=1)))
        errs.append(np.linalg.norm(p.corners - true_corners[k], axis=1))
    e = np.concatenate(errs)
    return {"corner_error_mean_m": round(float(e.mean()), 5), "corner_error_max_m": round(float(e.max()), 5)}
