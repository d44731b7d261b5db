"""The segmentation targets on the default building `demo` (384 x 288 frontal views of a planar and a
curved part whose frames stand 0.12 m proud of the glass, every effect on): corners within 1 px (median)
and 2 px (95th percentile) of the true glass corners, hidden behind the frames or not, exact counts and
whole-panel IoU of at least 0.95. About a minute: the DAG up to segment_panels."""

from __future__ import annotations

import os

import numpy as np
import pytest

from facade_pipeline.layout import BuildingLayout
from tests.segmentation.conftest import doit
from tests.segmentation.test_accuracy import evaluate

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    root = tmp_path_factory.mktemp("demo_seg")
    doit(["segment_panels", "building=demo"], {**os.environ, "TQDM_DISABLE": "1"}, root)
    return evaluate(BuildingLayout(root, "demo"))


def test_demo_corners_counts_and_panel_iou(demo):
    err = np.concatenate([v["corner_errors_px"] for v in demo])
    assert len(err) > 300
    assert np.median(err) <= 1.0 and np.percentile(err, 95) <= 2.0
    assert all(v["n_pred"] == v["n_true"] for v in demo)
    assert min(v["iou_complete"].min() for v in demo) >= 0.95
    assert any(v["kind"] == "cylinder" for v in demo) and any(v["kind"] == "plane" for v in demo)
