"""Degree-7 polynomial warps: exactness, both directions, conditioning reported near image borders."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.geometry.polywarp import PolyWarp, fit_polywarp
from facade_pipeline.rectification.surface_map import image_grid


def barrel(xy: np.ndarray, W=64.0, H=64.0, k=0.05) -> np.ndarray:
    c = np.array([W / 2, H / 2])
    q = (xy - c) / (W / 2)
    return c + (W / 2) * q * (1 + k * (q**2).sum(axis=1, keepdims=True))


def test_identity_and_json_round_trip():
    w = PolyWarp.identity((0.0, 0.0, 64.0, 48.0))
    pts = np.random.default_rng(0).uniform(0, 48, (20, 2))
    assert np.allclose(w(pts), pts) and w.is_identity
    back = PolyWarp.from_dict(w.to_dict())
    assert np.allclose(back(pts), pts)


def test_degree_7_fits_a_smooth_warp_both_ways_to_the_border():
    src = image_grid(64, 64, 25)
    dst = barrel(src)
    fwd = fit_polywarp(src, dst, 7, (0, 0, 64, 64))
    inv = fit_polywarp(dst, src, 7)
    assert fwd.max_px < 1e-3 and inv.max_px < 0.05
    border = np.concatenate(
        [
            np.stack([np.linspace(0, 64, 50), np.zeros(50)], 1),
            np.stack([np.full(50, 64.0), np.linspace(0, 64, 50)], 1),
        ]
    )
    assert np.abs(fwd(border) - barrel(border)).max() < 0.01  # between samples, on the border
    assert np.abs(inv(fwd(border)) - border).max() < 0.1
    assert fwd.condition < 50  # Legendre basis on the full domain: well conditioned


def test_conditioning_is_reported_when_samples_leave_the_border_empty():
    full = fit_polywarp(image_grid(64, 64, 25), barrel(image_grid(64, 64, 25)), 7, (0, 0, 64, 64))
    centre = 16 + image_grid(32, 32, 25)  # samples only in the middle half, domain the whole image
    part = fit_polywarp(centre, barrel(centre), 7, (0, 0, 64, 64))
    assert part.condition > 100 * full.condition  # the extrapolation risk shows in the report
    assert part.max_px < 1e-3  # ... while the residual at the samples alone looks perfect
    assert np.isfinite(part.condition)


def test_too_few_samples_is_an_error():
    with pytest.raises(ValueError, match="at least 36 sample pairs"):
        fit_polywarp(np.zeros((10, 2)), np.zeros((10, 2)), 7)
