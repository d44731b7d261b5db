"""Conservative pixel support of each splat and its tile bins (16 x 16 px tiles, front to back by centre
depth).

A splat can only be blended where alpha = opacity * G >= 1/255, i.e. where rho <= R^2 = 2 ln(255 opacity),
with rho = min(u^2 + v^2, |x - c|^2 / s^2) (s the low-pass sigma, sqrt(2)/2 px in 2DGS). The support is
therefore the union of
- the screen image of the disk u^2 + v^2 <= R^2 restricted to depth z >= near (ray-splat branch), and
- the disk |x - c| <= R s around the projected centre c, when the centre is beyond the near plane
  (low-pass branch, whose depth is the centre's).
The bounds are computed in float64 without gradients and widened by a margin, so that binning never drops a
splat-pixel pair that the blending formula would keep: the rasterizers stay exact.
"""

from __future__ import annotations

import math

import torch

from facade_pipeline.splatting.types import (
    ALPHA_MIN,
    LOWPASS_SIGMA_PX,
    TILE_SIZE,
    PixelWindow,
    TileBins,
    lowpass_inv_var,
)

RHO_MARGIN = 1e-3
"""Relative and absolute slack on R^2 (float32 rounding of rho in the rasterizers)."""
PIXEL_MARGIN = 0.25
"""Slack on the pixel bounds (float32 rounding of the ray transform; csrc/surfel_raster.cpp uses the same)."""


def _interval_ratio_bounds(
    num: tuple[torch.Tensor, torch.Tensor], den: tuple[torch.Tensor, torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds of n / d over the box [num] x [den] with d > 0: attained at the corners."""
    corners = torch.stack([num[i] / den[j] for i in (0, 1) for j in (0, 1)], dim=-1)  # [N, 4]
    return corners.amin(-1), corners.amax(-1)


def _disk_bounds(
    T: torch.Tensor, R2: torch.Tensor, near: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixel box (x_min, y_min, x_max, y_max) of the screen image of the splat disk u^2 + v^2 <= R^2 with
    depth >= near, and whether it is non-empty. T: [N, 3, 3] float64 ray transforms.

    Where the whole disk lies beyond the near plane its image is an ellipse whose extent along x is given
    exactly by the lines h_x = T0 - x T2 tangent to the disk: (T0z - x T2z)^2 = R^2 |T0xy - x T2xy|^2, a
    quadratic in x. Otherwise (the disk crosses the near plane) the numerator and the clipped depth are
    bounded
    separately and their ratio over that box bounds the image."""
    R = R2.sqrt()
    a, b, e = T[:, 0], T[:, 1], T[:, 2]  # [N, 3]
    e_xy = e[:, :2].norm(dim=-1)
    z_lo, z_hi = e[:, 2] - R * e_xy, e[:, 2] + R * e_xy
    nonempty = z_hi >= near
    conic = z_lo >= near
    out = []
    for row in (a, b):
        # exact extent of the ellipse (valid where conic: then A > 0)
        A = e[:, 2] ** 2 - R2 * e_xy**2
        A_safe = torch.where(conic, A, torch.ones_like(A))
        B = row[:, 2] * e[:, 2] - R2 * (row[:, :2] * e[:, :2]).sum(-1)
        C = row[:, 2] ** 2 - R2 * (row[:, :2] ** 2).sum(-1)
        mid = B / A_safe
        half = (mid**2 - C / A_safe).clamp_min(0).sqrt()
        # interval bound where the disk crosses the near plane
        n_half = R * row[:, :2].norm(dim=-1)
        lo, hi = _interval_ratio_bounds(
            (row[:, 2] - n_half, row[:, 2] + n_half), (z_lo.clamp_min(near), z_hi.clamp_min(near))
        )
        out.append((torch.where(conic, mid - half, lo), torch.where(conic, mid + half, hi)))
    (x0, x1), (y0, y1) = out
    return x0, y0, x1, y1, nonempty


def pixel_support_bounds(
    ray_transform: torch.Tensor,  # [N, 3, 3]
    opacities: torch.Tensor,  # [N]
    near: float,
    lowpass_sigma_px: float = LOWPASS_SIGMA_PX,
) -> torch.Tensor:  # [N, 4] float64 (x_min, y_min, x_max, y_max) in full-image pixels; empty: min > max
    """Conservative pixel box of every splat's support (module docstring) for a low-pass filter of
    ``lowpass_sigma_px``. Splats that can never reach alpha 1/255 or whose transform is not finite get an
    empty box."""
    T = ray_transform.detach().to(torch.float64)
    o = opacities.detach().to(torch.float64)
    alive = (o >= ALPHA_MIN * (1 - 1e-6)) & torch.isfinite(T).flatten(1).all(-1) & torch.isfinite(o)
    R2 = 2 * torch.log((o / ALPHA_MIN).clamp_min(1.0))
    R2 = R2 * (1 + RHO_MARGIN) + RHO_MARGIN
    T = torch.where(alive[:, None, None], T, torch.zeros_like(T))
    x0, y0, x1, y1, disk_ok = _disk_bounds(T, R2, near)
    # low-pass disk around the projected centre
    z_c = T[:, 2, 2]
    centre_ok = z_c >= near
    z_safe = torch.where(centre_ok, z_c, torch.ones_like(z_c))
    cx, cy = T[:, 0, 2] / z_safe, T[:, 1, 2] / z_safe
    r = (R2 / lowpass_inv_var(lowpass_sigma_px)).sqrt()
    inf = torch.full_like(cx, math.inf)

    def union(lo3: torch.Tensor, lo2: torch.Tensor, pick: str) -> torch.Tensor:
        sign = 1.0 if pick == "min" else -1.0
        v3 = torch.where(disk_ok, lo3, sign * inf)
        v2 = torch.where(centre_ok, lo2, sign * inf)
        v = torch.minimum(v3, v2) if pick == "min" else torch.maximum(v3, v2)
        return v - sign * PIXEL_MARGIN

    bounds = torch.stack(
        [union(x0, cx - r, "min"), union(y0, cy - r, "min"),
         union(x1, cx + r, "max"), union(y1, cy + r, "max")],
        dim=-1,
    )
    bounds = torch.nan_to_num(bounds, nan=math.inf, posinf=math.inf, neginf=-math.inf)
    empty = ~alive | ~(disk_ok | centre_ok)
    none = torch.tensor([math.inf, math.inf, -math.inf, -math.inf], dtype=bounds.dtype, device=bounds.device)
    bounds[empty] = none
    return bounds


def _tile_range(
    lo: torch.Tensor, hi: torch.Tensor, origin: int, n_tiles: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Inclusive tile index range [t0, t1] covering pixel coordinates [lo, hi] (t0 > t1 when none)."""
    t0 = torch.floor((lo - origin) / TILE_SIZE).clamp(-1, n_tiles).to(torch.int64).clamp_min(0)
    t1 = torch.floor((hi - origin) / TILE_SIZE).clamp(-1, n_tiles).to(torch.int64).clamp_max(n_tiles - 1)
    return t0, t1


def bin_splats(
    bounds: torch.Tensor,  # [N, 4] float64 from pixel_support_bounds
    depth: torch.Tensor,  # [N] centre depth, the sort key
    window: PixelWindow,
) -> TileBins:
    """Every (tile, splat) pair whose tile meets the splat's support, sorted by tile and then front to back by
    centre depth (stable: equal depths keep the input order)."""
    device = bounds.device
    tiles_x = -(-window.width // TILE_SIZE)
    tiles_y = -(-window.height // TILE_SIZE)
    b = bounds.clone()
    b[:, 0].clamp_(min=float(window.x0))  # clip to the window (keeps empty boxes empty)
    b[:, 1].clamp_(min=float(window.y0))
    b[:, 2].clamp_(max=float(window.x0 + window.width))
    b[:, 3].clamp_(max=float(window.y0 + window.height))
    tx0, tx1 = _tile_range(b[:, 0], b[:, 2], window.x0, tiles_x)
    ty0, ty1 = _tile_range(b[:, 1], b[:, 3], window.y0, tiles_y)
    nx = (tx1 - tx0 + 1).clamp_min(0)
    ny = (ty1 - ty0 + 1).clamp_min(0)
    nx = torch.where(b[:, 0] <= b[:, 2], nx, torch.zeros_like(nx))
    ny = torch.where(b[:, 1] <= b[:, 3], ny, torch.zeros_like(ny))
    counts = nx * ny  # [N]
    # order splats front to back first, so that a stable sort by tile keeps depth order within tiles
    order = torch.sort(depth.detach().to(torch.float64), stable=True).indices  # [N]
    counts_o = counts[order]
    total = int(counts_o.sum())
    pair_splat = torch.repeat_interleave(order, counts_o)  # [M]
    starts = torch.cumsum(counts_o, 0) - counts_o
    k = torch.arange(total, device=device) - torch.repeat_interleave(starts, counts_o)
    nx_p, tx0_p, ty0_p = nx[pair_splat], tx0[pair_splat], ty0[pair_splat]
    tile = (ty0_p + k // nx_p.clamp_min(1)) * tiles_x + tx0_p + k % nx_p.clamp_min(1)
    tile_sorted, perm = torch.sort(tile, stable=True)
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(torch.bincount(tile_sorted, minlength=tiles_x * tiles_y), 0)
    return TileBins(offsets=offsets, splat_ids=pair_splat[perm], bounds=bounds,
                    window=window, tiles_x=tiles_x, tiles_y=tiles_y)
