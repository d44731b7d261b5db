"""Ray-cast rendering of a synthetic scene with open3d's RaycastingScene.

Primary rays go through ``supersample`` x ``supersample`` sub-pixel positions and are averaged. On glass the
colour is the deferred shading of the paper (Eq. 7-8):

    I = (1 - refl) D + refl F R,    F = F0 + (1 - F0) (1 - cos theta)^5  (Schlick; F = F0 without "fresnel")

with theta between the normal n and the direction to the camera w_o, and R the radiance along the mirror
direction w_r = 2 (w_o . n) n - w_o: the scene traced one bounce with "near_field_reflection", else the sky
alone (no secondary ray is cast). Other surfaces are diffuse: albedo * (ambient + sun Lambert term), no
shadows; a room behind an unglazed unit is lit only by what it sees through its opening. Rays
are processed in chunks of ``chunk_rays``, so memory depends on the chunk and image size only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.synthetic.cameras import Lens
from facade_pipeline.synthetic.mesh import Material, TriMesh
from facade_pipeline.synthetic.scene import Scene
from facade_pipeline.synthetic.textures import albedo, lighting, room_radiance, sky


@dataclass
class RayCounts:
    """Rays cast so far, by purpose."""

    primary: int = 0
    secondary: int = 0
    ground_truth: int = 0
    other: int = 0


class Tracer:
    """Closest-hit ray casting against one triangle mesh; counts every ray it casts."""

    def __init__(self, mesh: TriMesh):
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
        )
        self.counts = RayCounts()

    def cast(self, origins: np.ndarray, dirs: np.ndarray, purpose: str) -> tuple[np.ndarray, np.ndarray]:
        """Closest hits of rays [N, 3] + [N, 3] (unit dirs, world): distance t [N] (inf on a miss) and
        triangle id [N] int64 (-1 on a miss)."""
        setattr(self.counts, purpose, getattr(self.counts, purpose) + len(origins))
        if len(origins) == 0:
            return np.zeros(0), np.zeros(0, np.int64)
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        ans = self._scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        miss = ~np.isfinite(t)
        prim[miss] = -1
        return t, prim


@dataclass(frozen=True, eq=False)
class SceneArrays:
    """Per-triangle lookups of a scene: material [F], object id [F], outward unit normals [F, 3]."""

    material: np.ndarray
    object_id: np.ndarray
    normals: np.ndarray

    @classmethod
    def of(cls, scene: Scene) -> SceneArrays:
        return cls(scene.mesh.material, scene.mesh.object_id, scene.mesh.normals)


@dataclass
class Hits:
    """First hits of N rays: points [N, 3], normals facing the ray's origin [N, 3], material [N]
    (NONE on a miss), object ids [N], distances t [N] (0 on a miss)."""

    points: np.ndarray
    normals: np.ndarray
    material: np.ndarray
    object_id: np.ndarray
    t: np.ndarray
    prim: np.ndarray = field(repr=False)


def first_hits(tracer: Tracer, arrays: SceneArrays, o: np.ndarray, d: np.ndarray, purpose: str) -> Hits:
    """Cast rays and look up what they hit."""
    t, prim = tracer.cast(o, d, purpose)
    hit = prim >= 0
    safe = np.where(hit, prim, 0)
    n = arrays.normals[safe]
    n = np.where((np.einsum("ij,ij->i", n, d) > 0)[:, None], -n, n)
    t = np.where(hit, t, 0.0)
    return Hits(
        o + t[:, None] * d,
        np.where(hit[:, None], n, 0.0),
        np.where(hit, arrays.material[safe], Material.NONE).astype(np.uint8),
        np.where(hit, arrays.object_id[safe], -1),
        t,
        prim,
    )


def diffuse_radiance(scene: Scene, hits: Hits, d: np.ndarray) -> np.ndarray:
    """Radiance [N, 3] of hits seen along d [N, 3] without tracing further: the sky on misses, lit albedo on
    diffuse surfaces (rooms lit through their openings), and on glass (1 - refl) D + refl F0 sky(w_r) (the
    bounce budget is spent)."""
    p = scene.params
    hit = hits.material != Material.NONE
    out = np.empty((len(d), 3))
    out[~hit] = sky(d[~hit], p.environment)
    glass = hits.material == Material.GLASS
    room = hits.material == Material.INTERIOR
    if room.any():
        out[room] = room_radiance(hits.points[room], hits.normals[room], hits.object_id[room], scene.rooms,
                                  p.environment, p.seed)
    diff = hit & ~glass & ~room
    if diff.any():
        a = albedo(
            hits.material[diff],
            hits.points[diff],
            hits.normals[diff],
            hits.object_id[diff],
            scene.site_xy(hits.points[diff]),
            p.environment,
            p.facade,
            p.seed,
        )
        out[diff] = a * lighting(hits.normals[diff], p.environment)
    if glass.any():
        n, dg = hits.normals[glass], d[glass]
        wr = dg - 2.0 * np.einsum("ij,ij->i", dg, n)[:, None] * n
        refl = p.facade.glass_reflectivity
        out[glass] = (1 - refl) * scene.panel_diffuse[hits.object_id[glass]] + refl * np.asarray(
            p.facade.glass_f0
        ) * sky(wr, p.environment)
    return out


def schlick(f0: np.ndarray, cos_theta: np.ndarray) -> np.ndarray:
    """Schlick's Fresnel (Eq. 8): F = F0 + (1 - F0) (1 - cos theta)^5; f0 [3], cos_theta [N] -> [N, 3]."""
    f0 = np.asarray(f0, dtype=np.float64)
    return f0 + (1.0 - f0) * (1.0 - np.clip(cos_theta, 0.0, 1.0))[:, None] ** 5


def glass_radiance(
    scene: Scene, tracer: Tracer, arrays: SceneArrays, hits: Hits, d: np.ndarray
) -> np.ndarray:
    """Eq. 7 on glass hits (all rows of ``hits`` are glass): I = (1 - refl) D + refl F R."""
    p = scene.params
    n = hits.normals
    w_o = -d
    cos = np.einsum("ij,ij->i", w_o, n)
    w_r = 2.0 * cos[:, None] * n - w_o
    if p.has("near_field_reflection"):
        o2 = hits.points + p.render.ray_offset_m * n
        R = diffuse_radiance(scene, first_hits(tracer, arrays, o2, w_r, "secondary"), w_r)
    else:
        R = sky(w_r, p.environment)
    f0 = np.asarray(p.facade.glass_f0)
    F = schlick(f0, cos) if p.has("fresnel") else np.broadcast_to(f0, R.shape)
    refl = p.facade.glass_reflectivity
    return (1.0 - refl) * scene.panel_diffuse[hits.object_id] + refl * F * R


def shade(scene: Scene, tracer: Tracer, arrays: SceneArrays, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Radiance [N, 3] along primary rays o, d [N, 3]."""
    hits = first_hits(tracer, arrays, o, d, "primary")
    out = diffuse_radiance(scene, hits, d)
    glass = hits.material == Material.GLASS
    if glass.any():
        sub = Hits(
            hits.points[glass],
            hits.normals[glass],
            hits.material[glass],
            hits.object_id[glass],
            hits.t[glass],
            hits.prim[glass],
        )
        out[glass] = glass_radiance(scene, tracer, arrays, sub, d[glass])
    return out


@dataclass(frozen=True, eq=False)
class ViewRender:
    """One rendered view. ``image`` [H, W, 3] float32 linear radiance (not clipped); maps from the ray
    through each pixel centre: ``normals`` [H, W, 3] world, facing the camera (0 where invalid), ``depth``
    [H, W] along the camera z axis (m, 0 where invalid), ``valid`` [H, W] bool, ``reflectivity`` [H, W],
    ``material`` [H, W] uint8 (``Material``)."""

    image: np.ndarray
    normals: np.ndarray
    depth: np.ndarray
    valid: np.ndarray
    reflectivity: np.ndarray
    material: np.ndarray


def render_view(
    scene: Scene,
    tracer: Tracer,
    arrays: SceneArrays,
    camera: PinholeCamera,
    supersample: int | None = None,
    lens: Lens | None = None,
) -> ViewRender:
    """Render ``camera``'s image (supersampled ``supersample`` per side, default ``render.supersample``;
    chunked) and its ground-truth maps; with a ``lens``, the image is taken through it (its size) and the
    maps stay ``camera``'s."""
    r = scene.params.render
    ss = r.supersample if supersample is None else supersample
    shot = camera if lens is None else lens.camera
    H, W, S = shot.height, shot.width, ss * ss
    o, d = camera.all_pixel_rays(ss) if lens is None else lens.pixel_rays(ss)
    rgb = np.empty((len(o), 3), np.float32)
    for a in range(0, len(o), r.chunk_rays):
        rgb[a : a + r.chunk_rays] = shade(
            scene, tracer, arrays, o[a : a + r.chunk_rays], d[a : a + r.chunk_rays]
        )
    image = rgb.reshape(H, W, S, 3).mean(axis=2, dtype=np.float64).astype(np.float32)
    return ViewRender(image, *truth_maps(scene, tracer, arrays, camera))


def truth_maps(
    scene: Scene, tracer: Tracer, arrays: SceneArrays, camera: PinholeCamera
) -> tuple[np.ndarray, ...]:
    """(normals, depth, valid, reflectivity, material) from the rays through the pixel centres."""
    H, W = camera.height, camera.width
    o, d = camera.all_pixel_rays(1)
    z_axis = camera.forward
    normals, depth = np.zeros((H * W, 3)), np.zeros(H * W)
    material = np.zeros(H * W, np.uint8)
    step = scene.params.render.chunk_rays
    for a in range(0, len(o), step):
        h = first_hits(tracer, arrays, o[a : a + step], d[a : a + step], "ground_truth")
        normals[a : a + step], material[a : a + step] = h.normals, h.material
        depth[a : a + step] = h.t * (d[a : a + step] @ z_axis)
    valid = material != Material.NONE
    refl = np.where(material == Material.GLASS, scene.params.facade.glass_reflectivity, 0.0)
    return (
        normals.reshape(H, W, 3).astype(np.float32),
        depth.reshape(H, W).astype(np.float32),
        valid.reshape(H, W),
        refl.reshape(H, W).astype(np.float32),
        material.reshape(H, W),
    )
