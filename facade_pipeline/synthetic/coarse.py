"""What photogrammetry makes of a glass facade (the paper's Fig. 2): raw/coarse_mesh.ply and
raw/coarse_points.ply. The mesh also holds the roofs of the building body behind the facade (``roofs``),
which a UAV survey sees from above and which hide glass from the high views.

The coarse mesh of a part is a height field h(s, z) over its surface coordinates (see ``facade``): the
frames' front (h = frame_depth_m) and the glass (h = 0), on a grid that contains every frame edge, so steps
become steep slopes one grid cell wide. With "coarse_mesh_distortion" the glass gets smooth bumps whose
largest |h| is exactly ``glass_bump_m`` and loses ``glass_hole_fraction`` of its triangles as blob-shaped
holes; frames move by at most ``frame_noise_m``. The point cloud samples the same surfaces; with
"coarse_points_glass_artifacts" glass points are thinned to ``glass_points_keep_fraction`` and ghost points
(environment points mirrored through the glass surface, i.e. the depth photogrammetry finds for a
reflection) appear behind the glass.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facade_pipeline.synthetic.facade import PartGeometry
from facade_pipeline.synthetic.mesh import Material, TriMesh
from facade_pipeline.synthetic.noise import fbm, rng_for, value_noise
from facade_pipeline.synthetic.scene import Scene
from facade_pipeline.synthetic.textures import albedo, lighting, sky

EDGE_MERGE_M = 1e-6  # grid lines closer than this are merged (m)
GHOST_MAX_RADIUS_FRACTION = 0.9  # ghosts of a cylindrical part stay within this fraction of its radius (-)
ROOF_MIN_UP = 0.9  # a body triangle whose normal is within about 25 deg of up is roof (-)


@dataclass(frozen=True, eq=False)
class HeightField:
    """A part's coarse surface: grid s [I], z [J] (m), heights h [I, J] (m), frame flags [I, J]."""

    s: np.ndarray
    z: np.ndarray
    h: np.ndarray
    is_frame: np.ndarray


def frame_flags(g: PartGeometry, s: np.ndarray, z: np.ndarray) -> np.ndarray:
    """True where surface coordinates (s, z) (broadcast) lie on a mullion or transom (edges included)."""
    hw = g.frame_width_m / 2 + EDGE_MERGE_M
    on_m = (np.abs(np.asarray(s)[..., None] - g.s_lines) <= hw).any(-1)
    on_t = (np.abs(np.asarray(z)[..., None] - g.z_lines) <= hw).any(-1)
    return on_m | on_t


def _grid(lines: np.ndarray, half: float, lo: float, hi: float, step: float) -> np.ndarray:
    edges = np.concatenate([lines - half, lines + half])
    n = max(1, int(np.ceil((hi - lo) / step)))
    g = np.unique(np.clip(np.concatenate([np.linspace(lo, hi, n + 1), edges]), lo, hi))
    return g[np.concatenate([[True], np.diff(g) > EDGE_MERGE_M])]


def height_field(g: PartGeometry, scene: Scene) -> HeightField:
    """The coarse height field of part ``g`` (true heights, plus the distortion if declared)."""
    p = scene.params
    L, H, fw = g.part.width_m, g.part.height_m, g.frame_width_m
    s = _grid(g.s_lines, fw / 2, -L / 2, L / 2, p.coarse.mesh_resolution_m)
    z = _grid(g.z_lines, fw / 2, 0.0, H, p.coarse.mesh_resolution_m)
    S, Z = np.meshgrid(s, z, indexing="ij")
    frame = frame_flags(g, S, Z)
    h = np.where(frame, p.facade.frame_depth_m, 0.0)
    if p.has("coarse_mesh_distortion"):
        sc = p.coarse.glass_bump_scale_m
        bump = 2.0 * fbm(S / sc, Z / sc, p.seed + 101 * g.index, 3) - 1.0
        jitter = 2.0 * value_noise(S / sc, Z / sc, p.seed + 101 * g.index + 17) - 1.0
        h = h + np.where(
            frame,
            p.coarse.frame_noise_m * _unit_max(jitter, frame),
            p.coarse.glass_bump_m * _unit_max(bump, ~frame),
        )
    return HeightField(s, z, h, frame)


def _unit_max(x: np.ndarray, where: np.ndarray) -> np.ndarray:
    """x scaled so that max |x| over ``where`` is 1 (unchanged if that max is 0)."""
    m = np.abs(x[where]).max() if where.any() else 0.0
    return x / m if m > 0 else x


def height_field_mesh(g: PartGeometry, hf: HeightField, scene: Scene) -> tuple[TriMesh, np.ndarray]:
    """World mesh of a height field (glass triangles: all three vertices on glass; object id = part index)
    and vertex colours [V, 3]. Holes are cut here when "coarse_mesh_distortion" is declared."""
    p = scene.params
    I, J = len(hf.s), len(hf.z)
    S, Z = np.meshgrid(hf.s, hf.z, indexing="ij")
    verts = g.surface(S, Z, hf.h).reshape(-1, 3)
    idx = np.arange(I * J).reshape(I, J)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    frame_v = hf.is_frame.ravel()
    glass_t = ~frame_v[tris].any(axis=1)
    keep = np.ones(len(tris), bool)
    if p.has("coarse_mesh_distortion") and p.coarse.glass_hole_fraction > 0 and glass_t.any():
        cs, cz = S.ravel()[tris].mean(1), Z.ravel()[tris].mean(1)
        sc = p.coarse.glass_bump_scale_m
        noise = value_noise(cs / sc, cz / sc, p.seed + 101 * g.index + 29)
        keep = ~glass_t | (noise < np.quantile(noise[glass_t], 1.0 - p.coarse.glass_hole_fraction))
    mat = np.where(glass_t, Material.GLASS, Material.FRAME).astype(np.uint8)
    mesh = TriMesh(verts, tris.astype(np.int64), mat, np.full(len(tris), g.index, np.int32)).select(keep)
    colors = np.where(frame_v[:, None], np.asarray(p.facade.frame_color), _glass_colour(g, S.ravel(), scene))
    return mesh, np.clip(colors, 0.0, 1.0)


def _glass_colour(g: PartGeometry, s: np.ndarray, scene: Scene) -> np.ndarray:
    """What a photogrammetric texture shows on glass: the interior mixed with the reflected sky."""
    p = scene.params
    n = g.normal(s)
    refl = p.facade.glass_reflectivity
    D = np.asarray(p.facade.glass_tint) * np.asarray(p.facade.interior_color)
    return (1 - refl) * D + refl * np.asarray(p.facade.glass_f0) * sky(n, p.environment)


def roofs(scene: Scene) -> TriMesh:
    """The roofs of the building body behind the facade: its upward-facing triangles. Photogrammetry of a
    UAV survey reconstructs a roof, matte and seen from above, as well as any wall; the body's other faces
    are hidden behind the facade or seen by no view."""
    b = scene.body
    t = b.vertices[b.triangles]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    up = n[:, 2] > ROOF_MIN_UP * np.linalg.norm(n, axis=1)
    return b.select(up)


def coarse_mesh(scene: Scene) -> tuple[TriMesh, np.ndarray]:
    """The coarse mesh of every part's facade and of the roofs behind it (vertices compacted) and its
    vertex colours [V, 3]."""
    meshes, colors = [], []
    offset = 0
    roof = roofs(scene)
    pieces = [height_field_mesh(g, height_field(g, scene), scene) for g in scene.parts]
    pieces.append((roof, np.tile(np.asarray(scene.params.facade.wall_color, float), (len(roof.vertices), 1))))
    for m, c in pieces:
        used, inverse = np.unique(m.triangles, return_inverse=True)
        meshes.append(TriMesh(m.vertices[used], inverse.reshape(-1, 3) + offset, m.material, m.object_id))
        colors.append(c[used])
        offset += len(used)
    return TriMesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.triangles for m in meshes]),
        np.concatenate([m.material for m in meshes]),
        np.concatenate([m.object_id for m in meshes]),
    ), np.concatenate(colors)


def facade_points(g: PartGeometry, scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] and colours [N, 3] sampled uniformly over a part's front surfaces (frame fronts and
    glass) at ``points_per_m2``; with "coarse_points_glass_artifacts" glass keeps only a fraction."""
    p = scene.params
    n = int(round(p.coarse.points_per_m2 * g.part.width_m * g.part.height_m))
    s = rng.uniform(-g.part.width_m / 2, g.part.width_m / 2, n)
    z = rng.uniform(0.0, g.part.height_m, n)
    keep_draw = rng.uniform(size=n)  # drawn always, so that switching the effect off changes nothing else
    frame = frame_flags(g, s, z)
    keep = np.ones(n, bool)
    if p.has("coarse_points_glass_artifacts"):
        keep = frame | (keep_draw < p.coarse.glass_points_keep_fraction)
    h = np.where(frame, p.facade.frame_depth_m, 0.0)
    xyz = g.surface(s, z, h)
    rgb = np.where(frame[:, None], np.asarray(p.facade.frame_color), _glass_colour(g, s, scene))
    return xyz[keep], rgb[keep]


def environment_samples(scene: Scene, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points [N, 3] on the environment within ``environment_radius_m`` of the site origin
    (horizontally), uniform by area over the part of the surfaces inside that radius, and their lit albedo
    [N, 3]. The radius cuts surfaces where it passes, not whole triangles: a building's face, two large
    triangles, keeps its full height up to the cut (a test by triangle centroids kept one triangle of such a
    face, and so a building half as tall, or none of it)."""
    p = scene.params
    env = scene.environment
    origin = scene.world_from_site[:3, 3][:2]
    radius = p.coarse.environment_radius_m
    # a triangle reaches inside the disc when an edge passes within the radius or the triangle covers the
    # origin (seen from above)
    c = env.vertices[env.triangles][:, :, :2] - origin  # [F, 3, 2] corners, seen from above
    e = np.roll(c, -1, axis=1) - c  # edges
    s = np.clip(-(c * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-12), 0.0, 1.0)
    edge_dist = np.linalg.norm(c + s[..., None] * e, axis=2).min(axis=1)  # [F]
    side = c[..., 0] * e[..., 1] - c[..., 1] * e[..., 0]  # [F, 3]: the origin's side of each edge
    covers = (side >= 0).all(axis=1) | (side <= 0).all(axis=1)
    near = (edge_dist < radius) | covers
    if count <= 0 or not near.any():
        return np.zeros((0, 3)), np.zeros((0, 3))
    ids = np.flatnonzero(near)
    w = env.areas[ids]
    xyz = np.zeros((0, 3))
    tri = np.zeros(0, np.int64)
    for _ in range(1000):  # draw by area over the triangles that reach in, keep the points inside
        if len(xyz) >= count:
            break
        n = 2 * (count - len(xyz)) + 16
        t = ids[rng.choice(len(ids), size=n, p=w / w.sum())]
        u, v = rng.uniform(size=(2, n))
        flip = u + v > 1
        u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
        V = env.vertices[env.triangles[t]]
        q = V[:, 0] + u[:, None] * (V[:, 1] - V[:, 0]) + v[:, None] * (V[:, 2] - V[:, 0])
        inside = np.linalg.norm(q[:, :2] - origin, axis=1) < radius
        xyz, tri = np.concatenate([xyz, q[inside]]), np.concatenate([tri, t[inside]])
    if len(xyz) < count:
        raise RuntimeError(
            f"could not draw {count} environment points within {radius} m of the site origin ({len(xyz)} "
            "after 1000 rounds): the surfaces that reach inside cover almost none of it"
        )
    xyz, tri = xyz[:count], tri[:count]
    normals = env.normals[tri]
    a = albedo(
        env.material[tri],
        xyz,
        normals,
        env.object_id[tri],
        scene.site_xy(xyz),
        p.environment,
        p.facade,
        p.seed,
    )
    return xyz, np.clip(a * lighting(normals, p.environment), 0.0, 1.0)


def ghost_points(
    g: PartGeometry, env_xyz: np.ndarray, env_rgb: np.ndarray, scene: Scene, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``ghost_points_per_part`` environment points mirrored through the part's glass surface, in
    surface coordinates (s, z, h) -> (s, z, -h), kept where they fall behind the part's glass."""
    s, z, h = g.surface_coords(env_xyz)
    ok = (h > 0) & (np.abs(s) < g.part.width_m / 2) & (z > 0) & (z < g.part.height_m)
    if g.part.kind == "cylindrical":
        ok &= h < GHOST_MAX_RADIUS_FRACTION * g.part.radius_m
    ids = np.flatnonzero(ok)
    ids = rng.permutation(ids)[: scene.params.coarse.ghost_points_per_part]
    return g.surface(s[ids], z[ids], -h[ids]), env_rgb[ids]


def coarse_points(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The coarse point cloud: xyz [N, 3] (world, m) and colours [N, 3] in [0, 1]."""
    p = scene.params
    xyz, rgb = [], []
    env_xyz, env_rgb = environment_samples(scene, p.coarse.environment_points, rng_for(p.seed, "env_points"))
    for g in scene.parts:
        a, b = facade_points(g, scene, rng_for(p.seed, "facade_points", g.index))
        xyz.append(a)
        rgb.append(b)
        if p.has("coarse_points_glass_artifacts"):
            a, b = ghost_points(g, env_xyz, env_rgb, scene, rng_for(p.seed, "ghost_points", g.index))
            xyz.append(a)
            rgb.append(b)
    xyz.append(env_xyz)
    rgb.append(env_rgb)
    return np.concatenate(xyz), np.concatenate(rgb)
