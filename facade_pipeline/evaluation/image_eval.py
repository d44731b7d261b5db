"""Image metrics of one rendered view against its photo, per region, and the error heat map.

Regions (bool masks [H, W]): ``facade`` (the baked facade mask), ``glass`` (facade and glass),
``glass_interior`` (the glass pixels at least ``INTERIOR_MARGIN_PX`` from the glass region's edge and from
the image border: the frames' edges, where a pixel mixes glass and frame, left out), ``frames`` (facade
but not glass) and ``unclipped`` (the facade's pixels whose photo has no channel clipped,
``training.data.CLIP_LEVEL``: a clipped channel records only that the light was at least that bright, so a
render darker than it is wrong by at least the difference and one brighter is right; where the view
carries no clipped mask, none). Each region gets PSNR, SSIM (``metrics.py``: 11x11 Gaussian window, sigma 1.5,
statistics renormalised over the mask) and LPIPS (``lpips.py``) under every configured convention. A
region without a pixel gets ``None`` (JSON null), never a number; LPIPS without weights is the string
``"unavailable"``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from facade_pipeline.evaluation.lpips import LpipsUnavailable, lpips_score
from facade_pipeline.evaluation.metrics import psnr, ssim
from facade_pipeline.evaluation.params import LpipsSetting

REGIONS = ("facade", "glass", "glass_interior", "frames", "unclipped")
#: pixels nearer than this to the edge of a view's glass region are left out of ``glass_interior``
INTERIOR_MARGIN_PX = 2
UNAVAILABLE = "unavailable"
#: anchors of the heat-map colour ramp (black -> purple -> orange -> yellow), evenly spaced in [0, 1]
_RAMP = np.array([[0, 0, 4], [87, 16, 110], [188, 55, 84], [249, 142, 9], [252, 255, 164]], np.float64) / 255


def region_masks(
    facade: np.ndarray, glass: np.ndarray, clipped: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """The evaluation regions (``REGIONS``) from the facade and glass masks [H, W] bool and the photo's
    clipped pixels [H, W] bool (any channel; None: no ``unclipped`` region)."""
    facade, glass = np.asarray(facade, bool), np.asarray(glass, bool)
    on_glass = facade & glass
    masks = {
        "facade": facade,
        "glass": on_glass,
        "glass_interior": erode(on_glass, INTERIOR_MARGIN_PX),
        "frames": facade & ~glass,
    }
    if clipped is not None:
        masks["unclipped"] = facade & ~np.asarray(clipped, bool)
    return masks


def erode(mask: np.ndarray, px: int) -> np.ndarray:  # [H, W] bool -> [H, W] bool
    """``mask`` without the pixels within ``px`` (Chebyshev distance) of a pixel outside it or of the
    image border."""
    mask = np.asarray(mask, bool)
    if px <= 0:
        return mask
    h, w = mask.shape
    padded = np.pad(mask, px, constant_values=False)  # off the image counts as outside the mask
    out = mask.copy()
    for dy in range(2 * px + 1):
        for dx in range(2 * px + 1):
            out &= padded[dy : dy + h, dx : dx + w]
    return out


def _finite(x: float) -> float | str:
    """A JSON-safe PSNR: identical images give +inf, written as the string "inf"."""
    return x if math.isfinite(x) else "inf"


def _lpips(render: np.ndarray, truth: np.ndarray, mask: np.ndarray, setting: LpipsSetting) -> dict[str, Any]:
    out: dict[str, Any] = {}
    x0 = torch.as_tensor(np.ascontiguousarray(render.transpose(2, 0, 1)), dtype=torch.float32)
    x1 = torch.as_tensor(np.ascontiguousarray(truth.transpose(2, 0, 1)), dtype=torch.float32)
    m = torch.as_tensor(mask)
    for conv in setting.conventions:
        s = lpips_score(x0, x1, convention=conv, mask=m, weights_dir=setting.weights_dir)
        out[conv] = UNAVAILABLE if isinstance(s, LpipsUnavailable) else round(s.value, 6)
    return out


def view_metrics(
    render: np.ndarray, truth: np.ndarray, masks: dict[str, np.ndarray], setting: LpipsSetting
) -> dict[str, dict[str, Any] | None]:
    """PSNR (dB), SSIM and LPIPS of ``render`` [H, W, 3] against ``truth`` [H, W, 3] (both in [0, 1]) over
    each region of ``masks``; ``None`` for an empty region."""
    out: dict[str, dict[str, Any] | None] = {}
    for name, m in masks.items():
        if not m.any():
            out[name] = None
            continue
        out[name] = {
            "pixels": int(m.sum()),
            "psnr": _finite(round(psnr(render, truth, m), 4)),
            "ssim": round(ssim(render, truth, m, border="renormalize"), 6),
            "lpips": _lpips(render, truth, m, setting),
        }
    return out


def mean_metrics(per_view: list[dict[str, Any]], conventions: tuple[str, ...]) -> dict[str, Any]:
    """Means over views per region. PSNR is averaged in dB (as 3DGS-family papers do); an infinite PSNR
    (a perfect view) is left out of the mean. LPIPS is "unavailable" when any view lacks it. Where the rows
    carry ``normal_error_glass_deg``, its mean over the views that have one (None: none has)."""
    out: dict[str, Any] = {}
    for region in REGIONS:
        rows = [v["metrics"][region] for v in per_view if v["metrics"].get(region)]
        if not rows:
            out[region] = None
            continue
        ps = [r["psnr"] for r in rows if r["psnr"] != "inf"]
        lp: dict[str, Any] = {}
        for c in conventions:
            vals = [r["lpips"][c] for r in rows]
            lp[c] = UNAVAILABLE if UNAVAILABLE in vals else round(float(np.mean(vals)), 6)
        out[region] = {
            "views": len(rows),
            "psnr": round(float(np.mean(ps)), 4) if ps else "inf",
            "ssim": round(float(np.mean([r["ssim"] for r in rows])), 6),
            "lpips": lp,
        }
    if any("normal_error_glass_deg" in v for v in per_view):
        errs = [v["normal_error_glass_deg"] for v in per_view if v.get("normal_error_glass_deg") is not None]
        out["normal_error_glass_deg"] = float(np.mean(errs)) if errs else None
    return out


def error_heatmap(render: np.ndarray, truth: np.ndarray, mask: np.ndarray, max_error: float) -> np.ndarray:
    """[H, W, 3] uint8: the absolute error, mean over RGB, mapped to a black-to-yellow ramp with
    ``max_error`` (and above) at the top; pixels outside ``mask`` are grey."""
    if not max_error > 0:
        raise ValueError(f"max_error must be > 0, got {max_error}")
    err = np.abs(np.asarray(render, np.float64) - np.asarray(truth, np.float64)).mean(axis=-1)
    t = np.clip(err / max_error, 0.0, 1.0) * (len(_RAMP) - 1)
    i = np.minimum(t.astype(int), len(_RAMP) - 2)
    f = (t - i)[..., None]
    rgb = _RAMP[i] * (1 - f) + _RAMP[i + 1] * f
    rgb[~np.asarray(mask, bool)] = 0.5
    return np.round(rgb * 255).astype(np.uint8)


def side_by_side(truth: np.ndarray, render: np.ndarray, heat: np.ndarray, gap_px: int = 2) -> np.ndarray:
    """[H, 3 W + 2 gap, 3] uint8: ground truth | render | error heat map, separated by white gaps."""
    h = truth.shape[0]
    gap = np.full((h, gap_px, 3), 255, np.uint8)
    u8 = [np.round(np.clip(a, 0, 1) * 255).astype(np.uint8) for a in (truth, render)]
    return np.concatenate([u8[0], gap, u8[1], gap, heat], axis=1)
