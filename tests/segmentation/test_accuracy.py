"""Accuracy of rectify + segment_panels against the simulator's truth on the shipped synthetic scenes
(reflections on). Figures for benchmarks/RESULTS.md come from benchmarks/bench_segmentation.py."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.manifest import read_manifest
from facade_pipeline.scene import ImportedScene
from facade_pipeline.segmentation.accuracy import (
    evaluate_view,
    panel_ious,
    panel_ious_vs_panels,
    truth_as_real,
)
from facade_pipeline.segmentation.real_truth import evaluate_photo, quad_mask, summary, whole_panes
from facade_pipeline.segmentation.result import ViewSegmentation
from facade_pipeline.synthetic.truth import SyntheticTruth

BUILDINGS = ["synthetic64", "synthetic64_curved"]


def evaluate(layout) -> list[dict]:
    scene = ImportedScene.load(layout)
    truth = SyntheticTruth.load(layout, scene.georef_from_local)
    return [evaluate_view(layout, v, truth, 4) for v in scene.frontal_views]


@pytest.fixture(scope="module")
def results(scenes):
    return {b: evaluate(scenes[b][0]) for b in BUILDINGS}


def test_planar_views_are_rectified_by_a_plane_and_curved_ones_by_a_cylinder(scenes):
    kinds = {
        b: {m["kind"] for m in read_manifest(scenes[b][0], "rectify").metrics["views"].values()}
        for b in BUILDINGS
    }
    assert kinds == {"synthetic64": {"plane"}, "synthetic64_curved": {"cylinder"}}


@pytest.mark.parametrize("building", BUILDINGS)
def test_rectification_residual_and_straight_edges(results, building):
    r = results[building]
    assert max(v["rectify_residual_px"] for v in r) < 0.5
    straight = np.concatenate([v["edge_straightness_px"] for v in r])
    assert len(straight) > 10 and straight.max() < 1.0


@pytest.mark.parametrize("building", BUILDINGS)
def test_corner_error_median_and_95th_percentile(results, building):
    err = np.concatenate([v["corner_errors_px"] for v in results[building]])
    assert len(err) >= 20
    assert np.median(err) <= 1.0 and np.percentile(err, 95) <= 2.0


@pytest.mark.parametrize("building", BUILDINGS)
def test_every_view_has_a_facade_and_the_corners_file_follows_the_contract(scenes, building):
    layout = scenes[building][0]
    for v in ImportedScene.load(layout).frontal_views:
        # the reader checks the size against the view's and each panel's 4 finite corners in both images
        seg = ViewSegmentation.load(layout, v.stem, v.camera.width, v.camera.height)
        assert seg.stem == v.stem and seg.facade_found and seg.rectified and seg.reason == ""
        for p in seg.panels:
            assert p.corners_px.shape == (4, 2) and p.corners_rectified_px.shape == (4, 2)
            assert p.row >= 0 and p.col >= 0


@pytest.mark.parametrize("building", BUILDINGS)
def test_panel_count_exact_and_mask_iou(results, building):
    for v in results[building]:
        assert v["n_pred"] == v["n_true"]
        assert (v["iou_complete"] >= 0.95).all()


@pytest.mark.parametrize("building", BUILDINGS)
def test_the_truth_in_the_real_photos_layout(scenes, building):
    """gt/ as real photos' truth (``truth_as_real``): the glass the mask holds lies inside the panels'
    outlines, a whole pane's quad is mostly glass (the frames hide a little of it), and the segmentation
    scored on it as on real photos finds every whole pane."""
    from skimage.measure import points_in_poly

    layout = scenes[building][0]
    scene = ImportedScene.load(layout)
    truth = SyntheticTruth.load(layout, scene.georef_from_local)
    per_photo = {}
    for v in scene.frontal_views:
        mask, outlines = truth_as_real(truth, v.stem)
        W, H = v.camera.width, v.camera.height
        ys, xs = np.mgrid[0:H, 0:W] + 0.5
        centres = np.stack([xs.ravel(), ys.ravel()], axis=1)
        inside = np.zeros(H * W, bool)
        for o in outlines:
            inside |= points_in_poly(centres, np.asarray(o, float) + 0.5)
        assert mask.ravel()[inside].sum() >= 0.95 * mask.sum()
        for pane in whole_panes(outlines, W, H):
            assert mask[quad_mask(pane, W, H)].mean() > 0.7
        seg = ViewSegmentation.load(layout, v.stem, W, H)
        per_photo[v.stem] = evaluate_photo(seg, mask.astype(np.uint8) * 255, outlines)
    s = summary(per_photo)
    assert s["whole_panes"] > 0 and s["found_fraction"] == 1.0


def test_a_panel_over_no_pixel_centre_is_scored_zero_not_dropped():
    """A cut panel may be a sliver along the border that covers no pixel centre: it is still a predicted
    panel, scored 0, and the scores stay one per panel, in the panels' order (the bench indexes them with
    the panels' completeness)."""
    pred = np.full((6, 8), -1)
    pred[1:5, 1:4] = 0  # panel 0 over the first pane; panel 1 covers nothing
    true = np.full((6, 8), -1)
    true[1:5, 1:4] = 7
    true[1:5, 5:7] = 8
    np.testing.assert_allclose(panel_ious_vs_panels(pred, true, 2), [1.0, 0.0])
    np.testing.assert_allclose(panel_ious(pred, true >= 0, 1, 2), [1.0, 0.0])
