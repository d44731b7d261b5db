"""Geometric correction of the coarse facade mesh (the paper, section 3.1.3, Fig. 6b).

Each 3D panel is shrunk in its surface about its centre; the coarse mesh inside the panel's cuboid (the
shrunk footprint, extended by a half-depth either way along the normal) is removed and the shrunk panel
is put in its place, triangulated with its front facing outward, so the frames around it stay. On a
cylindrical part the footprint and the panel follow the cylinder (the cuboid bends with the surface).
Frames: local (01_import), metres; surface coordinates (s, z, h) as in ``facade_pipeline.panels``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from facade_pipeline.panels import Panel, PanelSet, PartSurface

RemovalRule = Literal["any_vertex", "centroid", "all_vertices"]


@dataclass(frozen=True, eq=False)
class CorrectedMesh:
    """The corrected mesh: ``vertices`` [V, 3], ``triangles`` [F, 3], ``is_panel`` [F] (True on inserted
    glass), and how many coarse triangles were removed."""

    vertices: np.ndarray
    triangles: np.ndarray
    is_panel: np.ndarray
    n_removed: int


def shrunk_corners(surface: PartSurface, panel: Panel, factor: float) -> np.ndarray:
    """Surface coordinates [4, 3] of the panel's corners shrunk about their centre by ``factor`` (h = 0)."""
    szh = surface.coords(panel.corners)
    c = szh.mean(axis=0)
    out = c + factor * (szh - c)
    out[:, 2] = 0.0
    return out


def _bilinear(corners: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Points [..., 3] of the bilinear patch over corners [4, 3] (BL, BR, TR, TL) at (u, v) in [0, 1]^2."""
    u, v = u[..., None], v[..., None]
    bottom = (1 - u) * corners[0] + u * corners[1]
    top = (1 - u) * corners[3] + u * corners[2]
    return (1 - v) * bottom + v * top


def panel_patch(surface: PartSurface, szh: np.ndarray, max_facet_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The panel over surface corners ``szh`` [4, 3] as triangles facing outward: vertices [M, 3] and
    triangles [K, 3]. On a cylinder the panel is split into facets of at most ``max_facet_deg`` (deg)."""
    n_u = 1
    if surface.kind == "cylindrical":
        span = float(np.ptp(szh[:, 0])) / surface.radius_m
        n_u = max(1, math.ceil(math.degrees(span) / max_facet_deg))
    u, v = np.meshgrid(np.linspace(0, 1, n_u + 1), np.array([0.0, 1.0]), indexing="ij")  # [n_u + 1, 2]
    verts = surface.points(_bilinear(szh, u, v).reshape(-1, 3))
    idx = np.arange((n_u + 1) * 2).reshape(n_u + 1, 2)
    a, b, c, d = idx[:-1, 0], idx[1:, 0], idx[1:, 1], idx[:-1, 1]  # BL, BR, TR, TL of each facet
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])  # right x up = outward
    return verts, tris


def in_cuboid(surface: PartSurface, szh: np.ndarray, half_depth_m: float, points: np.ndarray) -> np.ndarray:
    """[N] bool: world ``points`` [N, 3] inside the panel's cuboid: within the convex footprint ``szh``
    [4, 3] in (s, z) and within ``half_depth_m`` (m) of the surface along its normal."""
    q = surface.coords(points)
    inside = np.abs(q[:, 2]) <= half_depth_m
    c = szh[:, :2]
    for k in range(4):  # counter-clockwise in (s, z): every edge has the point on its left
        e, w = c[(k + 1) % 4] - c[k], q[:, :2] - c[k]
        inside &= e[0] * w[:, 1] - e[1] * w[:, 0] >= 0
    return inside


def correct_mesh(
    vertices: np.ndarray,
    triangles: np.ndarray,
    panels: PanelSet,
    shrink_factor: float,
    cuboid_half_depth_m: float,
    max_facet_deg: float,
    removal: RemovalRule,
) -> CorrectedMesh:
    """Replace the coarse mesh (``vertices`` [V, 3], ``triangles`` [F, 3]) inside each panel's cuboid by the
    shrunk panel (``removal`` decides when a triangle is inside: any vertex, its centroid, all vertices)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    remove = np.zeros(len(f), bool)
    new_v, new_f = [v], [f]
    offset = len(v)
    for p in panels.panels:
        surf = panels.parts[p.part]
        szh = shrunk_corners(surf, p, shrink_factor)
        if removal == "centroid":
            remove |= in_cuboid(surf, szh, cuboid_half_depth_m, v[f].mean(axis=1))
        else:
            vin = in_cuboid(surf, szh, cuboid_half_depth_m, v)[f]
            remove |= vin.any(axis=1) if removal == "any_vertex" else vin.all(axis=1)
        pv, pf = panel_patch(surf, szh, max_facet_deg)
        new_v.append(pv)
        new_f.append(pf + offset)
        offset += len(pv)
    keep = np.concatenate([~remove, np.ones(sum(len(x) for x in new_f[1:]), bool)])
    all_f = np.concatenate(new_f)[keep]
    is_panel = np.concatenate([np.zeros(len(f), bool), np.ones(len(keep) - len(f), bool)])[keep]
    return CorrectedMesh(np.concatenate(new_v), all_f, is_panel, int(remove.sum()))
