"""Quads cut by the image border (their inner corners count), triangle labels of the corrected mesh and
the masks baked from the same rays (frames hide glass), label files, and the check images."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.bake.maps import bake_view, panel_masks
from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.meshing.correct import (
    FRAME,
    GLASS,
    OTHER,
    correct_mesh,
    label_triangles,
    read_labels,
    write_labels,
)
from facade_pipeline.meshing.overlay import panels_over_view, scaled_camera, shaded_render, upscale_factor
from facade_pipeline.panels3d.grid import build_panel_set, true_corners
from tests.meshing.conftest import params_of
from tests.panels3d.test_panels_geometry import DEPTH, FW, PITCH_M, cfg, facade

W, H = 200, 150


def narrow_camera(surf, s: float, z: float) -> PinholeCamera:
    """A frontal camera 9 m out seeing about 6 x 4.5 m of the facade: panels get cut by its border."""
    target = surf.points(np.array([[s, z, 0.0]]))[0]
    eye = target + 9.0 * surf.normals_at(target[None])[0]
    return PinholeCamera(intrinsics(300.0, 300.0, W / 2, H / 2), look_at(eye, target), W, H)


def observe_cut(surf, corners, cams, min_px: float = 4.0):
    """Panels as segment_panels reports them: the visible part of each (corners clamped to the image, fine
    for these frontal views of axis-aligned panels), ``complete`` False when cut."""
    quads, complete, view = [], [], []
    for i, cam in enumerate(cams):
        for sz in corners.values():
            uv, _ = cam.project(surf.points(np.concatenate([sz, np.zeros((4, 1))], axis=1)))
            cut = np.clip(uv, [0, 0], [cam.width, cam.height])
            if np.ptp(cut[:, 0]) < min_px or np.ptp(cut[:, 1]) < min_px:
                continue
            quads.append(cut)
            complete.append(bool(np.allclose(cut, uv)))
            view.append(i)
    return quads, complete, view


def test_border_corners_are_not_panel_corners():
    cam = PinholeCamera(intrinsics(10.0, 10.0, 5, 5), np.eye(4), 10, 10)
    quad = np.array([[0, 8], [5, 8], [5, 2], [0, 2.0]])  # cut by the left border
    quads = [quad, quad]
    ok = true_corners(quads, np.array([False, True]), [0, 0], [cam], 1.5)
    assert ok.tolist() == [[False, True, True, False], [True] * 4]  # complete quads keep every corner


def test_panels_cut_by_the_border_are_recovered_from_their_inner_corners():
    surf, corners, v, f = facade("planar")
    cams = [narrow_camera(surf, -1.8, 2.0), narrow_camera(surf, 1.8, 2.0)]  # the top row is cut in both
    quads, complete, view = observe_cut(surf, corners, cams)
    assert not all(complete) and sum(complete) < 6
    rc = MeshRaycaster(v, f)
    pts = surf.points(np.c_[np.random.default_rng(1).uniform([-3, 1.3], [3, 4.6], (400, 2)), np.zeros(400)])
    only_whole = [i for i, c in enumerate(complete) if c]
    ps_whole, _ = build_panel_set(
        [quads[i] for i in only_whole],
        [True] * len(only_whole),
        [view[i] for i in only_whole],
        cams,
        rc,
        pts,
        cfg(),
    )
    speck = np.array([[0.0, 9.0], [5.0, 9.0], [5.0, 4.0], [0.0, 4.0]])  # a speck of mask at the border
    quads, complete, view = quads + [speck], complete + [False], view + [0]
    ps, m = build_panel_set(quads, complete, view, cams, rc, pts, cfg())
    assert len(ps_whole.panels) < 6 and m["n_panels"] == 6 and m["n_incomplete_quads_used"] > 0
    assert sorted((p.row, p.col) for p in ps.panels) == [(r, c) for r in range(2) for c in range(3)]
    for p in ps.panels:
        true = surf.points(np.concatenate([corners[(p.row, p.col)], np.zeros((4, 1))], axis=1))
        assert np.abs(p.corners - true).max() < 0.03  # the top edge of the top row from the grid's regularity


@pytest.fixture(scope="module")
def corrected():
    """The planar 2 x 3 facade corrected with its true panels, labelled."""
    surf, corners, v, f = facade("planar")
    cams = [narrow_camera(surf, -1.8, 3.0), narrow_camera(surf, 1.8, 3.0)]
    quads, complete, view = observe_cut(surf, corners, cams)
    pts = surf.points(np.c_[np.random.default_rng(1).uniform([-3, 1.3], [3, 4.6], (400, 2)), np.zeros(400)])
    ps, _ = build_panel_set(quads, complete, view, cams, MeshRaycaster(v, f), pts, cfg())
    p = params_of("correct_mesh")
    out = correct_mesh(v, f, ps, p.shrink_factor, p.cuboid_half_depth * PITCH_M, p.max_facet_deg, 1.0)
    labels = label_triangles(out.vertices, out.triangles, out.is_panel, ps, p.frame_half_depth * PITCH_M)
    return surf, ps, out, labels


def test_labels_glass_frames_and_other(corrected):
    surf, ps, out, labels = corrected
    assert (labels[out.is_panel] == GLASS).all() and not (labels[~out.is_panel] == GLASS).any()
    h = surf.coords(out.vertices[out.triangles].mean(axis=1))
    assert (labels == FRAME).any() and (labels == OTHER).any()  # the mesh runs past the facade's outline
    assert (np.abs(h[labels == FRAME, 2] - DEPTH) < 0.2).all()


def test_glass_mask_from_the_rays_is_hidden_by_frames(corrected):
    surf, ps, out, labels = corrected
    target = surf.points(np.array([[0.0, 3.0, 0.0]]))[0]
    eye = target + 6.0 * surf.normals_at(target[None])[0] + 5.0 * np.cross([0, 0, 1.0], surf.normal)
    cam = PinholeCamera(intrinsics(120.0, 120.0, 80, 60), look_at(eye, target), 160, 120)  # oblique
    baked = bake_view(MeshRaycaster(out.vertices, out.triangles), cam, 1000, labels=labels)
    glass = baked.label == GLASS
    _, projected = panel_masks(ps, cam, 8, 0.05)
    hidden = projected & (baked.label == FRAME)
    assert glass.any() and hidden.sum() > 0.03 * projected.sum()  # frames in front of the glass hide it
    assert not (glass & ~projected).any() or (glass & ~projected).sum() < 0.01 * glass.sum()
    o, d = cam.all_pixel_rays()
    hit = o + baked.depth.reshape(-1, 1) / (d @ cam.cam_from_world[2, :3])[:, None] * d
    assert np.abs(surf.coords(hit[glass.ravel()])[:, 2]).max() < 1e-3  # glass pixels see the glass plane
    assert (baked.label[~baked.valid] == 0).all()
    plain = bake_view(MeshRaycaster(out.vertices, out.triangles), cam, 1000)
    assert np.array_equal(plain.normal, baked.normal) and not plain.label.any()


def test_label_file_round_trip_and_bad_files(tmp_path):
    labels = np.array([0, 1, 2, 2], np.uint8)
    write_labels(tmp_path / "l.npy", labels)
    assert np.array_equal(read_labels(tmp_path / "l.npy", 4), labels)
    with pytest.raises(InputError, match=r"5 uint8 labels.*shape \(4,\)"):
        read_labels(tmp_path / "l.npy", 5)  # a mesh with another triangle count
    (tmp_path / "bad.npy").write_bytes(b"not numpy")
    with pytest.raises(InputError, match="bad.npy"):
        read_labels(tmp_path / "bad.npy", 4)
    with pytest.raises(InputError, match="no file"):
        read_labels(tmp_path / "none.npy", 4)


def test_check_images(corrected):
    surf, ps, out, labels = corrected
    cam = narrow_camera(surf, 0.0, 3.0)
    assert upscale_factor(cam.width, 480) == 3 and upscale_factor(1000, 480) == 1
    big = scaled_camera(cam, 3)
    uv, _ = cam.project(ps.panels[0].corners)
    assert np.allclose(big.project(ps.panels[0].corners)[0], 3 * uv)
    img = panels_over_view(np.zeros((H, W, 3), np.uint8), cam, [uv], ps, 3)
    assert img.shape == (3 * H, 3 * W, 3) and (img[..., 1] > 150).any() and (img[..., 0] > 150).any()
    shaded = shaded_render(MeshRaycaster(out.vertices, out.triangles), cam, labels)
    assert shaded.shape == (H, W, 3) and shaded.dtype == np.uint8
    blue = shaded[..., 2] > shaded[..., 0] + 40  # glass is tinted blue, frames brown
    assert 0.2 < blue.mean() < 0.9


def test_a_panel_placed_by_two_parts_is_kept_once_where_the_glass_is():
    from facade_pipeline.panels3d.grid import dedupe_across_parts
    from facade_pipeline.panels3d.model import Panel, PartSurface

    near = PartSurface("planar", [0, 0, 0], [0, -1, 0])
    far = PartSurface("planar", [0, 0.3, 0], [0, -1, 0])  # a second part's surface, 30 cm behind
    corners = np.array([[-1, 0, 0], [1, 0, 0], [1, 0, 2], [-1, 0, 2.0]])
    a = Panel(0, 0, 0, corners, [0, -1, 0], 0.0)
    b = Panel(1, 0, 0, corners + [0, 0.3, 0], [0, -1, 0], -0.3)
    other = Panel(1, 0, 1, corners + [5, 0.3, 0], [0, -1, 0], -0.3)
    rng = np.random.default_rng(0)
    glass = np.c_[rng.uniform(-0.9, 0.9, 200), np.zeros(200), rng.uniform(0.1, 1.9, 200)]  # on panel a
    kept = dedupe_across_parts([a, b, other], [near, far], glass, cfg())
    assert [(p.part, p.col) for p in kept] == [(0, 0), (1, 1)]
    kept = dedupe_across_parts([a, b, other], [near, far], glass + [0, 0.3, 0], cfg())
    assert [(p.part, p.col) for p in kept] == [(1, 0), (1, 1)]


def test_frames_finer_than_the_coarse_cells_are_backed_not_holes(corrected):
    surf, ps, fine, _ = corrected
    s_lines = np.arange(4) * (2.0 + FW) - 1.5 * (2.0 + FW)
    z_lines = np.arange(3) * (1.8 + FW) + 1.0
    back = surf.coords(fine.vertices[fine.triangles[len(fine.triangles) - fine.n_backing :]].mean(axis=1))
    under_bar = (np.abs(back[:, :1] - s_lines) < 0.4 * FW).any(-1) | (
        np.abs(back[:, 1:2] - z_lines) < 0.4 * FW
    ).any(-1)
    assert not under_bar.any()  # the coarse mesh's own frames stand there: nothing doubles them
    # a photogrammetric mesh of a wall, flat, in cells far wider than a frame bar: every cell touches a panel
    s, z = np.linspace(-5, 5, 5), np.linspace(0, 6, 4)
    S, Z = np.meshgrid(s, z, indexing="ij")
    v = surf.points(np.stack([S.ravel(), Z.ravel(), np.zeros(S.size)], axis=1))
    idx = np.arange(S.size).reshape(S.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    p = params_of("correct_mesh")
    out = correct_mesh(v, f, ps, p.shrink_factor, p.cuboid_half_depth * PITCH_M, p.max_facet_deg, 1.0)
    labels = label_triangles(out.vertices, out.triangles, out.is_panel, ps, p.frame_half_depth * PITCH_M)
    assert out.n_backing > 0
    cam = narrow_camera(surf, 0.0, 2.9)
    baked = bake_view(MeshRaycaster(out.vertices, out.triangles), cam, 1000, labels=labels)
    o, dirs = cam.all_pixel_rays()
    t = surf.intersect(o, dirs)
    szh = surf.coords(o + t[:, None] * dirs).reshape(H, W, 3)
    ds = np.abs(szh[..., :1] - s_lines).min(-1)
    dz = np.abs(szh[..., 1:2] - z_lines).min(-1)
    inside = (szh[..., 0] > s_lines[0]) & (szh[..., 0] < s_lines[-1])
    inside &= (szh[..., 1] > z_lines[0]) & (szh[..., 1] < z_lines[-1])
    bar = inside & ((ds < 0.4 * FW) | (dz < 0.4 * FW))  # well inside a bar (its true half width: 0.5)
    pane = inside & (ds > 0.6 * FW) & (dz > 0.6 * FW)  # well inside a pane
    assert bar.sum() > 100 and pane.sum() > 1000
    assert (baked.label[bar] == FRAME).all()  # the bars were holes: the backing fills them
    assert (baked.label[pane] == GLASS).all()  # and hides no glass
    hit = o + baked.depth.reshape(-1, 1) / (dirs @ cam.cam_from_world[2, :3])[:, None] * dirs
    h = surf.coords(hit[bar.ravel()])[:, 2]
    assert (h < 0).all() and (h > -0.1 * FW).all()  # just behind the glass
