"""Typed hand-off objects of the 2DGS renderer: the pixel window, the per-splat projection, the tile bins
and the rendered maps."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

Backend = Literal["auto", "cpp", "torch", "gsplat"]
"""Which rasterizer runs:

- ``torch``: pure torch, any device; the exact reference, memory bounded by tiles and depth chunks.
- ``cpp``: the same algorithm as a compiled C++/OpenMP CPU kernel (built on first use, cached); falls back
  to ``torch`` with a logged warning if it cannot be built.
- ``gsplat``: ``gsplat.rasterization_2dgs`` on CUDA (optional ``gpu`` extra); see ``gsplat_backend`` for the
  documented differences.
- ``auto``: ``gsplat`` for CUDA tensors when CUDA and gsplat are available, ``cpp`` for CPU tensors, else
  ``torch``.
"""

TILE_SIZE = 16
"""Tiles are 16 x 16 pixels, as in the reference rasterizer."""
ALPHA_MIN = 1.0 / 255.0
"""Intersections with alpha below this are skipped."""
ALPHA_MAX = 0.99
"""alpha = min(ALPHA_MAX, opacity * G)."""
TRANSMITTANCE_MIN = 1e-4
"""A pixel stops at the splat that would bring its transmittance below this (that splat is not blended)."""
LOWPASS_SIGMA_PX = math.sqrt(0.5)
"""The reference 2DGS screen-space low-pass filter, rho_2d = 2 |x - c|^2: a Gaussian of sigma sqrt(2)/2 px
around the projected centre c, which every splat renders at least as wide as. ``render_2dgs`` takes another
sigma (``lowpass_sigma_px``); gsplat's CUDA kernel has this one built in."""
NEAR_M = 0.2
"""Splat intersections nearer than this to the camera are skipped (m): the reference 2DGS near plane (fixed
there; DESIGN.md). UAV views are metres to tens of metres from the facade, so it never binds there; the
models keep 2DGS's value."""
LOWPASS_SIGMA_TOL_PX = 1e-4
"""A sigma this close to LOWPASS_SIGMA_PX is the reference one (a config file's 0.7071)."""


def is_reference_lowpass(sigma_px: float) -> bool:
    """Whether ``sigma_px`` is 2DGS's low-pass sigma (within LOWPASS_SIGMA_TOL_PX)."""
    return abs(sigma_px - LOWPASS_SIGMA_PX) <= LOWPASS_SIGMA_TOL_PX


def lowpass_inv_var(sigma_px: float) -> float:
    """The factor k of rho_2d = k |x - c|^2 for a low-pass Gaussian of ``sigma_px`` pixels: 1 / sigma^2, and
    exactly 2 for the reference sigma. ValueError unless sigma is finite and positive."""
    if not (math.isfinite(sigma_px) and sigma_px > 0):
        raise ValueError(f"the low-pass sigma must be a finite positive number of pixels, got {sigma_px}")
    return 2.0 if is_reference_lowpass(sigma_px) else 1.0 / (sigma_px * sigma_px)


@dataclass(frozen=True)
class PixelWindow:
    """A sub-window of the image, in pixels: columns [x0, x0 + width), rows [y0, y0 + height)."""

    x0: int
    y0: int
    width: int
    height: int

    def check_inside(self, image_width: int, image_height: int) -> None:
        """ValueError unless the window is non-empty and inside an image of the given size."""
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"crop window must be non-empty, got {self}")
        x_out = self.x0 < 0 or self.x0 + self.width > image_width
        if x_out or self.y0 < 0 or self.y0 + self.height > image_height:
            raise ValueError(f"crop window {self} is not inside the {image_width}x{image_height} image")


@dataclass(frozen=True)
class ProjectedSurfels:
    """Per-splat quantities in the camera, differentiable with respect to the splat parameters.

    ``ray_transform`` is the 3x3 matrix T = K [s_u R_cw t_u | s_v R_cw t_v | R_cw p + t_cw] that maps splat
    coordinates (u, v, 1) to homogeneous pixel coordinates (x z, y z, z) (paper Eq. 4, depth row kept).
    Its rows T0, T1, T2 give the ray-splat intersection planes h_x = T0 - x T2, h_y = T1 - y T2; its last row
    is the camera-frame z of (u, v, 1), so T[2, 2] is the depth of the centre in metres.
    """

    ray_transform: torch.Tensor  # [N, 3, 3] pixels (rows 0, 1) and metres (row 2)
    normal_world: torch.Tensor  # [N, 3] unit t_u x t_v, world frame, flipped to face the camera
    depth: torch.Tensor  # [N] camera-frame z of the centre (m), the sort key; detached


@dataclass(frozen=True)
class TileBins:
    """Splat-tile intersections of one view, sorted by tile then by centre depth (stable on ties).

    Tile t (row-major over ``tiles_x`` x ``tiles_y`` tiles of ``TILE_SIZE`` px anchored at the window origin)
    owns ``splat_ids[offsets[t]:offsets[t + 1]]``.
    """

    offsets: torch.Tensor  # [tiles_y * tiles_x + 1] int64
    splat_ids: torch.Tensor  # [M] int64, front to back within a tile
    bounds: torch.Tensor  # [N, 4] float64 (x_min, y_min, x_max, y_max) pixel support, full-image px
    window: PixelWindow
    tiles_x: int
    tiles_y: int


@dataclass(frozen=True)
class SurfelRender:
    """Per-pixel maps of one rendered view (or crop window), all composited front to back (paper Eq. 5).

    With w_i = alpha_i prod_{j<i} (1 - alpha_j) the blending weight of the i-th splat along the pixel's ray:
    """

    features: torch.Tensor  # [H, W, F] sum_i w_i f_i: premultiplied by alpha (composited over black)
    alpha: torch.Tensor  # [H, W] 1 - final transmittance = sum_i w_i
    depth_expected: torch.Tensor  # [H, W] sum_i w_i z_i / alpha (camera-frame z, m); 0 where alpha = 0
    depth_median: torch.Tensor  # [H, W] z of the last splat blended while transmittance > 0.5, else 0
    normal: torch.Tensor  # [H, W, 3] sum_i w_i n_i, world frame, each n_i facing the camera; not normalised
    distortion: torch.Tensor  # [H, W] sum_{i,j<i} w_i w_j (m_i - m_j)^2 over NDC depths m (2DGS Eq. 13)
