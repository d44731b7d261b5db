"""Initial Gaussians (section 3.2): the coarse point cloud inside the facade's bounds, plus samples of the
corrected mesh as surfels lying in the surface (oriented along the mesh normal)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from facade_pipeline.training.data import InitGeometry
from facade_pipeline.training.model import GaussianModel, quat_from_normal


def sample_mesh(
    vertices: np.ndarray, triangles: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` points uniformly by area on a triangle mesh [V, 3] / [T, 3], with their unit face normals
    and the index of the triangle each lies on. Degenerate (zero-area) triangles are never chosen."""
    empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
    if count <= 0 or len(triangles) == 0:
        return empty
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    if area.sum() <= 0:
        return empty
    tri = rng.choice(len(triangles), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    pts = a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])
    normals = cross[tri] / np.linalg.norm(cross[tri], axis=1, keepdims=True)
    return pts, normals, tri


def crop_to_bounds(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin_m: float) -> np.ndarray:
    """[P] bool: points inside the box [lo - margin, hi + margin]."""
    return np.all((points >= lo - margin_m) & (points <= hi + margin_m), axis=1)


#: An initial splat's size is its mean distance to this many nearest neighbours: the 3DGS (and 2DGS)
#: initialisation, never tuned here.
INIT_KNN = 3
#: Initial opacity of every splat: 3DGS's and 2DGS's 0.1, never tuned here.
INIT_OPACITY = 0.1


def knn_distance(points: np.ndarray, k: int) -> np.ndarray:  # [P, 3] -> [P]
    """Mean distance to the ``k`` nearest other points (the 3DGS initial scale), at least 1e-4 m."""
    if len(points) < 2:
        return np.full(len(points), 0.1)
    k = min(k, len(points) - 1)
    d, _ = cKDTree(points).query(points, k=k + 1)
    return np.maximum(d[:, 1:].mean(axis=1), 1e-4)


def initial_model(
    geom: InitGeometry,
    bounds: tuple[np.ndarray, np.ndarray],
    max_points: int,
    mesh_samples: int,
    margin_m: float,
    knn: int,
    opacity: float,
    reflectivity: float,
    reflectivity_glass: float,
    f0: float,
    sh_degree: int,
    seed: int,
    device: torch.device | str,
) -> GaussianModel:
    """The initial model: up to ``max_points`` coarse points within the bounds (random rotations) and
    ``mesh_samples`` mesh samples lying in the surface; scales from the k-nearest-neighbour distance;
    colours from the points (mesh samples take their nearest point's colour). Reflectivity
    ``reflectivity_glass`` for samples of the mesh's glass triangles (when it has labels), else
    ``reflectivity``."""
    rng = np.random.default_rng(seed)
    keep = np.flatnonzero(crop_to_bounds(geom.points, *bounds, margin_m))
    if len(keep) > max_points:
        keep = np.sort(rng.choice(keep, size=max_points, replace=False))
    pts, cols = geom.points[keep], geom.colors[keep]
    mpts, mnormals, mtri = sample_mesh(geom.mesh_vertices, geom.mesh_triangles, mesh_samples, rng)
    on_glass = np.zeros(len(mpts), bool) if geom.mesh_glass is None else geom.mesh_glass[mtri]
    refl = np.concatenate(
        [np.full(len(pts), reflectivity), np.where(on_glass, reflectivity_glass, reflectivity)]
    )
    if len(pts):
        _, nearest = cKDTree(pts).query(mpts, k=1) if len(mpts) else (None, np.zeros(0, int))
        mcols = cols[nearest]
    else:
        mcols = np.full((len(mpts), 3), 0.5)
    means = np.concatenate([pts, mpts])
    if len(means) == 0:
        from facade_pipeline.errors import InputError

        raise InputError(None, "coarse points or corrected-mesh samples inside the facade bounds", "none")
    rq = rng.normal(size=(len(pts), 4))
    quats = torch.cat(
        [
            torch.as_tensor(rq / np.linalg.norm(rq, axis=1, keepdims=True)),
            quat_from_normal(torch.as_tensor(mnormals, dtype=torch.float64)),
        ]
    )
    dist = knn_distance(means, knn)
    f32 = dict(dtype=torch.float32, device=device)
    return GaussianModel.create(
        torch.as_tensor(means, **f32),
        quats.to(**f32),
        torch.as_tensor(np.stack([dist, dist], 1), **f32),
        torch.as_tensor(np.concatenate([cols, mcols]), **f32),
        opacity,
        torch.as_tensor(refl, **f32),
        f0,
        sh_degree,
    )
