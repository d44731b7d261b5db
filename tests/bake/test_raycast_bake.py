"""Ray casting and baking: holes, degenerate triangles, cameras inside or behind the mesh, normals wound
away from the camera, misses, chunking, masks, and the bit-exact EXR round trip."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.bake.maps import bake_view, panel_masks
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.geometry.raycast import MeshRaycaster, grazing
from facade_pipeline.io.exr import read_exr, write_exr
from facade_pipeline.panels3d.model import Panel, PanelSet, PartSurface


def grid_plane(n: int = 8, size: float = 4.0, y: float = 0.0):
    """A square in the plane y = ``y`` (x, z in [-size/2, size/2]) wound with its normal along -y."""
    s = np.linspace(-size / 2, size / 2, n + 1)
    X, Z = np.meshgrid(s, s, indexing="ij")
    v = np.stack([X.ravel(), np.full(X.size, y), Z.ravel()], axis=1)
    idx = np.arange(v.shape[0]).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def cube(half: float = 1.0):
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)], float)
    f = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    return v, f


def camera(eye, target, w: int = 40, h: int = 30, f: float = 30.0) -> PinholeCamera:
    return PinholeCamera(
        intrinsics(f, f, w / 2, h / 2), look_at(np.array(eye, float), np.array(target, float)), w, h
    )


def check_facing(baked, cam: PinholeCamera):
    assert np.isfinite(baked.normal).all() and np.isfinite(baked.depth).all()
    _, d = cam.all_pixel_rays()
    dots = np.sum(baked.normal.reshape(-1, 3) * d, axis=1)
    assert (dots[baked.valid.ravel()] < 0).all()
    assert (baked.normal[~baked.valid] == 0).all() and (baked.depth[~baked.valid] == 0).all()


@pytest.mark.parametrize("where", ["inside", "outside"])
def test_camera_inside_or_outside_a_closed_mesh_sees_normals_facing_it(where):
    rc = MeshRaycaster(*cube())
    cam = camera([0.1, -0.2, 0.05], [0.1, 1.0, 0.0]) if where == "inside" else camera([0, -5, 0.3], [0, 0, 0])
    baked = bake_view(rc, cam, chunk_rays=97)
    if where == "inside":
        assert baked.valid.all()  # every ray hits a wall from inside
    check_facing(baked, cam)


@pytest.mark.parametrize("wound_toward_camera", [True, False])
def test_camera_behind_the_mesh_and_normals_wound_away_face_the_camera(wound_toward_camera):
    v, f = grid_plane()
    if not wound_toward_camera:
        f = f[:, ::-1]
    cam = camera([0.3, 6.0, 0.2], [0.3, 0.0, 0.2])  # on the +y side, behind a plane wound toward -y
    baked = bake_view(MeshRaycaster(v, f), cam, chunk_rays=1000)
    assert baked.valid.any()
    check_facing(baked, cam)
    assert np.allclose(baked.normal[baked.valid], [0.0, 1.0, 0.0], atol=1e-6)
    assert np.allclose(baked.depth[baked.valid], 6.0, atol=1e-4)  # depth along the camera axis


def test_holes_degenerate_and_nonfinite_triangles_never_crash():
    v, f = grid_plane(n=4)
    v = np.concatenate([v, [[np.nan, 0.0, 0.0]]])
    bad = np.array(
        [[0, 0, 1], [0, 1, 2], [0, 1, len(v) - 1], [0, 1, len(v) + 5]]
    )  # repeated, collinear, NaN, out of range
    f = np.concatenate([f[4:], bad])  # the first triangles removed: a hole
    rc = MeshRaycaster(v, f)
    assert rc.n_dropped == 4
    cam = camera([0.0, -5.0, 0.0], [0, 0, 0])
    baked = bake_view(rc, cam, chunk_rays=64)
    assert baked.valid.any() and not baked.valid.all()  # the hole and the sky are not valid
    check_facing(baked, cam)
    o, d = cam.all_pixel_rays()
    hits = rc.cast(o, d)
    assert set(np.unique(hits.prim[hits.hit])) <= set(range(len(f) - 4))  # ids of the caller's mesh
    assert np.isinf(hits.t[~hits.hit]).all()


def test_empty_mesh_and_no_rays():
    rc = MeshRaycaster(np.zeros((3, 3)), np.array([[0, 1, 2]]))  # a single zero-area triangle
    assert rc.empty
    baked = bake_view(rc, camera([0, -5, 0], [0, 0, 0]), chunk_rays=100)
    assert not baked.valid.any() and (baked.normal == 0).all()
    assert rc.cast(np.zeros((0, 3)), np.zeros((0, 3))).t.shape == (0,)


def test_grazing_rays_are_flagged():
    n = np.array([[0.0, 1.0, 0.0]] * 2)
    d = np.array([[0.0, -1.0, 0.0], [np.cos(np.radians(1)), -np.sin(np.radians(1)), 0.0]])
    assert grazing(d, n, 85.0).tolist() == [False, True]


def test_chunking_does_not_change_the_maps():
    rc = MeshRaycaster(*cube())
    cam = camera([2.0, -4.0, 1.5], [0, 0, 0], w=37, h=23)
    a, b = bake_view(rc, cam, chunk_rays=37 * 23), bake_view(rc, cam, chunk_rays=5)
    # bands shift the principal point, so float32 directions may differ in the last bit
    assert np.array_equal(a.valid, b.valid)
    assert np.allclose(a.normal, b.normal, atol=1e-6) and np.allclose(a.depth, b.depth, rtol=1e-5)


def test_depth_and_normal_agree_with_a_slow_reference():
    v, f = grid_plane(n=3, size=10.0)
    cam = camera([1.0, -7.0, 2.0], [0.0, 0.0, 0.5])
    baked = bake_view(MeshRaycaster(v, f), cam, chunk_rays=300)
    o, d = cam.all_pixel_rays()
    t = -o[:, 1] / d[:, 1]  # plane y = 0
    p = o + t[:, None] * d
    inside = (np.abs(p[:, [0, 2]]) <= 5.0).all(axis=1)
    z = cam.world_to_cam(p)[:, 2]
    inner = (np.abs(p[:, [0, 2]]) <= 4.9).all(
        axis=1
    )  # away from the border, where float32 may decide either way
    assert np.array_equal(baked.valid.ravel()[inner | ~inside], inside[inner | ~inside])
    assert np.allclose(baked.depth.ravel()[inner], z[inner], rtol=1e-5)


def test_exr_round_trip_is_bit_exact(tmp_path):
    rc = MeshRaycaster(*cube())
    baked = bake_view(rc, camera([2.0, -4.0, 1.5], [0, 0, 0]), chunk_rays=500)
    rng = np.random.default_rng(0)
    odd = rng.normal(size=baked.depth.shape).astype(np.float32) * np.float32(1e-39)  # subnormals too
    write_exr(tmp_path / "n.exr", {"N": baked.normal, "valid": baked.valid.astype(np.float32), "odd": odd})
    back = read_exr(tmp_path / "n.exr")
    assert back["N"].dtype == np.float32
    for key, arr in (("N", baked.normal), ("odd", odd)):
        assert back[key].tobytes() == arr.tobytes()
    with pytest.raises(ValueError, match="NaN"):
        write_exr(tmp_path / "bad.exr", {"depth": np.full((2, 2), np.nan, np.float32)})


def test_panel_masks_project_the_panels():
    surf = PartSurface("planar", [0, 0, 0], [0, -1, 0])
    a = 0.975  # a 1.95 m square at 4 m with f = 40 px spans 19.5 px: pixel centres 10.5 ... 29.5 inside
    corners = np.array([[-a, 0, -a], [a, 0, -a], [a, 0, a], [-a, 0, a]])  # BL, BR, TR, TL seen from -y
    ps = PanelSet((surf,), (Panel(0, 0, 0, corners, [0, -1, 0], 0.0),))
    cam = camera([0.0, -4.0, 0.0], [0, 0, 0], w=40, h=40, f=40.0)
    facade, glass = panel_masks(ps, cam, edge_samples=4, near_m=0.05)
    assert glass.sum() == 20 * 20 and glass[10:30, 10:30].all()
    assert (facade == glass).all()  # a single panel: no frame width known
    behind = camera([0.0, 0.5, 0.0], [0, 5, 0])  # facing away: nothing in front of the camera
    assert not panel_masks(ps, behind, 4, 0.05)[1].any()
    close = camera([0.0, -0.2, 0.0], [0, 5, 0])  # panel partly behind the near plane: clipped, no crash
    assert panel_masks(ps, close, 4, 0.05)[1].dtype == bool


def test_baked_prior_round_trip_subsets_and_bad_files(tmp_path):
    """The 06_bake_normals hand-off: what ``save`` writes ``load`` reads back bit for bit; a reader asks
    for the maps it needs; wrong channels, sizes or disagreeing valid channels are named."""
    from facade_pipeline.bake.maps import BakedPrior
    from facade_pipeline.errors import InputError
    from facade_pipeline.layout import BuildingLayout

    layout = BuildingLayout(tmp_path, "b")
    rng = np.random.default_rng(0)
    valid = rng.random((6, 7)) > 0.3
    normal = np.where(valid[..., None], rng.normal(size=(6, 7, 3)), 0).astype(np.float32)
    depth = np.where(valid, rng.uniform(1, 5, (6, 7)), 0).astype(np.float32)
    prior = BakedPrior("uav_0", normal, valid, depth, valid, valid & (depth > 2))
    written = prior.save(layout)
    assert written == list(BakedPrior.paths(layout, "uav_0").values())
    back = BakedPrior.load(layout, "uav_0", (6, 7))
    for name in ("normal", "valid", "depth", "facade", "glass"):
        np.testing.assert_array_equal(getattr(back, name), getattr(prior, name))
    masks = BakedPrior.load(layout, "uav_0", None, ("facade_mask", "glass_mask"))
    assert masks.normal is None and masks.depth is None and masks.facade.shape == (6, 7)
    with pytest.raises(InputError, match=r"uav_0.png: expected a map of shape \(5, 7\)"):
        BakedPrior.load(layout, "uav_0", (5, 7), ("glass_mask",))
    write_exr(layout.path("bake_depth_map", stem="uav_0"), {"depth": depth, "valid": np.zeros((6, 7))})
    with pytest.raises(InputError, match="valid channel of uav_0.exr"):
        BakedPrior.load(layout, "uav_0", (6, 7))
    write_exr(layout.path("bake_normal_map", stem="uav_0"), {"normal": normal})
    with pytest.raises(InputError, match=r"channels N.X/Y/Z and valid, found channels \['normal'\]"):
        BakedPrior.load(layout, "uav_0", (6, 7), ("normal_map",))
