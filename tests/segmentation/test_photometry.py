"""Exposure and white balance taken out of a view (``photometry.normalise_exposure``) against the view as
taken: a gain per channel is undone, a view already at full scale is left as it is."""

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


def test_a_gain_per_channel_is_undone():
    img = _view()
    for gains in ((0.5, 0.5, 0.5), (0.9, 0.75, 0.6)):
        dark = np.rint(img * np.array(gains)).astype(np.uint8)
        back = normalise_exposure(dark).astype(int)
        # rounding to 8 bits, twice: half a level each way, times the gain back
        assert np.abs(back - img).max() <= np.ceil(0.5 / min(gains) + 0.5)
        assert np.abs(back - img).mean() < 1.0


def test_pixels_outside_the_view_do_not_set_the_scale():
    img = _view()
    dark = np.rint(img * 0.5).astype(np.uint8)
    valid = np.ones(img.shape[:2], bool)
    valid[:, :10] = False
    dark[:, :10] = 255  # outside the view: would hide the gain if counted
    back = normalise_exposure(dark, valid).astype(int)
    assert np.abs(back[:, 10:] - img[:, 10:]).max() <= 2
