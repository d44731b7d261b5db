"""Exposure taken out of a view (``photometry.normalise_exposure``) against the view as taken: a gain is
undone, a view already at full scale is left as it is, and its colours keep their ratios. And a frame's
presence (``edges.frame_presence``), which a brighter view keeps: its colour distances are relative to the
frame's colour."""

from __future__ import annotations

import numpy as np

from facade_pipeline.segmentation.edges import EdgeLine, frame_presence
from facade_pipeline.segmentation.evidence import Gradients
from facade_pipeline.segmentation.photometry import normalise_exposure


def _view(seed: int = 0) -> np.ndarray:
    """An RGB view with 5 % of its pixels at full scale in every channel (sunlit frames, sky reflected)."""
    rng = np.random.default_rng(seed)
    img = rng.integers(20, 230, size=(60, 80, 3)).astype(np.uint8)
    img[:3, :] = 255
    return img


def test_a_view_at_full_scale_is_left_as_it_is():
    img = _view()
    assert normalise_exposure(img) is img


def test_a_gain_is_undone():
    img = _view()
    for gain in (0.5, 0.8):
        dark = np.rint(img * gain).astype(np.uint8)
        back = normalise_exposure(dark).astype(int)
        # rounding to 8 bits, twice: half a level each way, times the gain back
        assert np.abs(back - img).max() <= np.ceil(0.5 / gain + 0.5)
        assert np.abs(back - img).mean() < 1.0


def test_one_gain_for_the_three_channels():
    """A view whose brightest part is blue (a sky reflected) keeps its colours: red and green are scaled
    by the blue channel's gain, not stretched to full scale on their own."""
    img = _view()
    img[:3, :] = (150, 200, 255)
    dark = np.rint(img * 0.6).astype(np.uint8)
    back = normalise_exposure(dark).astype(int)
    assert np.abs(back - img).max() <= 2
    assert back[..., 0].max() <= 230


def test_pixels_outside_the_view_do_not_set_the_scale():
    img = _view()
    dark = np.rint(img * 0.5).astype(np.uint8)
    valid = np.ones(img.shape[:2], bool)
    valid[:, :10] = False
    dark[:, :10] = 255  # outside the view: would hide the gain if counted
    back = normalise_exposure(dark, valid).astype(int)
    assert np.abs(back[:, 10:] - img[:, 10:]).max() <= 2


def _bar_view() -> tuple[np.ndarray, np.ndarray]:
    """An RGB view [120, 40, 3] (0-255, unrounded) of one vertical grey frame bar (columns 15-25) between
    panes of glass, and whether each row shows the bar's own colour: as lit over rows 0-59, 3 % darker
    over rows 60-79 (its shading, within the tolerance), 12 % darker over rows 80-99 (the bar in a
    shadow, out of it; 0.10 from the bar's colour, within 0.12 as an absolute distance) and behind a tree
    over rows 100-119."""
    img = np.empty((120, 40, 3))
    img[:] = (0.20, 0.20, 0.25)
    frame = np.array([0.50, 0.50, 0.50])
    img[:, 15:25] = frame
    img[60:80, 15:25] = 0.97 * frame
    img[80:100, 15:25] = 0.88 * frame
    img[100:, 15:25] = (0.20, 0.35, 0.10)
    return 255.0 * img, np.arange(120) < 80


def test_a_frame_is_present_where_it_was_at_a_brighter_exposure():
    """The view at an exposure up to twice as bright (nothing clips) finds the bar's colour where the
    view as taken does: within 0.12 of its colour, relative to its brightness, wherever its shading is,
    and not where the tree is or the shadow is deeper."""
    img, truth = _bar_view()
    low, high = (EdgeLine(a, 0.0, 60.0, np.zeros(120)) for a in (15.0, 25.0))
    for gain in (1.0, 1.25, 1.6, 1.9):
        present, unknown = frame_presence(Gradients.of(img * gain, 0), low, high, slice(0, 120), 0.12)
        np.testing.assert_array_equal(present, truth.astype(float), err_msg=f"gain {gain}")
        assert unknown is None
