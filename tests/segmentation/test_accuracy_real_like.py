"""The real photos' targets on the shipped real-like scene (close-ups through a distorted wide lens at
exposures from -1 to +1.5 stops, masts and a crane reflected, two stick-built units without glass showing a
room), its gt/ taken as the photos' truth: whole panes found, mask IoU median and min, corners, and no
complete panel over a unit without glass. A few minutes: the DAG up to segment_panels."""

from __future__ import annotations

import os

import numpy as np
import pytest

from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.scene import ImportedScene
from facade_pipeline.segmentation.accuracy import truth_as_real
from facade_pipeline.segmentation.real_truth import evaluate_photo, summary
from facade_pipeline.segmentation.result import ViewSegmentation
from facade_pipeline.synthetic.truth import SyntheticTruth
from tests.segmentation.conftest import doit

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def real_like(tmp_path_factory):
    root = tmp_path_factory.mktemp("real_like_seg")
    doit(["segment_panels", "building=real_like"], {**os.environ, "TQDM_DISABLE": "1"}, root)
    return BuildingLayout(root, "real_like")


def test_real_like_meets_the_real_photos_targets(real_like):
    scene = ImportedScene.load(real_like)
    truth = SyntheticTruth.load(real_like, scene.georef_from_local)
    per_photo = {}
    for v in scene.frontal_views:
        mask, outlines = truth_as_real(truth, v.stem)
        seg = ViewSegmentation.load(real_like, v.stem, v.camera.width, v.camera.height)
        per_photo[v.stem] = evaluate_photo(seg, mask.astype(np.uint8) * 255, outlines)
    s = summary(per_photo)
    assert s["found_fraction"] >= 0.9
    assert s["mask_iou_median"] >= 0.9 and s["mask_iou_min"] >= 0.75
    assert s["corner_error_median_px"] <= 3.0
    assert s["complete_less_than_half_glass"] == 0


def test_both_rooms_are_judged_by_what_the_other_panes_mirror(real_like):
    figures = read_manifest(real_like, "segment_panels").metrics["mirror"]
    assert len(figures["not_mirrored"]) == 2
    assert all(len(u["views"]) >= 3 for u in figures["not_mirrored"].values())
    assert figures["highest_kept_score"] < min(u["score"] for u in figures["not_mirrored"].values())
