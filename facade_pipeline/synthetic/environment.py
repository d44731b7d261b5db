"""The near-field environment in front of the facade: tiled ground, a fountain, nearby buildings, trees.

Everything is placed in the site frame (``world_from_site``: origin at the mean of the parts' origins on
the ground z = 0, y the mean outward normal of the parts, z up) at finite distances, so that reflections
of it in the glass move with parallax between views. Placement is random but deterministic for a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from facade_pipeline.synthetic.mesh import Material, TriMesh, concat, quads_to_mesh
from facade_pipeline.synthetic.params import EnvironmentParams, FacadePart

ROUND_SEGMENTS = 48  # facets around the fountain's cylinders
TRUNK_RADIUS_FRACTION = 0.03  # trunk radius / tree height
CROWN_RADIUS_FRACTION = 0.3  # crown radius / tree height
CROWN_CENTER_FRACTION = 0.65  # crown centre height / tree height
CLEARANCE_M = 2.0  # free space kept around the fountain, the court and the road when placing trees


def site_frame(parts: tuple[FacadePart, ...]) -> np.ndarray:
    """``world_from_site`` [4, 4]: origin = mean part origin at z = 0, y = mean outward normal, z up."""
    normals = np.array(
        [[math.cos(math.radians(p.facing_deg)), math.sin(math.radians(p.facing_deg)), 0.0] for p in parts]
    )
    y = normals.sum(axis=0)
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = np.cross(y, [0.0, 0.0, 1.0]), y, (0.0, 0.0, 1.0)
    origin = np.mean([p.origin_m for p in parts], axis=0)
    T[:3, 3] = (origin[0], origin[1], 0.0)
    return T


def _to_world(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def ground_mesh(env: EnvironmentParams, T: np.ndarray) -> TriMesh:
    """Square ground at z = 0 centred on the site origin, split into tiles of ``ground_tile_m``, facing up."""
    n = max(1, int(math.ceil(2 * env.ground_half_size_m / env.ground_tile_m)))
    g = np.linspace(-env.ground_half_size_m, env.ground_half_size_m, n + 1)
    x0, y0 = np.meshgrid(g[:-1], g[:-1], indexing="ij")
    x1, y1 = x0 + (g[1] - g[0]), y0 + (g[1] - g[0])
    z = np.zeros_like(x0)
    quads = np.stack([np.stack(c, -1) for c in ((x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z))], axis=2)
    quads = _to_world(T, quads.reshape(-1, 4, 3))
    return quads_to_mesh(quads, np.tile([0.0, 0.0, 1.0], (len(quads), 1)), Material.GROUND)


def cylinder_mesh(
    center: np.ndarray,
    radius: float,
    z0: float,
    z1: float,
    material: int,
    inward: bool = False,
    top: bool = False,
) -> TriMesh:
    """Side of a vertical cylinder (world ``center`` [3] on its axis at z = 0), optionally with a top disc.
    ``inward`` makes the side face the axis (the inside of the fountain basin)."""
    a = np.linspace(0.0, 2 * math.pi, ROUND_SEGMENTS + 1)
    c, s = np.cos(a), np.sin(a)
    ring0 = np.stack([center[0] + radius * c, center[1] + radius * s, np.full_like(a, z0)], -1)
    ring1 = ring0.copy()
    ring1[:, 2] = z1
    quads = np.stack([ring0[:-1], ring0[1:], ring1[1:], ring1[:-1]], axis=1)
    mid = 0.5 * (a[:-1] + a[1:])
    out = np.stack([np.cos(mid), np.sin(mid), np.zeros_like(mid)], -1) * (-1.0 if inward else 1.0)
    meshes = [quads_to_mesh(quads, out, material)]
    if top:
        meshes.append(disc_mesh(center, radius, z1, material))
    return concat(meshes)


def disc_mesh(center: np.ndarray, radius: float, z: float, material: int, inner: float = 0.0) -> TriMesh:
    """Horizontal disc (or annulus with ``inner`` > 0) at height z, facing up."""
    a = np.linspace(0.0, 2 * math.pi, ROUND_SEGMENTS + 1)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], -1)
    outer = center[:2].tolist() + [z] + ring * radius
    inn = center[:2].tolist() + [z] + ring * max(inner, 1e-3)
    quads = np.stack([inn[:-1], outer[:-1], outer[1:], inn[1:]], axis=1)
    return quads_to_mesh(quads, np.tile([0.0, 0.0, 1.0], (ROUND_SEGMENTS, 1)), material)


def fountain_mesh(env: EnvironmentParams, T: np.ndarray) -> TriMesh:
    """A circular basin (stone wall 0.4 m thick), water at 70 % of its height, and a central column."""
    c = _to_world(T, np.array([[*env.fountain_center_m, 0.0]]))[0]
    r, hgt = env.fountain_radius_m, env.fountain_height_m
    wall = 0.1 * r
    return concat(
        [
            cylinder_mesh(c, r, 0.0, hgt, Material.STONE),
            cylinder_mesh(c, r - wall, 0.7 * hgt, hgt, Material.STONE, inward=True),
            disc_mesh(c, r, hgt, Material.STONE, inner=r - wall),
            disc_mesh(c, r - wall, 0.7 * hgt, Material.WATER, inner=0.1 * r),
            cylinder_mesh(c, 0.1 * r, 0.7 * hgt, 3.0 * hgt, Material.STONE, top=True),
        ]
    )


def box_mesh(center: np.ndarray, size: np.ndarray, yaw: float, material: int, object_id: int = -1) -> TriMesh:
    """An axis-aligned box rotated by ``yaw`` (rad) about z; ``center`` [3] is the centre of its base."""
    sx, sy, sz = np.asarray(size, dtype=np.float64) / [2.0, 2.0, 1.0]
    corners = np.array([[x, y, z] for z in (0.0, sz) for y in (-sy, sy) for x in (-sx, sx)])
    R = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    v = corners @ R.T + center
    faces = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    out = (
        np.array([[0, 0, -1], [0, 0, 1], [0, -1, 0], [0, 1, 0], [-1, 0, 0], [1, 0, 0]], dtype=np.float64)
        @ R.T
    )
    return quads_to_mesh(v[np.array(faces)], out, material, object_id)


def sphere_mesh(center: np.ndarray, radius: float, material: int, subdivisions: int = 1) -> TriMesh:
    """A low-poly sphere: an octahedron subdivided ``subdivisions`` times, vertices pushed to the sphere."""
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
    tris = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    tri_v = v[tris]
    for _ in range(subdivisions):
        a, b, c = tri_v[:, 0], tri_v[:, 1], tri_v[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tri_v = np.concatenate(
            [np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
        )
    tri_v /= np.linalg.norm(tri_v, axis=2, keepdims=True)
    F = len(tri_v)
    return TriMesh(
        center + radius * tri_v.reshape(-1, 3),
        np.arange(3 * F).reshape(F, 3),
        np.full(F, material, np.uint8),
        np.full(F, -1, np.int32),
    )


@dataclass(frozen=True)
class Placement:
    """Site-frame placements of the environment objects (for scene.json)."""

    buildings: tuple[tuple[float, float, float, float, float, float], ...]  # x, y, width, depth, height, yaw
    trees: tuple[tuple[float, float, float], ...]  # x, y, height
    poles: tuple[tuple[float, float, float], ...] = ()  # x, y, height ("masts_and_cranes")
    crane: tuple[float, ...] = ()  # x, y, height, jib length ("masts_and_cranes")


def place_objects(
    env: EnvironmentParams,
    half_span_m: float,
    rng: np.random.Generator,
    masts: np.random.Generator | None = None,
) -> Placement:
    """Buildings in slots across site x beyond ``building_distance_m``; trees at random spots that keep
    ``CLEARANCE_M`` from the fountain, the court, the road and each other; with a generator ``masts``
    ("masts_and_cranes", drawn apart so that the other objects stay where they were) poles across the
    facade's span and a tower crane beside it."""
    buildings = []
    span = max(half_span_m, env.building_distance_m[1])
    slots = np.linspace(-span, span, env.building_count + 1)
    for k in range(env.building_count):
        w = min(rng.uniform(*env.building_width_m), 0.9 * (slots[k + 1] - slots[k]))
        d, h = rng.uniform(*env.building_depth_m), rng.uniform(*env.building_height_m)
        x = 0.5 * (slots[k] + slots[k + 1])
        y = rng.uniform(*env.building_distance_m) + d / 2
        buildings.append((x, y, w, d, h, rng.uniform(-0.25, 0.25)))
    trees: list[tuple[float, float, float]] = []
    for _ in range(200 * max(env.tree_count, 1)):
        if len(trees) >= env.tree_count:
            break
        x, y = rng.uniform(-half_span_m, half_span_m), rng.uniform(*env.tree_distance_m)
        h = rng.uniform(*env.tree_height_m)
        if _tree_fits(env, x, y, h * CROWN_RADIUS_FRACTION, trees):
            trees.append((x, y, h))
    if masts is None:
        return Placement(tuple(buildings), tuple(trees))
    # poles spread across the span (a stratum each), so that every part of the facade reflects one
    edges = np.linspace(-half_span_m, half_span_m, env.pole_count + 1)
    poles = tuple(
        (float(masts.uniform(a, b)), float(masts.uniform(*env.pole_distance_m)), env.pole_height_m)
        for a, b in zip(edges[:-1], edges[1:], strict=True)
    )
    crane = (float(masts.uniform(-half_span_m, half_span_m)) / 2, env.crane_distance_m, env.crane_height_m,
             env.crane_height_m)
    return Placement(tuple(buildings), tuple(trees), poles, crane)


def _tree_fits(env: EnvironmentParams, x: float, y: float, r: float, trees: list) -> bool:
    gap = CLEARANCE_M + r
    fx, fy = env.fountain_center_m
    if math.hypot(x - fx, y - fy) < env.fountain_radius_m + gap:
        return False
    (cx, cy), (cl, cw) = env.court_center_m, env.court_size_m
    if abs(x - cx) < cl / 2 + gap and abs(y - cy) < cw / 2 + gap:
        return False
    if abs(y - env.road_distance_m) < env.road_width_m / 2 + gap:
        return False
    return all(
        math.hypot(x - tx, y - ty) > r + th * CROWN_RADIUS_FRACTION + CLEARANCE_M for tx, ty, th in trees
    )


def environment_mesh(env: EnvironmentParams, T: np.ndarray, placement: Placement) -> TriMesh:
    """Ground, fountain, buildings (object id = building index) and trees, in world coordinates."""
    meshes = [ground_mesh(env, T), fountain_mesh(env, T)]
    yaw_site = math.atan2(T[1, 0], T[0, 0])
    for k, (x, y, w, d, h, yaw) in enumerate(placement.buildings):
        c = _to_world(T, np.array([[x, y, 0.0]]))[0]
        meshes.append(box_mesh(c, np.array([w, d, h]), yaw_site + yaw, Material.BUILDING, k))
    for x, y, h in placement.trees:
        c = _to_world(T, np.array([[x, y, 0.0]]))[0]
        meshes.append(
            cylinder_mesh(c, TRUNK_RADIUS_FRACTION * h, 0.0, CROWN_CENTER_FRACTION * h, Material.TRUNK)
        )
        meshes.append(
            sphere_mesh(c + [0.0, 0.0, CROWN_CENTER_FRACTION * h], CROWN_RADIUS_FRACTION * h, Material.CROWN)
        )
    meshes += [mast_mesh(T, x, y, h) for x, y, h in placement.poles]
    if placement.crane:
        meshes.append(crane_mesh(T, *placement.crane))
    return concat(meshes)


POLE_RADIUS_FRACTION = 0.015  # pole radius / pole height
POLE_ARM_FRACTION = 0.2  # length of a pole's arm toward the facade / pole height
CRANE_MAST_FRACTION = 0.04  # side of the crane's square mast / its height
CRANE_JIB_FRACTION = 0.025  # depth of the jib / the crane's height
CRANE_COUNTER_FRACTION = 0.3  # the counter-jib's length / the jib's


def mast_mesh(T: np.ndarray, x: float, y: float, h: float) -> TriMesh:
    """A pole at site (x, y), ``h`` tall, with an arm reaching toward the facade at its top (a lamp post)."""
    c = _to_world(T, np.array([[x, y, 0.0]]))[0]
    r = POLE_RADIUS_FRACTION * h
    yaw = math.atan2(T[1, 0], T[0, 0])
    arm_c = _to_world(T, np.array([[x, y - POLE_ARM_FRACTION * h / 2, h - 2 * r]]))[0]
    return concat([
        box_mesh(c, np.array([2 * r, 2 * r, h]), yaw, Material.MAST, 0),
        box_mesh(arm_c, np.array([2 * r, POLE_ARM_FRACTION * h, 2 * r]), yaw, Material.MAST, 0),
    ])


def crane_mesh(T: np.ndarray, x: float, y: float, h: float, jib: float) -> TriMesh:
    """A tower crane at site (x, y): a square mast ``h`` tall, a jib of length ``jib`` along site +x and a
    counter-jib along -x at its top, and a hoist cable hanging from the jib's far half."""
    yaw = math.atan2(T[1, 0], T[0, 0])
    m, d = CRANE_MAST_FRACTION * h, CRANE_JIB_FRACTION * h
    cw = CRANE_COUNTER_FRACTION * jib
    parts = [
        (x, y, 0.0, m, m, h + d),
        (x + (jib - cw) / 2, y, h, jib + cw, d, d),
        (x + 0.6 * jib, y, 0.35 * h, 0.2 * d, 0.2 * d, 0.65 * h),
    ]
    return concat([
        box_mesh(_to_world(T, np.array([[px, py, pz]]))[0], np.array([sx, sy, sz]), yaw, Material.MAST, 1)
        for px, py, pz, sx, sy, sz in parts
    ])
