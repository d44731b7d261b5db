"""What a glass mask loses against its truth (``real_truth.mask_losses``), on drawn masks whose every wrong
pixel is known: each class counts exactly the pixels drawn into it, and the side offsets are the shifts
drawn."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.segmentation.real_truth import LOSS_CLASSES, mask_losses, side_offsets

H, W = 120, 160


def box(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """[H, W] bool: pixels x0 <= x < x1, y0 <= y < y1."""
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def outline(x0: int, y0: int, x1: int, y1: int) -> list:
    """The pane's outline in panes.json's convention (pixel indices of its corner pixels)."""
    return [[x0, y1 - 1], [x1 - 1, y1 - 1], [x1 - 1, y0], [x0, y0]]


def quad(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """A predicted panel's corners [4, 2] (pixel edges: the pixels x0 <= x < x1 have their centres inside)."""
    return np.array([[x0, y1], [x1, y1], [x1, y0], [x0, y0]], float)


def test_each_wrong_pixel_in_the_class_drawn():
    a, b = (10, 10, 60, 50), (80, 10, 130, 50)  # two whole panes
    c = (0, 70, 40, 120)  # a pane cut by the left and bottom border
    truth = box(*a) | box(*b) | box(*c)
    empty = (60, 70, 110, 110)  # a unit without glass
    # pane a found 2 px short on its left side, pane b missed, the cut pane found, a false panel
    found_a = (12, 10, 60, 50)
    pred = box(*found_a) | box(*c) | box(*empty)
    r = mask_losses(pred, truth, [outline(*a), outline(*b), outline(*c)],
                    [quad(*found_a), quad(*c), quad(*empty)])
    n = r["count_px"]
    assert n["missed whole pane"] == 50 * 40
    assert n["short of the edge"] == 2 * 40
    assert n["false panel"] == 50 * 40
    assert n["missed cut pane"] == n["glass inside a found pane"] == 0
    assert n["over the edge"] == n["false elsewhere"] == 0
    assert r["wrong_px"] == sum(n.values())
    union, inter = (pred | truth).sum(), (pred & truth).sum()
    assert r["iou"] == pytest.approx(inter / union)
    assert r["gain"]["missed whole pane"] == pytest.approx((inter + 2000) / union - inter / union)
    assert r["gain"]["false panel"] == pytest.approx(inter / (union - 2000) - inter / union)
    assert r["cut_panes"] == (1, 1)
    # sides bottom, right, top, left: only the left one is short, by 2 px
    assert r["offsets_px"].shape == (1, 4)
    np.testing.assert_allclose(r["offsets_px"][0], [0, 0, 0, -2], atol=0.3)


def test_a_mask_beyond_the_glass_and_across_a_missed_bar():
    a, b = (10, 10, 60, 50), (10, 58, 60, 100)  # two panes, a transom of 8 px between them
    truth = box(*a) | box(*b)
    over = (10, 10, 60, 52)  # pane a's mask 2 px over the transom
    across = (70, 10, 100, 100)  # a panel across a bar, a little glass in it and much frame: "elsewhere"
    truth_across = box(70, 10, 100, 80)
    truth = truth | truth_across
    pred = box(*over) | box(*b) | box(*across)
    panes = [outline(*a), outline(*b), outline(70, 10, 100, 80)]
    r = mask_losses(pred, truth, panes, [quad(*over), quad(*b), quad(*across)])
    n = r["count_px"]
    assert n["over the edge"] == 2 * 50 + 3 * 30
    assert n["false elsewhere"] == 17 * 30
    assert set(n) == set(LOSS_CLASSES)
    np.testing.assert_allclose(r["offsets_px"][0], [2, 0, 0, 0], atol=0.3)


def test_side_offsets_follow_a_shifted_mask():
    pane = np.array(outline(20, 20, 80, 70), float) + 0.5
    truth = box(20, 20, 80, 70)
    for dx in (-3, 0, 2):
        pred = box(20 + dx, 20, 80 + dx, 70)
        # a shift to the right: the right side reaches beyond the truth, the left stops short
        np.testing.assert_allclose(side_offsets(pred, truth, pane, 8.0), [0, dx, 0, -dx], atol=0.3)


def test_clipped_wrong_pixels_are_counted():
    truth = box(10, 10, 60, 50)
    pred = box(14, 10, 60, 50)
    image = np.full((H, W, 3), 120, np.uint8)
    image[:, :12] = 255  # the first two missed columns clipped
    r = mask_losses(pred, truth, [outline(10, 10, 60, 50)], None, image)
    assert r["wrong_px"] == 4 * 40 and r["clipped_px"] == 2 * 40
