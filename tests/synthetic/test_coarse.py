"""The coarse mesh and points look like photogrammetry of glass, by the declared amounts."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from facade_pipeline.synthetic.coarse import coarse_mesh, coarse_points, frame_flags
from facade_pipeline.synthetic.mesh import Material
from facade_pipeline.synthetic.scene import build_scene
from tests.synthetic.conftest import replace_in, tiny


@pytest.mark.parametrize("building", ["synthetic64", "synthetic64_curved"])
def test_coarse_mesh_deviates_on_glass_and_not_on_frames_by_the_declared_amounts(building):
    p = replace_in(tiny(building), "coarse", glass_bump_m=0.3, frame_noise_m=0.02, glass_hole_fraction=0.2)
    scene = build_scene(p)
    mesh, colors = coarse_mesh(scene)
    assert colors.shape == mesh.vertices.shape and np.all((colors >= 0) & (colors <= 1))
    vertices = mesh.vertices[np.unique(mesh.triangles[mesh.material != Material.WALL])]  # not the roofs
    g = scene.parts[0]
    s, z, h = g.surface_coords(vertices)
    frame = frame_flags(g, s, z)
    glass_dev = np.abs(h[~frame])
    frame_dev = np.abs(h[frame] - p.facade.frame_depth_m)
    assert np.isclose(glass_dev.max(), 0.3, rtol=1e-9)  # the declared largest deviation, reached
    assert np.median(glass_dev) > 0.05  # uneven over the whole glass, not at a few spikes
    assert frame_dev.max() <= 0.02 + 1e-9 and frame_dev.max() > 0.005
    # in 3D: coarse frame vertices are within the frame noise of the true frame surfaces
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(
        o3d.core.Tensor(scene.frames.vertices.astype(np.float32)),
        o3d.core.Tensor(scene.frames.triangles.astype(np.uint32)),
    )
    dist = rc.compute_distance(o3d.core.Tensor(vertices[frame].astype(np.float32))).numpy()
    sag = 0.0  # true curved frames are flat facets: add the chord's sagitta to the tolerance
    if g.part.kind == "cylindrical":
        arc = np.radians(p.facade.curve_max_facet_deg)  # no facet turns through more
        sag = (g.part.radius_m + p.facade.frame_depth_m) * (1 - np.cos(arc / 2))
    assert dist.max() <= 0.02 + sag + 1e-4


def test_holes_remove_the_declared_fraction_of_glass():
    p = replace_in(tiny(), "coarse", glass_hole_fraction=0.25)
    mesh, _ = coarse_mesh(build_scene(p))
    full, _ = coarse_mesh(build_scene(replace_in(p, "coarse", glass_hole_fraction=0.0)))
    kept = (mesh.material == Material.GLASS).sum() / (full.material == Material.GLASS).sum()
    assert abs(kept - 0.75) < 0.01
    assert (mesh.material == Material.FRAME).sum() == (full.material == Material.FRAME).sum()


def test_ghost_points_lie_behind_the_glass_as_mirror_images():
    p = replace_in(tiny(), "coarse", ghost_points_per_part=300, environment_points=4000)
    scene = build_scene(p)
    xyz, rgb = coarse_points(scene)
    g = scene.parts[0]
    s, z, h = g.surface_coords(xyz[: len(xyz) - p.coarse.environment_points])
    ghosts = h < -1e-6
    assert 0 < ghosts.sum() <= 300
    assert np.all(np.abs(s[ghosts]) < g.part.width_m / 2) and np.all(
        (z[ghosts] > 0) & (z[ghosts] < g.part.height_m)
    )
    env = xyz[-p.coarse.environment_points :]
    es, ez, eh = g.surface_coords(env)
    mirror = np.stack([es, ez, -eh], 1)
    ghost = np.stack([s[ghosts], z[ghosts], h[ghosts]], 1)
    d = np.linalg.norm(ghost[:, None, :] - mirror[None], axis=2).min(axis=1)
    assert d.max() < 1e-9  # every ghost is the mirror image of an environment point
    assert np.all((rgb >= 0) & (rgb <= 1))


def test_environment_points_fill_the_disc_and_stop_at_its_edge():
    """The radius cuts surfaces where it passes: a building it crosses keeps points up to its full height on
    the inside part, and no point lies outside."""
    base = tiny()
    scene = build_scene(base)
    env = scene.environment
    origin = scene.world_from_site[:3, 3][:2]
    # the building that spans the widest range of distances from the origin, and a radius through its middle
    spans = []
    for k in range(len(scene.placement.buildings)):
        v = env.vertices[env.triangles[env.object_id == k]].reshape(-1, 3)
        d = np.linalg.norm(v[:, :2] - origin, axis=1)
        spans.append((d.max() - d.min(), k, 0.5 * (d.min() + d.max()), v[:, 2].max() - v[:, 2].min()))
    _, k, radius, height = max(spans)
    p = replace_in(base, "coarse", environment_radius_m=float(radius), environment_points=20000)
    cut = build_scene(p)
    xyz, rgb = coarse_points(cut)
    pts = xyz[-p.coarse.environment_points :]
    assert len(pts) == 20000 and np.all((rgb >= 0) & (rgb <= 1))
    assert np.linalg.norm(pts[:, :2] - origin, axis=1).max() < radius
    # points on building k: inside its footprint (seen from above), above the ground
    bx, by, bw, bd, _, byaw = cut.placement.buildings[k]
    centre = (cut.world_from_site @ np.array([bx, by, 0.0, 1.0]))[:2]
    rel = pts[:, :2] - centre
    yaw = byaw + np.arctan2(cut.world_from_site[1, 0], cut.world_from_site[0, 0])
    u = rel @ np.array([np.cos(yaw), np.sin(yaw)])
    w = rel @ np.array([-np.sin(yaw), np.cos(yaw)])
    on = (np.abs(u) <= bw / 2 + 1e-6) & (np.abs(w) <= bd / 2 + 1e-6) & (pts[:, 2] > 0.5)
    assert on.sum() > 20
    assert pts[on, 2].max() > 0.95 * height  # the full height, not one triangle of each face


@pytest.mark.parametrize("building", ["synthetic64", "synthetic64_curved"])
def test_the_coarse_mesh_holds_the_roof_that_hides_glass_from_above(building):
    """Photogrammetry of a UAV survey reconstructs the roof behind the facade: the coarse mesh has the
    building body's upward faces at the facade's top, behind it, and a ray down from above the body meets
    the roof before anything else, as in the true scene."""
    scene = build_scene(tiny(building))
    mesh, _ = coarse_mesh(scene)
    roof = mesh.select(mesh.material == Material.WALL)
    g = scene.parts[0]
    v = roof.vertices[np.unique(roof.triangles)]
    s, z, h = g.surface_coords(v)
    assert len(roof.triangles) > 0
    assert np.allclose(z, g.part.height_m) and (h < 0).all()  # at the top, behind the glass
    t = roof.vertices[roof.triangles]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    assert (n[:, 2] > 0).all()  # facing up, as seen from the UAV views
    above = g.surface(np.array([0.0]), np.array([g.part.height_m + 5.0]), np.array([-1.0]))[0]
    for m in (mesh, scene.mesh):
        rc = o3d.t.geometry.RaycastingScene()
        rc.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                         o3d.core.Tensor(m.triangles.astype(np.uint32)))
        ray = o3d.core.Tensor(np.array([[*above, 0.0, 0.0, -1.0]], np.float32))
        hit = rc.cast_rays(ray)
        assert np.isclose(float(hit["t_hit"].numpy()[0]), 5.0, atol=1e-3)
        assert m.material[int(hit["primitive_ids"].numpy()[0])] == Material.WALL
