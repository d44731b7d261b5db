"""Image metrics over a mask (PSNR, SSIM).

Everything is computed in float64 (numpy; PSNR through the training package's ``losses.psnr``, the one
PSNR of the project); torch tensors are accepted and copied to the CPU.

Images are ``[H, W]`` or ``[H, W, C]`` arrays with values in ``[0, data_range]`` (``data_range`` is 1 for our
renders). A mask is a bool array ``[H, W]`` (True = the pixel counts), the same for every channel; ``None``
means every pixel. No metric ever returns NaN: when there is nothing to average (an empty mask) it
raises ``EmptyMaskError`` (a ``ValueError``). Identical images give PSNR = +inf, as scikit-image.

PSNR over a mask
    MSE = sum over masked pixels p and channels c of (x_pc - y_pc)^2 / (n_masked * C);
    PSNR = 10 log10(data_range^2 / MSE). Pixels outside the mask do not enter at all.

SSIM over a mask (Wang et al. 2004, "Image quality assessment: from error visibility to structural
similarity", Eq. 13 with the Gaussian-weighted statistics of their Sec. III-B)
    An 11x11 Gaussian window w (sigma 1.5, normalised to sum 1), K1 = 0.01, K2 = 0.03,
    C1 = (K1 R)^2, C2 = (K2 R)^2, population (not sample) covariances. The mask enters the local statistics
    as well as the final average: at a window centre p, with m the mask (1 inside, 0 outside),
        W_p    = sum_q w_(q-p) m_q
        mu_x   = sum_q w_(q-p) m_q x_q / W_p              (and mu_y likewise)
        s_x^2  = sum_q w_(q-p) m_q x_q^2 / W_p - mu_x^2   (and s_y^2, s_xy likewise)
        SSIM_p = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2)),
    i.e. the Gaussian weights of each window are renormalised over the masked pixels it covers, so a pixel
    outside the mask changes nothing (a plain "SSIM map, then mean over the mask" would still see unmasked
    pixels through the windows that straddle the mask's edge). The map is averaged over channels, then over
    the masked window centres. With a full mask W_p = 1 and this is the standard SSIM.

    Border windows (``border``):
    - ``"valid"`` (default): only centres whose whole 11x11 window lies inside the image count, i.e. a 5 px
      frame is dropped. This is exactly what ``skimage.metrics.structural_similarity(gaussian_weights=True,
      sigma=1.5, use_sample_covariance=False)`` averages (it filters with reflect padding, then crops 5 px,
      so the padding never reaches the values it keeps): with a full mask the two agree to rounding.
    - ``"renormalize"``: every masked pixel is a centre; the part of a window that falls off the image counts
      as outside the mask and the weights are renormalised over what is left. This keeps masks that touch
      the image border; it differs from scikit-image only in those 5 px.
    We never zero-pad the images themselves (as ``conv2d(padding=5)`` SSIM implementations do): that biases
    the border towards black.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from facade_pipeline.evaluation.errors import EmptyMaskError, MetricInputError
from facade_pipeline.training import losses

SSIM_WINDOW_PX = 11
SSIM_SIGMA_PX = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03

SsimBorder = Literal["valid", "renormalize"]


# --------------------------------------------------------------------------------------------- input checks


def _as_f64(a: Any, name: str) -> np.ndarray:
    """A float64 numpy copy of an array or torch tensor."""
    if hasattr(a, "detach"):  # a torch tensor
        a = a.detach().cpu().numpy()
    arr = np.asarray(a)
    if arr.dtype == bool or not np.issubdtype(arr.dtype, np.number):
        raise MetricInputError(f"{name} as a numeric array", f"dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise MetricInputError(f"finite values in {name}", f"{int((~np.isfinite(arr)).sum())} NaN or Inf")
    return arr


def _as_mask(mask: Any, shape: tuple[int, ...], name: str = "mask") -> np.ndarray:
    """A bool mask of ``shape`` (``None`` -> all True); 0/1 numbers are accepted, other values are not."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    if hasattr(mask, "detach"):
        mask = mask.detach().cpu().numpy()
    m = np.asarray(mask)
    if m.shape != shape:
        raise MetricInputError(f"{name} of shape {shape}", f"shape {m.shape}")
    if m.dtype != bool:
        if not np.isin(m, (0, 1)).all():
            raise MetricInputError(f"{name} as bool or 0/1 values", f"other values (dtype {m.dtype})")
        m = m.astype(bool)
    return m


def _image_pair(img0: Any, img1: Any, mask: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two float64 images [H, W, C] (a channel axis added to [H, W]) and a bool mask [H, W]."""
    x, y = _as_f64(img0, "img0"), _as_f64(img1, "img1")
    if x.shape != y.shape:
        raise MetricInputError("two images of the same shape", f"{x.shape} and {y.shape}")
    if x.ndim not in (2, 3):
        raise MetricInputError("images [H, W] or [H, W, C]", f"shape {x.shape}")
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    return x, y, _as_mask(mask, x.shape[:2])


def _check_data_range(data_range: float) -> float:
    if not (math.isfinite(data_range) and data_range > 0):
        raise MetricInputError("data_range > 0", str(data_range))
    return float(data_range)


# --------------------------------------------------------------------------------------------------- PSNR


def psnr(img0: Any, img1: Any, mask: Any = None, *, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over the masked pixels (all channels): 10 log10(R^2 / MSE).

    img0, img1: [H, W] or [H, W, C]; mask: bool [H, W] or None (every pixel). +inf where the images agree on
    the mask; ``EmptyMaskError`` for an empty mask."""
    x, y, m = _image_pair(img0, img1, mask)
    r = _check_data_range(data_range)
    if not m.any():
        raise EmptyMaskError("a mask with at least one pixel for PSNR", "an empty mask")
    return losses.psnr(torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(m), r)


# --------------------------------------------------------------------------------------------------- SSIM


def gaussian_window_1d(size_px: int = SSIM_WINDOW_PX, sigma_px: float = SSIM_SIGMA_PX) -> np.ndarray:
    """The 1D Gaussian window [size_px], centred, normalised to sum 1 (the 2D window is its outer product)."""
    t = np.arange(size_px, dtype=np.float64) - (size_px - 1) / 2.0
    w = np.exp(-0.5 * (t / sigma_px) ** 2)
    return w / w.sum()


def _filter_valid(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Separable correlation of a [H, W, ...] with the window w [K] on axes 0 and 1, keeping only the
    centres whose whole window is inside: [H - K + 1, W - K + 1, ...]."""
    k = len(w)
    h, wd = a.shape[0] - k + 1, a.shape[1] - k + 1
    rows = sum(w[i] * a[i : i + h] for i in range(k))
    return sum(w[j] * rows[:, j : j + wd] for j in range(k))


@dataclass(frozen=True, eq=False)
class SsimMap:
    """Per-pixel SSIM ``values`` [H, W] (mean over channels) and the window centres that count, ``counted``
    [H, W] bool; ``values`` is 0 where not counted."""

    values: np.ndarray
    counted: np.ndarray


def ssim_map(img0: Any, img1: Any, mask: Any = None, *, data_range: float = 1.0,
             border: SsimBorder = "valid") -> SsimMap:
    """The masked SSIM map (module docstring: Gaussian statistics renormalised over the mask; ``border``
    says which window centres count). img0, img1: [H, W] or [H, W, C]; mask: bool [H, W] or None."""
    x, y, m = _image_pair(img0, img1, mask)
    r = _check_data_range(data_range)
    w = gaussian_window_1d()
    half = SSIM_WINDOW_PX // 2
    if border == "valid":
        if min(x.shape[:2]) < SSIM_WINDOW_PX:
            raise MetricInputError(f"images at least {SSIM_WINDOW_PX} px on each side for SSIM",
                                   f"shape {x.shape[:2]}")
        counted = np.zeros_like(m)
        counted[half:-half, half:-half] = m[half:-half, half:-half]
    elif border == "renormalize":
        # Off-image pixels are outside the mask: zero-pad everything, the weights renormalise below.
        pad = ((half, half), (half, half), (0, 0))
        x, y = np.pad(x, pad), np.pad(y, pad)
        counted = m
        m = np.pad(m, pad[:2])
    else:
        raise MetricInputError("border 'valid' or 'renormalize'", repr(border))
    mf = m.astype(np.float64)[..., None]  # [H, W, 1]
    wsum = _filter_valid(mf, w)  # [H', W', 1]; > 0 at every counted centre (its own weight is > 0)
    wsum = np.where(wsum > 0, wsum, 1.0)
    mu_x, mu_y = _filter_valid(mf * x, w) / wsum, _filter_valid(mf * y, w) / wsum
    v_x = _filter_valid(mf * x * x, w) / wsum - mu_x * mu_x
    v_y = _filter_valid(mf * y * y, w) / wsum - mu_y * mu_y
    v_xy = _filter_valid(mf * x * y, w) / wsum - mu_x * mu_y
    c1, c2 = (SSIM_K1 * r) ** 2, (SSIM_K2 * r) ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * v_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (v_x + v_y + c2))
    s = s.mean(axis=2)  # [H', W']
    if border == "valid":
        s = np.pad(s, half)
    return SsimMap(values=np.where(counted, s, 0.0), counted=counted)


def ssim(img0: Any, img1: Any, mask: Any = None, *, data_range: float = 1.0,
         border: SsimBorder = "valid") -> float:
    """Mean SSIM over the masked window centres (11x11 Gaussian window, sigma 1.5; module docstring).

    ``EmptyMaskError`` when no centre counts: an empty mask, or with ``border="valid"`` no masked pixel at
    least 5 px from the image border."""
    sm = ssim_map(img0, img1, mask, data_range=data_range, border=border)
    n = int(sm.counted.sum())
    if n == 0:
        where = " (5 px or more from the image border, border='valid')" if border == "valid" else ""
        raise EmptyMaskError(f"a mask with a pixel that can centre an SSIM window{where}", "none")
    return float(sm.values[sm.counted].sum() / n)
