"""Triangle meshes with a material and an object id per triangle, and builders of boxes and curved prisms.

Winding: every triangle is counter-clockwise seen from outside, so its normal (b - a) x (c - a) points
outward (toward the cameras on the facade).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np


class Material(IntEnum):
    """Material ids stored per triangle; ``NONE`` marks rays that hit nothing (sky)."""

    NONE = 0
    GLASS = 1
    FRAME = 2
    WALL = 3
    GROUND = 4
    STONE = 5
    WATER = 6
    BUILDING = 7
    TRUNK = 8
    CROWN = 9
    INTERIOR = 10  # a room behind an unglazed unit; object id 4 * room + 0 walls, 1 shelves, 2 cloth, 3 posts
    MAST = 11  # poles and cranes; object id: 0 poles, 1 crane


@dataclass(frozen=True, eq=False)
class TriMesh:
    """Vertices [V, 3] float64 (world, m), triangles [F, 3] int64, material [F] uint8, object id [F] int32
    (panel index for glass, building index for buildings, -1 elsewhere)."""

    vertices: np.ndarray
    triangles: np.ndarray
    material: np.ndarray
    object_id: np.ndarray

    @property
    def normals(self) -> np.ndarray:  # [F, 3] unit outward normals, float64
        v = self.vertices[self.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    @property
    def areas(self) -> np.ndarray:  # [F] m^2
        v = self.vertices[self.triangles]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    def select(self, keep: np.ndarray) -> TriMesh:
        """The triangles where ``keep`` [F] is True (vertices are not compacted)."""
        return TriMesh(self.vertices, self.triangles[keep], self.material[keep], self.object_id[keep])


def empty_mesh() -> TriMesh:
    return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.uint8), np.zeros(0, np.int32))


def concat(meshes: Sequence[TriMesh]) -> TriMesh:
    """One mesh from several (triangle order kept: triangle ids follow the input order)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    return TriMesh(
        np.concatenate([m.vertices for m in meshes]) if meshes else np.zeros((0, 3)),
        np.concatenate([m.triangles + o for m, o in zip(meshes, offsets, strict=False)]).astype(np.int64)
        if meshes
        else np.zeros((0, 3), np.int64),
        np.concatenate([m.material for m in meshes]).astype(np.uint8) if meshes else np.zeros(0, np.uint8),
        np.concatenate([m.object_id for m in meshes]).astype(np.int32) if meshes else np.zeros(0, np.int32),
    )


def quads_to_mesh(quads: np.ndarray, outward: np.ndarray, material: int, object_id: int = -1) -> TriMesh:
    """Mesh of quads [Q, 4, 3] (corners in order around the quad) split into two triangles each, wound so
    that each triangle's normal has a positive dot product with ``outward`` [Q, 3]."""
    q = np.asarray(quads, dtype=np.float64)
    n = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]) + np.cross(q[:, 2] - q[:, 0], q[:, 3] - q[:, 0])
    flip = np.einsum("ij,ij->i", n, outward) < 0
    q = np.where(flip[:, None, None], q[:, ::-1], q)
    Q = len(q)
    base = 4 * np.arange(Q)[:, None]
    tris = (
        np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
        .reshape(2, Q, 3)
        .transpose(1, 0, 2)
        .reshape(-1, 3)
    )
    return TriMesh(
        q.reshape(-1, 3),
        tris.astype(np.int64),
        np.full(2 * Q, material, np.uint8),
        np.full(2 * Q, object_id, np.int32),
    )


SurfaceMap = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
"""(s, z, h) arrays -> [..., 3] world points: s along the surface, z up, h along its outward normal."""


def prism(
    surface: SurfaceMap,
    s: tuple[float, float],
    z: tuple[float, float],
    h: tuple[float, float],
    segments: int,
    material: int,
    object_id: int = -1,
) -> TriMesh:
    """A closed box in surface coordinates, s in [s0, s1] (split in ``segments`` facets), z in [z0, z1],
    h in [h0, h1], mapped to the world by ``surface``. On a curved surface it is a curved bar."""
    ss = np.linspace(s[0], s[1], segments + 1)
    S0, S1 = ss[:-1], ss[1:]
    quads, outs = [], []
    for hh, sign in ((h[1], 1.0), (h[0], -1.0)):  # front, back
        c = [
            surface(S0, z[0] + 0 * S0, hh + 0 * S0),
            surface(S1, z[0] + 0 * S0, hh + 0 * S0),
            surface(S1, z[1] + 0 * S0, hh + 0 * S0),
            surface(S0, z[1] + 0 * S0, hh + 0 * S0),
        ]
        quads.append(np.stack(c, axis=1))
        sm = 0.5 * (S0 + S1)
        outs.append(sign * (surface(sm, 0 * sm, 1.0 + 0 * sm) - surface(sm, 0 * sm, 0 * sm)))
    for zz, sign in ((z[1], 1.0), (z[0], -1.0)):  # top, bottom
        c = [
            surface(S0, zz + 0 * S0, h[0] + 0 * S0),
            surface(S1, zz + 0 * S0, h[0] + 0 * S0),
            surface(S1, zz + 0 * S0, h[1] + 0 * S0),
            surface(S0, zz + 0 * S0, h[1] + 0 * S0),
        ]
        quads.append(np.stack(c, axis=1))
        outs.append(np.tile([0.0, 0.0, sign], (segments, 1)))
    hm = 0.5 * (h[0] + h[1])
    zm = 0.5 * (z[0] + z[1])
    for ends, other in ((s[0], ss[1]), (s[1], ss[-2])):  # left, right ends
        e = np.array([ends])
        c = [
            surface(e, np.array([z[0]]), np.array([h[0]])),
            surface(e, np.array([z[0]]), np.array([h[1]])),
            surface(e, np.array([z[1]]), np.array([h[1]])),
            surface(e, np.array([z[1]]), np.array([h[0]])),
        ]
        quads.append(np.stack(c, axis=1))
        outs.append(
            surface(e, np.array([zm]), np.array([hm]))
            - surface(np.array([other]), np.array([zm]), np.array([hm]))
        )
    return quads_to_mesh(np.concatenate(quads), np.concatenate(outs), material, object_id)


def sheet(
    surface: SurfaceMap,
    s: tuple[float, float],
    z: tuple[float, float],
    segments: int,
    material: int,
    object_id: int = -1,
) -> TriMesh:
    """The one-sided surface patch h = 0, s in [s0, s1] (``segments`` facets), z in [z0, z1], facing +h."""
    ss = np.linspace(s[0], s[1], segments + 1)
    S0, S1 = ss[:-1], ss[1:]
    Z0, Z1 = np.full_like(S0, z[0]), np.full_like(S0, z[1])
    zero = np.zeros_like(S0)
    quads = np.stack(
        [surface(S0, Z0, zero), surface(S1, Z0, zero), surface(S1, Z1, zero), surface(S0, Z1, zero)], 1
    )
    sm = 0.5 * (S0 + S1)
    out = surface(sm, zero, zero + 1.0) - surface(sm, zero, zero)
    return quads_to_mesh(quads, out, material, object_id)
