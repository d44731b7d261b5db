"""PSNR and SSIM: against scikit-image, mask invariance, hand-computed cases, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from facade_pipeline.evaluation.errors import EmptyMaskError, MetricInputError
from facade_pipeline.evaluation.metrics import (
    SSIM_WINDOW_PX,
    gaussian_window_1d,
    psnr,
    ssim,
    ssim_map,
)

from .conftest import TOL

SKIMAGE_SSIM = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0)


def _pair(shape, seed=0, noise=0.1):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    return a, np.clip(a + noise * rng.standard_normal(shape), 0, 1)


def _blob_mask(h, w, seed=0):
    """An irregular mask away from the border plus a strip touching it."""
    yy, xx = np.mgrid[:h, :w]
    m = (yy - h / 2) ** 2 / (h / 3) ** 2 + (xx - w / 2) ** 2 / (w / 3) ** 2 < 1
    m[:, :3] = True
    return m


# ---------------------------------------------------------------------------------------------- PSNR/SSIM


@pytest.mark.parametrize("shape", [(32, 40), (37, 29, 3), (11, 11, 1)])
def test_full_mask_matches_skimage(shape):
    a, b = _pair(shape)
    channel_axis = 2 if len(shape) == 3 else None
    ref_ssim = structural_similarity(a, b, channel_axis=channel_axis, **SKIMAGE_SSIM)
    # scikit-image drops a 5 px frame (its windows there would need padding): border="valid" does the same.
    assert abs(ssim(a, b) - ref_ssim) < 1e-6
    assert abs(ssim(a, b, np.ones(shape[:2], bool)) - ref_ssim) < 1e-6
    assert abs(psnr(a, b) - peak_signal_noise_ratio(a, b, data_range=1.0)) < 1e-6


def test_data_range_and_torch_input():
    a, b = _pair((24, 24, 3), seed=1)
    ref = structural_similarity(255 * a, 255 * b, channel_axis=2, **{**SKIMAGE_SSIM, "data_range": 255})
    assert abs(ssim(torch.from_numpy(255 * a), 255 * b, data_range=255) - ref) < 1e-6
    assert abs(psnr(255 * a, 255 * b, data_range=255) - psnr(a, b)) < 1e-9


def test_identical_images():
    a, _ = _pair((20, 20, 3))
    assert psnr(a, a) == math.inf
    assert abs(ssim(a, a) - 1.0) < TOL[np.float64]
    assert abs(ssim(a, a, border="renormalize") - 1.0) < TOL[np.float64]


def test_psnr_hand_computed():
    a = np.zeros((4, 4))
    b = a.copy()
    b[0, 0] = 0.5  # MSE over the 2 masked pixels = 0.25 / 2
    m = np.zeros((4, 4), bool)
    m[0, :2] = True
    assert abs(psnr(a, b, m) - 10 * math.log10(1 / 0.125)) < TOL[np.float64]


@pytest.mark.parametrize("border", ["valid", "renormalize"])
def test_masked_metrics_ignore_outside(border):
    a, b = _pair((40, 48, 3), seed=2)
    m = _blob_mask(40, 48)
    rng = np.random.default_rng(5)
    a2, b2 = a.copy(), b.copy()
    a2[~m], b2[~m] = rng.random((int((~m).sum()), 3)), rng.random((int((~m).sum()), 3))
    assert abs(ssim(a, b, m, border=border) - ssim(a2, b2, m, border=border)) < TOL[np.float64]
    assert abs(psnr(a, b, m) - psnr(a2, b2, m)) < TOL[np.float64]
    assert ssim(a, b, border=border) != ssim(a2, b2, border=border)  # without the mask they do differ


def test_renormalize_differs_only_in_the_border_frame():
    a, b = _pair((30, 30, 3), seed=3)
    valid, renorm = ssim_map(a, b), ssim_map(a, b, border="renormalize")
    h = SSIM_WINDOW_PX // 2
    assert renorm.counted.all() and valid.counted.sum() == (30 - 2 * h) ** 2
    np.testing.assert_allclose(renorm.values[h:-h, h:-h], valid.values[h:-h, h:-h], atol=1e-12)
    assert not np.allclose(renorm.values[:h], 0)


def test_masked_ssim_equals_slow_reference():
    """Masked SSIM at a few centres against a direct weighted-statistics loop."""
    a, b = _pair((25, 25), seed=4)
    m = _blob_mask(25, 25)
    sm = ssim_map(a, b, m, border="renormalize")
    g = np.outer(gaussian_window_1d(), gaussian_window_1d())
    c1, c2 = 0.01**2, 0.03**2
    for y, x in [(12, 12), (0, 1), (20, 2), (5, 12)]:
        if not m[y, x]:
            continue
        ys, xs = np.mgrid[y - 5 : y + 6, x - 5 : x + 6]
        inside = (ys >= 0) & (ys < 25) & (xs >= 0) & (xs < 25)
        w = np.where(inside, g, 0.0)
        w = w * np.where(inside, m[ys.clip(0, 24), xs.clip(0, 24)], 0)
        w /= w.sum()
        pa, pb = a[ys.clip(0, 24), xs.clip(0, 24)], b[ys.clip(0, 24), xs.clip(0, 24)]
        mu_a, mu_b = (w * pa).sum(), (w * pb).sum()
        va, vb = (w * (pa - mu_a) ** 2).sum(), (w * (pb - mu_b) ** 2).sum()
        cov = (w * (pa - mu_a) * (pb - mu_b)).sum()
        ref = (2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (va + vb + c2))
        assert abs(sm.values[y, x] - ref) < 1e-10


def test_empty_masks_raise():
    a, b = _pair((20, 20))
    empty = np.zeros((20, 20), bool)
    for fn in (psnr, ssim):
        with pytest.raises(EmptyMaskError):
            fn(a, b, empty)
    edge = empty.copy()
    edge[0, :] = True  # only pixels that cannot centre a full window
    with pytest.raises(EmptyMaskError, match="5 px"):
        ssim(a, b, edge)
    assert 0 < ssim(a, b, edge, border="renormalize") <= 1
    assert issubclass(EmptyMaskError, ValueError)


@pytest.mark.parametrize(
    "args, kwargs",
    [
        ((np.zeros((8, 8)), np.zeros((8, 9))), {}),  # shape mismatch
        ((np.zeros((20, 20)), np.zeros((20, 20)), np.zeros((20, 21), bool)), {}),  # mask shape
        ((np.zeros((20, 20)), np.zeros((20, 20)), np.full((20, 20), 2)), {}),  # mask values
        ((np.full((20, 20), np.nan), np.zeros((20, 20))), {}),  # NaN
        ((np.zeros((20, 20)), np.zeros((20, 20))), {"data_range": 0}),
        ((np.zeros((8, 8)), np.zeros((8, 8))), {}),  # too small for an 11x11 window
        ((np.zeros((20, 20)), np.zeros((20, 20))), {"border": "reflect"}),
    ],
)
def test_bad_input(args, kwargs):
    with pytest.raises(MetricInputError):
        ssim(*args, **kwargs)
