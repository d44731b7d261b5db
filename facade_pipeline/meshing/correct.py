"""Geometric correction of the coarse facade mesh (the paper, section 3.1.3, Fig. 6b).

Each 3D panel is shrunk in its surface about its centre; the coarse mesh inside the panel's cuboid (the
shrunk footprint, extended by a half-depth either way along the normal) is removed and the shrunk panel
is put in its place, triangulated with its front facing outward, so the frames around it stay. On a
cylindrical part the footprint and the panel follow the cylinder (the cuboid bends with the surface).
Where the removal leaves the frames between and around the panels without surface (a coarse mesh whose
cells are wider than a frame bar loses every cell that touches a panel), a frame backing fills them.
Frames: local (01_import), metres; surface coordinates (s, z, h) as in ``facade_pipeline.panels3d.model``.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import write_bytes
from facade_pipeline.panels3d.model import Panel, PanelSet, PartSurface, frame_width, part_outline

OTHER, FRAME, GLASS = 0, 1, 2  # triangle labels of the corrected mesh (05_correct_mesh/triangle_labels.npy)
LABEL_NAMES = {OTHER: "other", FRAME: "frame", GLASS: "glass"}


@dataclass(frozen=True, eq=False)
class CorrectedMesh:
    """The corrected mesh: ``vertices`` [V, 3], ``triangles`` [F, 3], ``is_panel`` [F] (True on inserted
    glass), how many coarse triangles were removed and how many triangles of frame backing were added
    (``frame_backing``; they are last)."""

    vertices: np.ndarray
    triangles: np.ndarray
    is_panel: np.ndarray
    n_removed: int
    n_backing: int = 0


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
    insert_factor: float | None = None,
) -> CorrectedMesh:
    """Replace the coarse mesh (``vertices`` [V, 3], ``triangles`` [F, 3]) inside each panel's cuboid (the
    panel shrunk by ``shrink_factor``) by the panel scaled by ``insert_factor`` (default: the shrunk one).
    A coarse triangle with any vertex inside a cuboid is removed, so that no coarse fragment pokes through
    the inserted glass. Inserting the whole panel (1) closes the gap that the removal leaves around the
    shrunk one: the glass runs on under the kept frames, which stand in front of it, as in the real
    facade."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    remove = np.zeros(len(f), bool)
    new_v, new_f = [v], [f]
    offset = len(v)
    for p in panels.panels:
        surf = panels.parts[p.part]
        szh = shrunk_corners(surf, p, shrink_factor)
        remove |= in_cuboid(surf, szh, cuboid_half_depth_m, v)[f].any(axis=1)
        ins = szh if insert_factor is None else shrunk_corners(surf, p, insert_factor)
        if insert_factor is not None and insert_factor > shrink_factor:
            # coarse triangles centred over the inserted glass (the smoothed step down from a frame to the
            # glass) would cover it: they go too; frames lie outside the glass footprint and stay
            remove |= in_cuboid(surf, ins, cuboid_half_depth_m, v[f].mean(axis=1))
        pv, pf = panel_patch(surf, ins, max_facet_deg)
        new_v.append(pv)
        new_f.append(pf + offset)
        offset += len(pv)
    keep = np.concatenate([~remove, np.ones(sum(len(x) for x in new_f[1:]), bool)])
    all_f = np.concatenate(new_f)[keep]
    is_panel = np.concatenate([np.zeros(len(f), bool), np.ones(len(keep) - len(f), bool)])[keep]
    all_v = np.concatenate(new_v)
    bv, bf = frame_backing(panels, v, f[~remove], cuboid_half_depth_m, insert_factor or shrink_factor)
    return CorrectedMesh(
        np.concatenate([all_v, bv]),
        np.concatenate([all_f, bf + len(all_v)]),
        np.concatenate([is_panel, np.zeros(len(bf), bool)]),
        int(remove.sum()),
        len(bf),
    )


#: The frame backing's cells are this fraction of the part's frame width on a side: fine enough that the
#: frame bars keep their width within a quarter of it.
BACKING_CELL_FRACTION = 0.25
#: The backing lies this fraction of the frame width behind the glass surface: the glass, which may run
#: under its cells' edges, is hit first; a twentieth keeps the backing's parallax far below a bar's width.
BACKING_DEPTH_FRACTION = 0.05


def frame_backing(
    panels: PanelSet,
    vertices: np.ndarray,
    kept: np.ndarray,
    half_depth_m: float,
    insert_factor: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [M, 3] and outward triangles [K, 3] of surface where the frames between and around the
    panels have none: square cells (``BACKING_CELL_FRACTION`` of the part's frame width) within one frame
    width of a panel and outside every inserted panel (the panels scaled by ``insert_factor``), kept where
    the coarse mesh's ``kept`` triangles [F, 3] of ``vertices`` [V, 3] have no surface within
    ``half_depth_m`` (m) of the glass along its normal. They lie just behind the glass surface
    (``BACKING_DEPTH_FRACTION``): a coarse frame that stands proud of the glass is hit before them."""
    # imported here: correct_mesh's tests of the geometry alone need no ray caster
    from facade_pipeline.geometry.raycast import MeshRaycaster

    rc = MeshRaycaster(np.asarray(vertices, np.float64), np.asarray(kept, np.int64).reshape(-1, 3))
    out_v, out_f, offset = [], [], 0
    for k, surface in enumerate(panels.parts):
        own = panels.of_part(k)
        fw = frame_width(own, surface) if own else 0.0
        if fw <= 0.0:
            continue
        cell = BACKING_CELL_FRACTION * fw
        boxes = np.stack([surface.coords(p.corners)[:, :2] for p in own])  # [P, 4, 2]
        lo, hi = boxes.min(axis=(0, 1)) - fw, boxes.max(axis=(0, 1)) + fw
        s, z = (np.arange(a + cell / 2, b, cell) for a, b in zip(lo, hi, strict=True))
        ss, zz = (g.ravel() for g in np.meshgrid(s, z, indexing="ij"))
        centres = np.stack([ss, zz, np.zeros_like(ss)], axis=1)
        d = cell / 2
        square = np.array([[-d, -d, 0], [d, -d, 0], [d, d, 0], [-d, d, 0]])  # BL, BR, TR, TL: outward
        near = np.zeros(len(ss), bool)
        glass = np.zeros(len(ss), bool)  # cells wholly behind an inserted panel (one that it cuts stays)
        for p, box in zip(own, boxes, strict=True):
            near |= ((centres[:, :2] >= box.min(0) - fw) & (centres[:, :2] <= box.max(0) + fw)).all(1)
            ins = shrunk_corners(surface, p, insert_factor)
            corners = surface.points((centres[:, None] + square).reshape(-1, 3))
            glass |= in_cuboid(surface, ins, np.inf, corners).reshape(-1, 4).all(axis=1)
        centres = centres[near & ~glass]
        if not len(centres):
            continue
        if not rc.empty:
            foot = surface.points(centres)
            normal = surface.normals_at(foot)
            hits = rc.cast(foot + 2.0 * half_depth_m * normal, -normal)
            covered = np.isfinite(hits.t) & (hits.t <= 4.0 * half_depth_m)
            centres = centres[~covered]
        corners = centres[:, None, :] + square
        corners[..., 2] = -BACKING_DEPTH_FRACTION * fw
        out_v.append(surface.points(corners.reshape(-1, 3)))
        base = offset + 4 * np.arange(len(centres))[:, None]
        out_f.append(np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]))
        offset += 4 * len(centres)
    if not out_v:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(out_v), np.concatenate(out_f).astype(np.int64)


def label_triangles(
    vertices: np.ndarray, triangles: np.ndarray, is_panel: np.ndarray, panels: PanelSet, half_depth_m: float
) -> np.ndarray:
    """Label [F] uint8 of every triangle of the corrected mesh (``vertices`` [V, 3], ``triangles`` [F, 3]):
    GLASS for the inserted panels (``is_panel`` [F]), FRAME for the kept coarse triangles whose centroid
    lies inside a part's facade outline (its panels grown by one frame width, ``part_outline``) within
    ``half_depth_m`` (m) of the glass surface along its normal, OTHER for the rest. A ray's hit triangle
    then says whether the pixel sees glass, a frame (which may hide glass) or something else."""
    f = np.asarray(triangles, np.int64).reshape(-1, 3)
    centroids = np.asarray(vertices, np.float64)[f].mean(axis=1)
    labels = np.where(np.asarray(is_panel, bool), GLASS, OTHER).astype(np.uint8)
    for k, surface in enumerate(panels.parts):
        own = panels.of_part(k)
        if not own:
            continue
        (s0, z0, _), _, (s1, z1, _), _ = part_outline(own, surface)
        q = surface.coords(centroids)
        inside = (q[:, 0] >= s0) & (q[:, 0] <= s1) & (q[:, 1] >= z0) & (q[:, 1] <= z1)
        labels[inside & (np.abs(q[:, 2]) <= half_depth_m) & (labels == OTHER)] = FRAME
    return labels


def write_labels(path: str | Path, labels: np.ndarray) -> None:
    """Write triangle labels [F] as a uint8 ``.npy`` file, atomically."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(labels, np.uint8), allow_pickle=False)
    write_bytes(path, buf.getvalue())


def read_labels(path: str | Path, n_triangles: int) -> np.ndarray:
    """Read triangle labels [F] and check there is one valid label for each of ``n_triangles`` triangles."""
    path = Path(path)
    try:
        labels = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(path, "triangle labels written by correct_mesh", "no file") from None
    except (OSError, ValueError) as e:
        raise InputError(path, "a uint8 .npy array of triangle labels", f"{type(e).__name__}: {e}") from None
    if labels.dtype != np.uint8 or labels.shape != (n_triangles,) or labels.max(initial=0) > GLASS:
        raise InputError(
            path,
            f"{n_triangles} uint8 labels in 0..{GLASS} (one per corrected-mesh triangle)",
            f"{labels.dtype} array of shape {labels.shape}",
        )
    return labels
