"""The truth is true: panel corners, normals and depths in gt/ agree with the rendered scene."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from facade_pipeline.synthetic.mesh import Material
from facade_pipeline.synthetic.render import first_hits, truth_maps
from facade_pipeline.synthetic.scene import panels_description
from tests.synthetic.conftest import tiny

# (corner, neighbour along the row, neighbour along the column) in the order BL, BR, TR, TL
_CORNER_EDGES = ((0, 1, 3), (1, 0, 2), (2, 3, 1), (3, 2, 0))


def _corner_samples(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the projected corners uv [4, 2] of a panel: sample points 0.5 px inside the glass corner [4, 2]
    and sample points 0.5 px outside across either edge or both [12, 2]."""
    inside, outside = [], []
    for c, a, b in _CORNER_EDGES:
        e1 = (uv[a] - uv[c]) / np.linalg.norm(uv[a] - uv[c])
        e2 = (uv[b] - uv[c]) / np.linalg.norm(uv[b] - uv[c])
        inside.append(uv[c] + 0.5 * (e1 + e2))
        outside += [uv[c] - 0.5 * e1 + 0.5 * e2, uv[c] + 0.5 * e1 - 0.5 * e2, uv[c] - 0.5 * (e1 + e2)]
    return np.array(inside), np.array(outside)


@pytest.mark.parametrize("sim_name", ["planar_sim", "curved_sim"])
def test_projected_corners_land_on_the_glass_corners_within_half_a_pixel(sim_name, request):
    sim = request.getfixturevalue(sim_name)
    scene, checked = sim.scene, 0
    frontal = [v for v in sim.views if v.kind == "frontal"]
    assert frontal
    for view in frontal:
        part, rows, cols = view.block
        for pid, panel in enumerate(scene.panels):
            if panel.part != part or panel.row not in rows or panel.col not in cols:
                continue
            uv, _ = view.camera.project(panel.corners)
            inside, outside = _corner_samples(uv)
            o, d = view.camera.pixel_rays(*np.concatenate([inside, outside]).T)
            h = first_hits(sim.tracer, sim.arrays, o, d, "other")
            assert np.all(h.material[:4] == Material.GLASS) and np.all(h.object_id[:4] == pid)
            assert np.all(h.material[4:] == Material.FRAME), (view.name, pid, h.material[4:])
            checked += 1
    assert checked >= len(scene.panels)  # every panel is checked in some frontal view


def test_every_panel_is_inside_a_frontal_view_and_in_its_glass_mask(planar_sim):
    sim = planar_sim
    for pid, panel in enumerate(sim.scene.panels):
        seen = False
        for view in (v for v in sim.views if v.kind == "frontal"):
            uv, z = view.camera.project(panel.corners)
            if np.all(z > 0) and np.all(uv >= 0) and np.all(uv <= [view.camera.width, view.camera.height]):
                material = truth_maps(sim.scene, sim.tracer, sim.arrays, view.camera)[4]
                centre = np.floor(uv.mean(axis=0)).astype(int)
                seen |= material[centre[1], centre[0]] == Material.GLASS
        assert seen, f"panel {pid} is in no frontal view"


@pytest.mark.parametrize("sim_name", ["planar_sim", "curved_sim"])
def test_normal_and_depth_maps_equal_the_true_mesh(sim_name, request, tmp_path):
    from facade_pipeline.io.meshes import make_mesh, read_mesh, write_mesh

    sim = request.getfixturevalue(sim_name)
    write_mesh(tmp_path / "facade.ply", make_mesh(sim.scene.facade.vertices, sim.scene.facade.triangles))
    mesh = read_mesh(tmp_path / "facade.ply")  # what gt/facade_mesh.ply holds
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    tri_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    tri_n /= np.linalg.norm(tri_n, axis=1, keepdims=True)
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    for view in sim.views[:2] + sim.views[-1:]:
        normals, depth, valid, refl, material = truth_maps(sim.scene, sim.tracer, sim.arrays, view.camera)
        facade = (material == Material.GLASS) | (material == Material.FRAME)
        assert facade.sum() > 20
        o, d = view.camera.all_pixel_rays(1)
        ans = rc.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))
        prim = ans["primitive_ids"].numpy().reshape(facade.shape).astype(np.int64)
        n = tri_n[prim[facade]]
        n *= -np.sign(np.einsum("ij,ij->i", n, d.reshape(*facade.shape, 3)[facade]))[:, None]
        assert np.allclose(normals[facade], n, atol=1e-6)
        t = ans["t_hit"].numpy().reshape(facade.shape)[facade]
        z = t * (d.reshape(*facade.shape, 3)[facade] @ view.camera.cam_from_world[2, :3])
        assert np.allclose(depth[facade], z, rtol=1e-5)
        assert np.all(valid[facade]) and np.all(refl[material == Material.GLASS] > 0)
        assert np.all(refl[~(material == Material.GLASS)] == 0) and np.all(normals[~valid] == 0)


def test_panel_normals_and_corners_match_the_glass_mesh(planar_sim, curved_sim):
    for sim in (planar_sim, curved_sim):
        glass = sim.scene.glass
        tri_n = glass.normals
        for pid, panel in enumerate(sim.scene.panels):
            mine = glass.object_id == pid
            assert mine.any()
            verts = glass.vertices[glass.triangles[mine]].reshape(-1, 3)
            for corner in panel.corners:  # the corners are vertices of the panel's glass
                assert np.linalg.norm(verts - corner, axis=1).min() < 1e-9
            cos = tri_n[mine] @ panel.normal
            if sim.scene.parts[panel.part].part.kind == "planar":
                assert np.allclose(cos, 1.0, atol=1e-12)
            else:  # facets turn by at most half the panel's arc from the normal at its centre
                s0, s1, _, _ = sim.scene.parts[panel.part].panel_bounds(panel.row, panel.col)
                assert np.all(
                    cos >= np.cos(0.5 * (s1 - s0) / sim.scene.parts[panel.part].part.radius_m) - 1e-12
                )


def test_curved_glass_is_the_cylinder_to_within_its_facet_angle(curved_sim):
    """Every flat facet of the curved glass is a chord of the cylinder that turns through at most
    ``curve_max_facet_deg``: its normal is the cylinder's at the middle of its arc (the renderer's normals
    and the truth's are within half the facet angle of the cylinder's)."""
    scene = curved_sim.scene
    geom = next(g for g in scene.parts if g.part.kind == "cylindrical")
    glass = scene.glass
    mine = np.array([scene.panels[i].part == geom.index for i in glass.object_id])
    assert mine.any()
    corners = glass.vertices[glass.triangles[mine]]  # [F, 3, 3] world
    local = (corners - geom.world_from_facade[:3, 3]) @ geom.world_from_facade[:3, :3]
    # facade frame: the cylinder's axis stands at (0, -R) in x-y and x = -(R + h) sin(s / R)
    phi = np.arctan2(-local[..., 0], local[..., 1] + geom.part.radius_m)  # [F, 3]
    turn = np.degrees(phi.max(axis=1) - phi.min(axis=1))
    max_deg = tiny("synthetic64_curved").facade.curve_max_facet_deg  # the params curved_sim was built from
    assert turn.max() <= max_deg + 1e-9 and turn.max() > 0.5 * max_deg
    middle = geom.normal(0.5 * (phi.max(axis=1) + phi.min(axis=1)) * geom.part.radius_m)
    assert np.allclose(np.sum(glass.normals[mine] * middle, axis=1), 1.0, atol=1e-9)


def test_panels_json_orders_rows_bottom_up_and_columns_left_to_right(planar_sim, curved_sim):
    for sim in (planar_sim, curved_sim):
        panels = panels_description(sim.scene)["panels"]
        for pn in panels:
            c = np.array(pn["corners"])
            n = np.array(pn["normal"])
            right = np.cross([0.0, 0.0, 1.0], n)  # to the right of a viewer outside, facing -n
            assert (c[1] - c[0]) @ right > 0 and (c[2] - c[3]) @ right > 0  # BL -> BR goes right
            assert c[3, 2] > c[0, 2] and c[2, 2] > c[1, 2]  # top above bottom
        by = {(p["row"], p["col"]): np.array(p["corners"]).mean(axis=0) for p in panels}
        n0 = np.array(panels[0]["normal"])
        assert by[(1, 0)][2] > by[(0, 0)][2]
        assert (by[(0, 1)] - by[(0, 0)]) @ np.cross([0.0, 0.0, 1.0], n0) > 0
