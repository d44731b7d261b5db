"""The 03_segment hand-off (segmentation/result.py): what ``save`` writes is data_layout.md's format and
``load`` reads it back; a mask edited by hand in any 8-bit layout is read; bad files are named."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from facade_pipeline.errors import InputError
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.segmentation.result import SegmentedPanel, ViewSegmentation

W, H = 40, 30


def _result(stem: str = "frontal_0000") -> ViewSegmentation:
    mask = np.zeros((H, W), bool)
    mask[5:15, 4:12] = True
    quad = np.array([[4.0, 15.0], [12.0, 15.0], [12.0, 5.0], [4.0, 5.0]])
    panels = (
        SegmentedPanel(0, 0, quad + 0.12345, quad * 2.0, True),
        SegmentedPanel(0, 1, quad + [20.0, 0.0], quad * 2.0 + [40.0, 0.0], False),
    )
    return ViewSegmentation(stem, W, H, True, True, "", panels, mask)


def test_round_trip_and_documented_format(tmp_path):
    layout = BuildingLayout(tmp_path, "b")
    seg = _result()
    written = seg.save(layout)
    assert written == [layout.path(k, stem=seg.stem) for k in ("segment_corners", "segment_mask")]
    d = json.loads(written[0].read_text())
    assert set(d) == {"image", "width", "height", "rectified", "facade_found", "reason", "panels"}
    assert set(d["panels"][0]) == {"row", "col", "corners_px", "corners_rectified_px", "complete"}
    assert d["panels"][0]["corners_px"][0] == [4.123, 15.123]  # a thousandth of a pixel
    back = ViewSegmentation.load(layout, seg.stem, W, H)
    assert (back.stem, back.width, back.height, back.rectified, back.facade_found, back.reason) == (
        seg.stem, W, H, True, True, "",
    )  # fmt: skip
    assert [(p.row, p.col, p.complete) for p in back.panels] == [(0, 0, True), (0, 1, False)]
    np.testing.assert_allclose(back.panels[0].corners_px, np.round(seg.panels[0].corners_px, 3))
    np.testing.assert_array_equal(back.panels[1].corners_rectified_px, seg.panels[1].corners_rectified_px)
    np.testing.assert_array_equal(back.mask, seg.mask)


def test_mask_edited_by_hand_is_read_as_is(tmp_path):
    """A person paints the mask in any editor: RGB, grey levels, an alpha channel; at least 128 is panel."""
    layout = BuildingLayout(tmp_path, "b")
    seg = _result()
    seg.save(layout)
    painted = np.zeros((H, W, 4), np.uint8)
    painted[..., 3] = 255
    painted[20:25, 30:35, :3] = 200  # a new panel, light grey
    painted[0:2, 0:2, :3] = 100  # a stroke too dark to count
    cv2.imwrite(str(layout.path("segment_mask", stem=seg.stem)), painted)
    mask = ViewSegmentation.load(layout, seg.stem, W, H).mask
    assert mask.sum() == 25 and mask[20:25, 30:35].all()


def test_bad_files_are_named(tmp_path):
    layout = BuildingLayout(tmp_path, "b")
    seg = _result()
    with pytest.raises(InputError, match="corners/frontal_0000.json.*no file"):
        ViewSegmentation.load(layout, seg.stem, W, H)
    seg.save(layout)
    with pytest.raises(InputError, match="width x height 41x30"):
        ViewSegmentation.load(layout, seg.stem, W + 1, H)
    cv2.imwrite(str(layout.path("segment_mask", stem=seg.stem)), np.zeros((H, W + 2), np.uint8))
    with pytest.raises(InputError, match=r"masks/frontal_0000.png: expected a 40x30 mask.*42x30"):
        ViewSegmentation.load(layout, seg.stem, W, H)
    path = layout.path("segment_corners", stem=seg.stem)
    d = json.loads(path.read_text())
    d["panels"][1]["corners_px"] = [[0, 0], [1, 1], [2, 2]]
    path.write_text(json.dumps(d))
    with pytest.raises(InputError, match="panel 1 with 4 finite"):
        ViewSegmentation.load(layout, seg.stem, W, H)
    path.write_text("{")
    with pytest.raises(InputError, match="JSONDecodeError"):
        ViewSegmentation.load(layout, seg.stem, W, H)
