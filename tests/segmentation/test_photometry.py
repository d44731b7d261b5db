"""Exposure taken out of a view (``photometry.normalise_exposure``) against the view as taken: a gain is
undone, a view already at full scale is left as it is, and its colours keep their ratios."""

from __future__ import annotations

import numpy as np

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
