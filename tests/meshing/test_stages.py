"""The three 3D stages on a small synthetic64: targets met, counts in the manifests, files in the layout,
the authoritative mask, and bad inputs named."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from facade_pipeline.bake.maps import BakedPrior
from facade_pipeline.errors import InputError
from facade_pipeline.io.images import read_image, write_mask
from facade_pipeline.io.meshes import read_mesh
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.meshing.correct import FRAME, GLASS, read_labels
from facade_pipeline.meshing.overlay import PANEL_RGB, panels_over_view, upscale_factor
from facade_pipeline.panels3d.model import PanelSet
from facade_pipeline.panels3d.poses import registered_scene
from facade_pipeline.scene import ImportedScene
from facade_pipeline.segmentation.result import ViewSegmentation
from tests.meshing.conftest import run_stage


def test_panels_match_truth_and_counts_are_reported(built64):
    m = read_manifest(built64, "regularize_corners").metrics
    assert m["n_panels"] == 12 and m["n_parts"] == 1
    assert m["truth"]["corner_error_mean_m"] < 0.03  # 0.3 px noise at 6 m is 3 cm per corner before averaging
    for key in ("rays_rejected_missed", "rays_rejected_grazing", "rays_rejected_ghost", "corner_outliers"):
        assert isinstance(m[key], int)
    panels = PanelSet.load(built64.path("regularize_panels"))
    assert sorted((p.row, p.col) for p in panels.panels) == [(r, c) for r in range(3) for c in range(4)]
    assert m["panels_seen_in_one_view"] == sum(p.n_views == 1 for p in panels.panels)


def test_corrected_mesh_meets_targets_and_beats_coarse(built64):
    t = read_manifest(built64, "correct_mesh").metrics["truth"]
    assert t["corrected"]["glass_normal_error_mean_deg"] < 1.0 < t["coarse"]["glass_normal_error_mean_deg"]
    assert (
        t["corrected"]["glass_distance_mean_m"]
        < 0.01 * t["panel_width_m"]
        < t["coarse"]["glass_distance_mean_m"]
    )
    assert t["corrected"]["frame_distance_p95_m"] < 0.05  # frames were kept


def test_bake_outputs_are_finite_and_face_the_camera(built64):
    scene = ImportedScene.load(built64)
    m = read_manifest(built64, "bake_normals")
    assert m.metrics["n_views"] == len(scene.uav_views) == 4
    assert m.metrics["truth"]["glass_normal_error_mean_deg"] < 1.0
    for v in scene.uav_views:
        # the reader checks the channels, the sizes and that both maps have the same valid channel
        b = BakedPrior.load(built64, v.stem, (v.camera.height, v.camera.width))
        assert b.normal.dtype == b.depth.dtype == np.float32
        assert np.isfinite(b.normal).all() and np.isfinite(b.depth).all()
        valid = b.valid
        assert valid.any()
        assert np.allclose(np.linalg.norm(b.normal[valid], axis=1), 1.0, atol=1e-5)
        assert (b.normal[~valid] == 0).all() and (b.depth[~valid] == 0).all()
        o, dirs = v.camera.all_pixel_rays()
        assert (np.sum(b.normal.reshape(-1, 3) * dirs, axis=1)[valid.ravel()] < 0).all()
        glass, facade = b.glass, b.facade
        assert glass.any() and not (glass & ~facade).any() and not (glass & ~valid).any()
    # masks from the same rays as the normals, frames hiding glass: close to the true glass at 64 px
    assert m.metrics["truth"]["glass_mask_iou_min"] > 0.9
    assert set(m.metrics["truth"]["glass_mask_iou"]) == {v.stem for v in scene.uav_views}


def test_labels_and_check_images(built64):
    mesh = read_mesh(built64.path("correct_mesh"))
    labels = read_labels(built64.path("correct_mesh_labels"), len(mesh.triangles))
    m = read_manifest(built64, "correct_mesh").metrics
    assert (labels == GLASS).sum() == m["triangles_glass"] == m["panel_triangles"] > 0
    assert (labels == FRAME).sum() == m["triangles_frame"] > 0
    scene = ImportedScene.load(built64)
    img = read_image(built64.path("correct_mesh_overlay"))
    assert img.shape[1] >= 2 * 480 and img.std() > 10
    for v in scene.frontal_views:
        ov = read_image(built64.path("regularize_overlay", stem=v.stem))
        assert ov.shape[0] >= v.camera.height and ov.shape[1] >= 480
    outputs = set(read_manifest(built64, "regularize_corners").outputs)
    assert {
        built64.relative(built64.path("regularize_overlay", stem=v.stem)) for v in scene.frontal_views
    } <= outputs


def test_overlays_project_the_panels_through_the_registered_poses(built64):
    """The overlay shows the cameras later stages read: the panels' outlines (drawn over the quads) are where
    the registered pose puts them, and a refined view's differ from where the imported pose would."""
    panels = PanelSet.load(built64.path("regularize_panels"))
    imported = {v.stem: v for v in ImportedScene.load(built64).frontal_views}

    def outlines(photo, camera, factor):
        return (panels_over_view(photo, camera, [], panels, factor) == PANEL_RGB).all(axis=2)

    moved = 0
    for v in registered_scene(built64).frontal_views:
        factor = upscale_factor(v.camera.width, 480)
        photo = read_image(built64.root / v.image)
        saved = (read_image(built64.path("regularize_overlay", stem=v.stem)) == PANEL_RGB).all(axis=2)
        assert saved.any() and np.array_equal(saved, outlines(photo, v.camera, factor))
        if not np.allclose(v.camera.cam_from_world, imported[v.stem].camera.cam_from_world):
            moved += not np.array_equal(saved, outlines(photo, imported[v.stem].camera, factor))
    assert moved > 0


@pytest.fixture
def copy64(built64, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(built64.root, root / "synthetic64")
    return BuildingLayout(root, "synthetic64")


def test_mask_is_authoritative(copy64):
    """A panel erased from the mask is dropped; a mask region without corners becomes a panel."""
    layout = copy64
    view = ImportedScene.load(layout).frontal_views[0]
    stem = view.stem
    seg = ViewSegmentation.load(layout, stem, view.camera.width, view.camera.height)
    removed = seg.panels[0]  # corners gone, mask kept: the mask brings the panel back
    dataclasses.replace(seg, panels=seg.panels[1:]).save(layout)
    m = run_stage("regularize_corners", layout).get("metrics")
    assert m["mask_panels_added"] >= 1 and m["n_panels"] == 12
    x, y = removed.corners_px.mean(axis=0).astype(int)
    from scipy import ndimage

    mask = seg.mask.copy()
    lab, _ = ndimage.label(mask)
    mask[lab == lab[y, x]] = False  # the person erased that panel
    seg.save(layout)
    write_mask(layout.path("segment_mask", stem=stem), mask)
    m = run_stage("regularize_corners", layout)["metrics"]
    assert m["mask_panels_dropped"] == 1 and m["n_panels"] == 11


def test_missing_segment_file_is_named(copy64):
    stem = ImportedScene.load(copy64).frontal_views[1].stem
    copy64.path("segment_mask", stem=stem).unlink()
    with pytest.raises(InputError, match=f"masks/{stem}.png"):
        run_stage("regularize_corners", copy64)
