"""Panel surfaces, corner regularisation (misses, ghosts, one view only, cylinder rulings), the
authoritative mask and the mesh correction, on small hand-made scenes."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.meshing.correct import correct_mesh
from facade_pipeline.panels3d.grid import build_panel_set
from facade_pipeline.panels3d.model import PanelSet, PartSurface
from facade_pipeline.panels3d.observations import Quad, quad_mask, reconcile_with_mask
from tests.bake.test_raycast_bake import grid_plane
from tests.meshing.conftest import params_of

SURFACES = [
    PartSurface("planar", [1.0, 2.0, 0.0], [0.6, 0.8, 0.0]),
    PartSurface("cylindrical", [0.0, -20.0, 0.0], [0.0, 1.0, 0.0], 20.0, True, np.pi / 2),
    PartSurface("cylindrical", [0.0, 20.0, 0.0], [0.0, 1.0, 0.0], 20.0, False, -np.pi / 2),
]


@pytest.mark.parametrize("surf", SURFACES, ids=["planar", "convex", "concave"])
def test_surface_coordinates_round_trip_and_rays_meet_the_surface(surf):
    rng = np.random.default_rng(0)
    szh = np.stack([rng.uniform(-5, 5, 50), rng.uniform(0, 10, 50), rng.uniform(-0.3, 0.3, 50)], axis=1)
    assert np.allclose(surf.coords(surf.points(szh)), szh, atol=1e-9)
    on = surf.points(np.concatenate([szh[:, :2], np.zeros((50, 1))], axis=1))
    eye = on + 8.0 * surf.normals_at(on) + rng.normal(0, 1, (50, 3))  # cameras on the outside
    d = (on - eye) / np.linalg.norm(on - eye, axis=1, keepdims=True)
    t = surf.intersect(eye, d)
    assert np.allclose(eye + t[:, None] * d, on, atol=1e-7)
    right = surf.points(szh[:1] + [[0.1, 0, 0]]) - surf.points(szh[:1])
    assert (
        np.cross([0, 0, 1.0], surf.normals_at(surf.points(szh[:1]))[0]) @ right[0] > 0
    )  # s grows to the right
    if surf.convex or surf.kind == "planar":  # (inside a concave one, the far wall faces the ray)
        assert np.isinf(surf.intersect(eye[:1], -d[:1])).all()  # pointing away: no intersection


FW, DEPTH = 0.3, 0.12  # frame width and how far frames stand proud of the glass (m)


def facade(kind: str, n_cols: int = 3):
    """Truth of a 2 x ``n_cols`` panel facade (panels 2 x 1.8 m) on ``kind`` surface: its surface, the
    true panel corners (s, z) and a coarse mesh whose frames stand DEPTH proud of the glass."""
    surf = SURFACES[0] if kind == "planar" else SURFACES[1]
    s_lines = np.arange(n_cols + 1) * (2.0 + FW) - n_cols / 2 * (2.0 + FW)
    z_lines = np.arange(3) * (1.8 + FW) + 1.0
    corners = {
        (r, c): np.array(
            [
                [s_lines[c] + FW / 2, z_lines[r] + FW / 2],
                [s_lines[c + 1] - FW / 2, z_lines[r] + FW / 2],
                [s_lines[c + 1] - FW / 2, z_lines[r + 1] - FW / 2],
                [s_lines[c] + FW / 2, z_lines[r + 1] - FW / 2],
            ]
        )
        for r in range(2)
        for c in range(n_cols)
    }
    half = max(5.0, s_lines[-1] + 1.0)
    grid_s = np.linspace(-half, half, int(20 * half) + 1)
    s = np.unique(np.concatenate([grid_s, s_lines - FW / 2, s_lines + FW / 2]))
    z = np.unique(np.concatenate([np.linspace(0, 6, 61), z_lines - FW / 2, z_lines + FW / 2]))
    S, Z = np.meshgrid(s, z, indexing="ij")
    frame = (np.abs(S[..., None] - s_lines) <= FW / 2 + 1e-9).any(-1) | (
        np.abs(Z[..., None] - z_lines) <= FW / 2 + 1e-9
    ).any(-1)
    v = surf.points(np.stack([S.ravel(), Z.ravel(), np.where(frame, DEPTH, 0.0).ravel()], axis=1))
    idx = np.arange(S.size).reshape(S.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return surf, corners, v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def frontal_camera(surf: PartSurface, s: float, z: float, focal_px: float = 150.0) -> PinholeCamera:
    target = surf.points(np.array([[s, z, 0.0]]))[0]
    eye = target + 9.0 * surf.normals_at(target[None])[0]
    return PinholeCamera(intrinsics(focal_px, focal_px, 160, 120), look_at(eye, target), 320, 240)


def moved(cam: PinholeCamera, surf: PartSurface, ds: float, dz: float) -> PinholeCamera:
    """``cam`` with its centre moved by ``ds`` along the surface (planar) and ``dz`` up (m)."""
    t = ds * np.cross([0.0, 0.0, 1.0], surf.normal) + np.array([0.0, 0.0, dz])
    m = cam.cam_from_world.copy()
    m[:3, 3] -= m[:3, :3] @ t
    return PinholeCamera(cam.K, m, cam.width, cam.height)


def observe(surf, corners, cams, noise_px=0.2, seed=0):
    rng = np.random.default_rng(seed)
    quads, view = [], []
    for i, cam in enumerate(cams):
        for sz in corners.values():
            uv, _ = cam.project(surf.points(np.concatenate([sz, np.zeros((4, 1))], axis=1)))
            if (uv >= 1).all() and (uv[:, 0] < cam.width - 1).all() and (uv[:, 1] < cam.height - 1).all():
                quads.append(uv + rng.normal(0, noise_px, uv.shape))
                view.append(i)
    return quads, view


#: the building's panel pitch these scenes stand for, the unit of the lengths (the stage reads it from
#: segment_panels' survey): gcw_dev's surveyed pitch at full size, where the defaults are its lengths x 25
PITCH_M = 3.128


def cfg(**changes):
    return params_of("regularize_corners", **{"unit_m": PITCH_M, **changes})


def test_a_mask_with_its_frames_painted_over_is_reported_not_ignored():
    """All white: one region over every panel, far larger than they are together."""
    a = np.array([[5, 30], [25, 30], [25, 10], [5, 10]], float)
    b = np.array([[40, 30], [60, 30], [60, 10], [40, 10]], float)
    _, stats = reconcile_with_mask((Quad(a), Quad(b)), np.ones((60, 80), bool), 8, 0.6)
    assert stats["merged"] == 1
    # two panels whose mask regions touch (no frame between them in the mask) are not a merge
    touching = np.zeros((60, 80), bool)
    touching[10:30, 5:60] = True
    assert reconcile_with_mask((Quad(a), Quad(b)), touching, 8, 0.6)[1]["merged"] == 0


@pytest.mark.parametrize("kind", ["planar", "cylindrical"])
def test_panels_recovered_with_rulings_and_glass_depth(kind):
    surf, corners, v, f = facade(kind)
    cams = [frontal_camera(surf, -1.2, 3.0), frontal_camera(surf, 1.2, 3.0)]  # overlapping views
    quads, view = observe(surf, corners, cams)
    glass_points = surf.points(
        np.array([[s, z, 0.0] for (s, z) in np.random.default_rng(1).uniform([-3, 1.3], [3, 4.6], (400, 2))])
    )
    ps, m = build_panel_set(quads, [True] * len(quads), view, cams, MeshRaycaster(v, f), glass_points, cfg())
    assert ps.parts[0].kind == kind and m["n_panels"] == 6 and m["n_parts"] == 1
    for p in ps.panels:
        true = surf.points(np.concatenate([corners[(p.row, p.col)], np.zeros((4, 1))], axis=1))
        assert np.abs(p.corners - true).max() < 0.02  # glass depth found although the rays hit the frames
        assert np.allclose(p.corners[0, :2], p.corners[3, :2]) and np.allclose(
            p.corners[1, :2], p.corners[2, :2]
        )  # rulings
        assert p.normal @ surf.normals_at(p.center[None])[0] > 0.999
    assert max(p.n_views for p in ps.panels) == 2  # the middle column is seen twice and merged


def test_each_views_pose_error_is_taken_off_its_corners_not_voted_by_their_count():
    """Four views along a planar facade of six columns, each showing two or three of them, their poses
    each off by a few centimetres along the facade (no mean, no trend along the cameras: what an unbiased
    pose error looks like): a line seen mostly or only by one view would carry that view's error, but
    the views' shared lines measure their errors, and the panels land on the truth."""
    surf, corners, v, f = facade("planar", n_cols=6)
    true = [frontal_camera(surf, s, 2.2, focal_px=330.0) for s in (-4.8, -1.6, 1.6, 4.8)]
    quads, view = observe(surf, corners, true, noise_px=0.1)
    assert len(set(view)) == 4 and all(view.count(i) < len(corners) for i in range(4))  # partial views
    off = [(0.03, 0.04), (-0.03, -0.04), (-0.03, 0.04), (0.03, -0.04)]
    cams = [moved(c, surf, ds, dz) for c, (ds, dz) in zip(true, off, strict=True)]
    glass = surf.points(
        np.array([[s, z, 0.0] for (s, z) in np.random.default_rng(1).uniform([-7, 1.3], [7, 4.6], (800, 2))])
    )
    ps, m = build_panel_set(quads, [True] * len(quads), view, cams, MeshRaycaster(v, f), glass, cfg())
    assert m["n_panels"] == 12 and m["n_parts"] == 1
    for p in ps.panels:
        want = surf.points(np.concatenate([corners[(p.row, p.col)], np.zeros((4, 1))], axis=1))
        assert np.abs(p.corners - want).max() < 0.012  # without the offsets 2.5 cm off


def test_one_view_missed_and_ghost_rays_never_crash_and_are_counted():
    surf, corners, v, f = facade("planar")
    cam = frontal_camera(surf, 0.0, 3.0)
    quads, view = observe(surf, corners, [cam])
    # a hole under one corner (a miss) and a blob far in front of another (a ghost hit)
    hole_at = surf.points(np.array([[corners[(0, 0)][0, 0], corners[(0, 0)][0, 1], 0.0]]))[0]
    keep = np.linalg.norm(v[f].mean(axis=1) - hole_at, axis=1) > 0.25
    o, d = cam.pixel_rays(*quads[5][2:3].T)  # a small triangle across one corner ray, 3 m before the facade
    t_facade = surf.intersect(o, d)[0]
    e1 = np.cross(d[0], [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d[0], e1)
    gv = o[0] + d[0] * (t_facade - 3.0) + 0.2 * np.array([e1, -0.5 * e1 + 0.87 * e2, -0.5 * e1 - 0.87 * e2])
    v2, f2 = np.concatenate([v, gv]), np.concatenate([f[keep], [[len(v), len(v) + 1, len(v) + 2]]])
    ps, m = build_panel_set(
        quads,
        [True] * len(quads),
        view,
        [cam],
        MeshRaycaster(v2, f2),
        np.zeros((0, 3)),
        cfg(),
    )
    assert m["rays_rejected_missed"] >= 1 and m["rays_rejected_ghost"] >= 1
    assert m["n_panels"] == 6 and m["panels_seen_in_one_view"] == 6
    # without coarse points the glass depth comes from the coarse mesh inside the panels: on the glass,
    # behind the frame fronts that the corner rays hit
    assert np.allclose([surf.coords(p.corners)[:, 2].mean() for p in ps.panels], 0.0, atol=0.03)


def test_nothing_seen_gives_an_empty_panel_set():
    ps, m = build_panel_set([], [], [], [], MeshRaycaster(*grid_plane()), np.zeros((0, 3)), cfg())
    assert ps.panels == () and m["n_panels"] == 0


def test_mask_drops_refits_and_adds_panels():
    mask = np.zeros((60, 80), bool)
    mask[10:30, 5:25] = True  # panel A, corners agree
    mask[10:30, 40:60] = True  # panel B, corners are off
    mask[40:55, 5:25] = True  # region C, no corners
    a = np.array([[5, 30], [25, 30], [25, 10], [5, 10]], float)
    b = np.array([[40, 30], [50, 30], [50, 20], [40, 20]], float)
    d = np.array([[65, 50], [75, 50], [75, 40], [65, 40]], float)  # no mask pixel: dropped
    out, stats = reconcile_with_mask((Quad(a), Quad(b), Quad(d)), mask, 8, 0.6)
    assert stats == {"dropped": 1, "refit": 1, "added": 1, "merged": 0}
    assert np.allclose(out[0].corners_px, a)
    assert np.allclose(out[1].corners_px, [[40, 30], [60, 30], [60, 10], [40, 10]])
    assert np.allclose(out[2].corners_px, [[5, 55], [25, 55], [25, 40], [5, 40]])
    assert (
        quad_mask(out[2].corners_px, mask.shape)
        == (np.arange(60)[:, None] >= 40)
        & (np.arange(60)[:, None] < 55)
        & (np.arange(80) >= 5)
        & (np.arange(80) < 25)
    ).all()


@pytest.mark.parametrize("kind", ["planar", "cylindrical"])
def test_correction_replaces_the_cuboid_keeps_frames_and_faces_outward(kind):
    surf, corners, v, f = facade(kind)
    cams = [frontal_camera(surf, -1.2, 3.0), frontal_camera(surf, 1.2, 3.0)]
    quads, view = observe(surf, corners, cams, noise_px=0.0)
    pts = surf.points(np.c_[np.random.default_rng(2).uniform([-3, 1.3], [3, 4.6], (300, 2)), np.zeros(300)])
    ps, _ = build_panel_set(quads, [True] * len(quads), view, cams, MeshRaycaster(v, f), pts, cfg())
    p = params_of("correct_mesh")
    out = correct_mesh(v, f, ps, p.shrink_factor, p.cuboid_half_depth * PITCH_M, p.max_facet_deg)
    tri = out.vertices[out.triangles]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    c = tri.mean(axis=1)
    outward = np.einsum("ij,ij->i", n, surf.normals_at(c))
    assert (outward[out.is_panel] > 0).all()
    h = surf.coords(c)[:, 2]
    assert np.abs(h[out.is_panel]).max() < 0.02  # the panels lie on the glass (facets of the cylinder)
    kept = ~out.is_panel
    assert (
        out.n_removed > 0
        and (np.abs(h[kept] - DEPTH) < 1e-6).sum()
        > 0.9 * (np.abs(surf.coords(v[f].mean(1))[:, 2] - DEPTH) < 1e-6).sum()
    )
    szh = surf.coords(c[kept])
    inside = np.zeros(kept.sum(), bool)
    for p_ in ps.panels:
        q = surf.coords(p_.corners)
        ctr, half = q[:, :2].mean(0), 0.45 * np.ptp(q[:, :2], axis=0)
        inside |= (np.abs(szh[:, :2] - ctr) < half).all(axis=1)
    assert not inside.any()  # nothing coarse is left inside any panel's core


def test_panel_set_round_trip_and_damaged_file(tmp_path):
    surf, corners, v, f = facade("cylindrical")
    cams = [frontal_camera(surf, 0.0, 3.0)]
    quads, view = observe(surf, corners, cams)
    ps, _ = build_panel_set(
        quads, [True] * len(quads), view, cams, MeshRaycaster(v, f), np.zeros((0, 3)), cfg()
    )
    ps.save(tmp_path / "p.json")
    back = PanelSet.load(tmp_path / "p.json")
    assert [p.to_dict() for p in back.panels] == [p.to_dict() for p in ps.panels]
    assert back.parts[0].to_dict() == ps.parts[0].to_dict()
    (tmp_path / "bad.json").write_text('{"version": 1, "parts": []')
    with pytest.raises(InputError, match="bad.json"):
        PanelSet.load(tmp_path / "bad.json")
