"""Ray casting against a triangle mesh through open3d's ``RaycastingScene`` (Embree, all cores).

The scene is built once per mesh; rays are cast in chunks so that memory stays bounded whatever the
number of rays. Degenerate triangles (zero area, non-finite vertices) are dropped before the scene is built
and hit ids are mapped back to the caller's triangle indices. Distances are along unit directions (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

DEFAULT_CHUNK_RAYS = 1 << 18


@dataclass(frozen=True, eq=False)
class RayHits:
    """First hits of N rays: distance ``t`` [N] (inf: none), geometric unit ``normal`` [N, 3] of the hit
    triangle as wound in the mesh (zero where none), and the mesh triangle index ``prim`` [N] (-1: none)."""

    t: np.ndarray
    normal: np.ndarray
    prim: np.ndarray

    @property
    def hit(self) -> np.ndarray:  # [N] bool
        return np.isfinite(self.t)


def clean_triangles(vertices: np.ndarray, triangles: np.ndarray, min_area_m2: float = 1e-12) -> np.ndarray:
    """Indices of the triangles [F, 3] of ``vertices`` [V, 3] that are usable for ray casting: indices in
    range, finite vertices and area above ``min_area_m2`` (m^2)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return np.zeros(0, dtype=np.int64)
    in_range = (f >= 0).all(1) & (f < len(v)).all(1)
    fc = np.where(in_range[:, None], f, 0)
    p = v[fc]
    finite = np.isfinite(p).all(axis=(1, 2))
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    return np.flatnonzero(in_range & finite & (np.nan_to_num(area) > min_area_m2))


class MeshRaycaster:
    """First-hit ray casting against one mesh (local frame, m). Holes simply let rays through."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, min_area_m2: float = 1e-12):
        keep = clean_triangles(vertices, triangles, min_area_m2)
        self.prim_map = keep  # scene triangle -> caller's triangle index
        self.n_dropped = int(len(np.asarray(triangles).reshape(-1, 3)) - len(keep))
        self.scene = o3d.t.geometry.RaycastingScene()
        # per scene triangle: unit normal as wound and one vertex (float64 maths, float32 storage), for bakes
        # that look normals up by triangle id instead of fetching them per ray
        self.tri_normals = np.zeros((len(keep), 3), np.float32)
        self.tri_vertex = np.zeros((len(keep), 3), np.float64)
        if len(keep):
            f = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)[keep]
            p = np.asarray(vertices, dtype=np.float64)[f]
            n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            self.tri_normals[:] = n / np.linalg.norm(n, axis=1, keepdims=True)
            self.tri_vertex[:] = p[:, 0]
            v = np.asarray(vertices, dtype=np.float32)
            used, inv = np.unique(f, return_inverse=True)
            self.scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(v[used])),
                o3d.core.Tensor(inv.reshape(-1, 3).astype(np.uint32)),
            )

    @property
    def empty(self) -> bool:
        return len(self.prim_map) == 0

    def cast(self, origins: np.ndarray, dirs: np.ndarray, chunk_rays: int = DEFAULT_CHUNK_RAYS) -> RayHits:
        """First hits of rays ``origins`` [N, 3], unit ``dirs`` [N, 3], cast ``chunk_rays`` at a time."""
        o = np.asarray(origins, dtype=np.float32).reshape(-1, 3)
        d = np.asarray(dirs, dtype=np.float32).reshape(-1, 3)
        n = len(o)
        t = np.full(n, np.inf, np.float32)
        normal = np.zeros((n, 3), np.float32)
        prim = np.full(n, -1, np.int64)
        if self.empty or n == 0:
            return RayHits(t, normal, prim)
        for a in range(0, n, max(1, int(chunk_rays))):
            b = min(n, a + int(chunk_rays))
            r = self.cast_rays(np.concatenate([o[a:b], d[a:b]], axis=1))
            t[a:b], normal[a:b], prim[a:b] = r
        return RayHits(t, normal, prim)

    def closest(
        self, points: np.ndarray, chunk: int = DEFAULT_CHUNK_RAYS
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points [N, 3], mesh triangle indices [N] and triangle unit normals [N, 3] of
        query ``points`` [N, 3] (float32 precision: keep coordinates near the origin)."""
        q = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        pts, prim, nrm = np.zeros_like(q), np.zeros(len(q), np.int64), np.zeros_like(q)
        for a in range(0, len(q), chunk):
            out = self.scene.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(q[a : a + chunk])))
            pts[a : a + chunk] = out["points"].numpy()
            prim[a : a + chunk] = self.prim_map[out["primitive_ids"].numpy().astype(np.int64)]
            nrm[a : a + chunk] = out["primitive_normals"].numpy()
        return pts, prim, nrm

    def cast_rays(self, rays: np.ndarray | o3d.core.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One batch: rays [..., 6] float32 (origin, direction; t is in units of the direction's length) ->
        (t [M], normal [M, 3], prim [M]) flattened over the leading dimensions."""
        if not isinstance(rays, o3d.core.Tensor):
            rays = o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32))
        out = self.scene.cast_rays(rays)
        t = out["t_hit"].numpy().ravel()
        ids = out["primitive_ids"].numpy().ravel().astype(np.int64)
        hit = np.isfinite(t)
        prim = np.where(hit, self.prim_map[np.where(hit, ids, 0)], -1)
        normal = out["primitive_normals"].numpy().reshape(-1, 3)
        normal[~hit] = 0.0
        return t, normal, prim


def grazing(dirs: np.ndarray, normals: np.ndarray, max_incidence_deg: float) -> np.ndarray:
    """[N] bool: rays whose angle to the hit surface's normal exceeds ``max_incidence_deg`` (deg), i.e. that
    skim the surface and give an unreliable position. Either side of the surface counts the same."""
    cos = np.abs(np.sum(np.asarray(dirs, np.float64) * np.asarray(normals, np.float64), axis=-1))
    return cos < np.cos(np.radians(max_incidence_deg))
