"""Exact tile rasterizer of 2D Gaussians in pure torch, with a recomputing backward.

Per pixel x = (x, y) (pixel centres at +0.5) and splat with ray transform rows T0, T1, T2
(types.ProjectedSurfels):

    h_x = T0 - x T2,  h_y = T1 - y T2,  c = h_x x h_y            (skip where c2 = 0: seen edge-on)
    (u, v) = (c0 / c2, c1 / c2)                                  (ray-splat intersection, paper Eq. 4)
    rho = min(u^2 + v^2, |x - c_proj|^2 / s^2)   (low-pass fallback, c_proj the projected centre, s its
                                                 sigma: sqrt(2)/2 px in 2DGS)
    z = T2 . (u, v, 1) on the ray-splat branch, T2z (the centre's depth) on the low-pass branch
    alpha = min(0.99, opacity exp(-rho / 2));  skip alpha < 1/255 and z < near
    front to back by centre depth; stop before a splat that would bring the transmittance below 1e-4.

Splats are processed per group of tiles and per depth chunk of ``chunk`` splats, as [tiles, 256 px, chunk]
tensors, carrying the per-pixel state (transmittance, distortion moments, median depth, stop flag) from chunk
to chunk. The forward keeps only each chunk's incoming state; the backward walks the chunks in reverse and
recomputes each one under autograd, so memory is bounded by one chunk plus O(pixels x chunks) of state, never
splats x pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from facade_pipeline.splatting.types import (
    ALPHA_MAX,
    ALPHA_MIN,
    LOWPASS_SIGMA_PX,
    TILE_SIZE,
    TRANSMITTANCE_MIN,
    TileBins,
    lowpass_inv_var,
)

PIX = TILE_SIZE * TILE_SIZE


@dataclass(frozen=True)
class BlendSettings:
    near: float
    """Intersections nearer than this (camera-frame z, m) are skipped."""
    far: float
    """Far plane of the NDC depth m = far / (far - near) (1 - near / z) used by the distortion term only."""
    pair_budget: int = 1 << 20
    """Elements of one [tiles, pixels, chunk] tensor: bounds the working memory."""
    chunk: int = 32
    """Splats per depth chunk."""
    lowpass_sigma_px: float = LOWPASS_SIGMA_PX
    """sigma of the screen-space low-pass Gaussian (px): rho_2d = |x - c|^2 / sigma^2."""


@dataclass
class _State:
    T: torch.Tensor  # [G, P] transmittance
    M1: torch.Tensor  # [G, P] sum w m
    M2: torch.Tensor  # [G, P] sum w m^2
    med: torch.Tensor  # [G, P] median depth so far
    done: torch.Tensor  # [G, P] bool, the pixel has stopped


def _intersect(Tc, px, py, near: float, k_lp: float, differentiable: bool):
    """rho, z and the validity mask of every (pixel, splat) pair: Tc [G, S, 9], px, py [G, P] -> [G, P, S];
    ``k_lp`` the low-pass factor of rho_2d (types.lowpass_inv_var).

    Masked pairs get finite placeholder values; when ``differentiable`` the divisions are recomputed with
    denominators replaced where masked, so that no NaN or Inf reaches autograd."""
    a0, a1, a2, b0, b1, b2, e0, e1, e2 = (Tc[:, None, :, i] for i in range(9))  # [G, 1, S]
    X, Y = px[:, :, None], py[:, :, None]  # [G, P, 1]
    hx0, hx1, hx2 = a0 - X * e0, a1 - X * e1, a2 - X * e2
    hy0, hy1, hy2 = b0 - Y * e0, b1 - Y * e1, b2 - Y * e2
    c0 = hx1 * hy2 - hx2 * hy1
    c1 = hx2 * hy0 - hx0 * hy2
    c2 = hx0 * hy1 - hx1 * hy0  # [G, P, S]
    front = e2 >= near  # [G, 1, S]
    with torch.no_grad():
        nz = c2 != 0
        c2s = torch.where(nz, c2, torch.ones_like(c2))
        rho3 = torch.where(nz, (c0 / c2s) ** 2 + (c1 / c2s) ** 2, torch.full_like(c2, torch.inf))
        ez = torch.where(front, e2, torch.ones_like(e2))
        rho2 = k_lp * ((X - a2 / ez) ** 2 + (Y - b2 / ez) ** 2)
        rho2 = torch.where(front, rho2, torch.full_like(rho2, torch.inf))
        use3 = (rho3 <= rho2) & nz
        z3 = e0 * (c0 / c2s) + e1 * (c1 / c2s) + e2
        z = torch.where(use3, z3, e2.expand_as(z3))
        ok = (use3 | front) & (z >= near) & torch.isfinite(torch.where(use3, rho3, rho2))
        use3 = use3 & ok
        use2 = ok & ~use3
    c2s = torch.where(use3, c2, torch.ones_like(c2))
    u, v = c0 / c2s, c1 / c2s
    ez = torch.where(front, e2, torch.ones_like(e2))
    rho2 = k_lp * ((X - a2 / ez) ** 2 + (Y - b2 / ez) ** 2)
    rho = torch.where(use3, u * u + v * v, torch.where(use2, rho2, torch.zeros_like(rho2)))
    z = torch.where(use3, e0 * u + e1 * v + e2, torch.where(use2, e2, torch.full_like(e2, near)))
    del differentiable  # the same expressions serve both passes; masks were computed without grad
    return rho, z, ok


def _blend_chunk(Tc, oc, fc, nc, valid, px, py, st: _State, s: BlendSettings, differentiable: bool = False):
    """Blend one depth chunk into the carried state. Returns the new state and this chunk's contributions
    to the accumulated features [G, P, F], depth [G, P], normal [G, P, 3] and distortion [G, P]."""
    rho, z, ok = _intersect(Tc, px, py, s.near, lowpass_inv_var(s.lowpass_sigma_px), differentiable)
    alpha = torch.clamp(oc[:, None, :] * torch.exp(-0.5 * rho), max=ALPHA_MAX)  # [G, P, S]
    ok = ok & valid[:, None, :] & (alpha >= ALPHA_MIN)
    alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
    log1m = torch.log1p(-alpha)
    cum = torch.cumsum(log1m, dim=2)
    T_excl = st.T[:, :, None] * torch.exp(cum - log1m)  # transmittance before each splat
    T_after = st.T[:, :, None] * torch.exp(cum)
    with torch.no_grad():
        keep = ~st.done[:, :, None] & (T_after >= TRANSMITTANCE_MIN)  # a prefix along the chunk
        done = st.done | ~keep[:, :, -1]
    w = torch.where(keep, alpha * T_excl, torch.zeros_like(alpha))  # [G, P, S]
    scale = s.far / (s.far - s.near)
    m = scale * (1 - s.near / z)  # NDC depth, z >= near where ok
    wm, wm2 = w * m, w * m * m
    M1_excl = st.M1[:, :, None] + torch.cumsum(wm, 2) - wm
    M2_excl = st.M2[:, :, None] + torch.cumsum(wm2, 2) - wm2
    dist = (w * (m * m * (1 - T_excl) + M2_excl - 2 * m * M1_excl)).sum(2)
    log_kept = torch.where(keep, log1m, torch.zeros_like(log1m)).sum(2)
    # median: z of the last blended splat whose incoming transmittance exceeds 0.5
    with torch.no_grad():
        is_med = keep & ok & (T_excl > 0.5)
        idx = torch.arange(1, is_med.shape[2] + 1, device=is_med.device)
        last = (is_med * idx).amax(2)  # [G, P], 0 when none
    z_last = torch.gather(z, 2, (last - 1).clamp_min(0)[:, :, None])[:, :, 0]
    new = _State(
        T=st.T * torch.exp(log_kept),
        M1=st.M1 + wm.sum(2),
        M2=st.M2 + wm2.sum(2),
        med=torch.where(last > 0, z_last, st.med),
        done=done,
    )
    feats = torch.einsum("gps,gsf->gpf", w, fc)
    normal = torch.einsum("gps,gsk->gpk", w, nc)
    return new, (feats, (w * z).sum(2), normal, dist)


def _tile_pixels(bins: TileBins, tiles: torch.Tensor, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates [G, P] (full-image pixels) of the given tiles."""
    win = bins.window
    local = torch.arange(PIX, device=tiles.device)
    ty, tx = tiles // bins.tiles_x, tiles % bins.tiles_x
    px = win.x0 + tx[:, None] * TILE_SIZE + local[None, :] % TILE_SIZE + 0.5
    py = win.y0 + ty[:, None] * TILE_SIZE + local[None, :] // TILE_SIZE + 0.5
    return px.to(dtype), py.to(dtype)


def _chunk_ids(bins: TileBins, tiles: torch.Tensor, k: int, chunk: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Splat ids [G, S] of depth chunk k of each tile, and their validity (lists end at different lengths)."""
    start, end = bins.offsets[tiles], bins.offsets[tiles + 1]
    pos = start[:, None] + k * chunk + torch.arange(chunk, device=tiles.device)[None, :]
    valid = pos < end[:, None]
    ids = bins.splat_ids[torch.where(valid, pos, torch.zeros_like(pos))]
    return torch.where(valid, ids, torch.zeros_like(ids)), valid


def _tile_groups(bins: TileBins, s: BlendSettings) -> list[torch.Tensor]:
    """Non-empty tiles, longest lists first, in groups of at most pair_budget / (256 * chunk) tiles."""
    counts = bins.offsets[1:] - bins.offsets[:-1]
    order = torch.argsort(counts, descending=True, stable=True)
    order = order[counts[order] > 0]
    per_group = max(1, s.pair_budget // (PIX * s.chunk))
    return list(torch.split(order, per_group))


def _initial_state(G: int, like: torch.Tensor) -> _State:
    zeros = torch.zeros(G, PIX, dtype=like.dtype, device=like.device)
    return _State(T=torch.ones_like(zeros), M1=zeros, M2=zeros.clone(), med=zeros.clone(),
                  done=torch.zeros(G, PIX, dtype=torch.bool, device=like.device))


def _forward(Tm, opac, feat, nrm, bins: TileBins, s: BlendSettings):
    """Run every group and chunk; returns per-tile maps and the saved incoming states for the backward."""
    n_tiles = bins.tiles_x * bins.tiles_y
    F = feat.shape[1]
    out_F = Tm.new_zeros(n_tiles, PIX, F)
    out_D, out_dist, out_med = (Tm.new_zeros(n_tiles, PIX) for _ in range(3))
    out_T = Tm.new_ones(n_tiles, PIX)
    out_N = Tm.new_zeros(n_tiles, PIX, 3)
    saved = []  # (tiles, k, state_in) per processed chunk
    counts = bins.offsets[1:] - bins.offsets[:-1]
    for group in _tile_groups(bins, s):
        st = _initial_state(len(group), Tm)
        px, py = _tile_pixels(bins, group, Tm.dtype)
        rows = torch.arange(len(group), device=Tm.device)  # rows of st for the active tiles
        k = 0
        while len(rows) > 0:
            tiles = group[rows]
            ids, valid = _chunk_ids(bins, tiles, k, s.chunk)
            st_in = _State(st.T[rows], st.M1[rows], st.M2[rows], st.med[rows], st.done[rows])
            saved.append((tiles, k, st_in))
            new, (cF, cD, cN, cDist) = _blend_chunk(
                Tm[ids], opac[ids], feat[ids], nrm[ids], valid, px[rows], py[rows], st_in, s)
            st.T[rows], st.M1[rows], st.M2[rows], st.med[rows], st.done[rows] = (
                new.T, new.M1, new.M2, new.med, new.done)
            out_F[tiles] += cF
            out_D[tiles] += cD
            out_N[tiles] += cN
            out_dist[tiles] += cDist
            k += 1
            more = (counts[tiles] > k * s.chunk) & ~new.done.all(1)
            rows = rows[more]
        out_T[group], out_med[group] = st.T, st.med
    return (out_F, out_T, out_D, out_N, out_med, out_dist), saved


def _backward(Tm, opac, feat, nrm, bins: TileBins, s: BlendSettings, saved, grads):
    """Reverse walk over the saved chunks, recomputing each under autograd (exact gradients)."""
    gF, gT, gD, gN, gMed, gDist = grads  # per tile [n_tiles, P(, C)]; gT = dL/d(final transmittance)
    dTm, dop, dfeat, dnrm = (torch.zeros_like(x) for x in (Tm, opac, feat, nrm))
    g_state = {"T": gT.clone(), "M1": torch.zeros_like(gT), "M2": torch.zeros_like(gT), "med": gMed.clone()}
    for tiles, k, st_in in reversed(saved):
        ids, valid = _chunk_ids(bins, tiles, k, s.chunk)
        px, py = _tile_pixels(bins, tiles, Tm.dtype)
        leaves = [x[ids].detach().requires_grad_() for x in (Tm, opac, feat, nrm)]
        st_leaves = [t.detach().clone().requires_grad_() for t in (st_in.T, st_in.M1, st_in.M2, st_in.med)]
        with torch.enable_grad():
            new, contrib = _blend_chunk(*leaves, valid, px, py, _State(*st_leaves, st_in.done), s, True)
            outs = [new.T, new.M1, new.M2, new.med, *contrib]
            g_outs = [g_state[key][tiles] for key in ("T", "M1", "M2", "med")]
            g_outs += [gF[tiles], gD[tiles], gN[tiles], gDist[tiles]]
            got = torch.autograd.grad(outs, leaves + st_leaves, g_outs, allow_unused=True)
        got = [torch.zeros_like(x) if g is None else g for g, x in zip(got, leaves + st_leaves, strict=True)]
        flat = ids.reshape(-1)
        for acc, g in zip((dTm, dop, dfeat, dnrm), got[:4], strict=True):
            acc.index_add_(0, flat, g.reshape((flat.shape[0],) + acc.shape[1:]))
        for key, g in zip(("T", "M1", "M2", "med"), got[4:], strict=True):
            g_state[key][tiles] = g
    return dTm, dop, dfeat, dnrm


def tiles_to_image(x: torch.Tensor, bins: TileBins) -> torch.Tensor:
    """[n_tiles, 256, ...] tile-major maps -> [H, W, ...] image of the window."""
    rest = x.shape[2:]
    img = x.reshape((bins.tiles_y, bins.tiles_x, TILE_SIZE, TILE_SIZE) + rest)
    img = img.transpose(1, 2).reshape((bins.tiles_y * TILE_SIZE, bins.tiles_x * TILE_SIZE) + rest)
    return img[: bins.window.height, : bins.window.width]


def image_to_tiles(img: torch.Tensor, bins: TileBins) -> torch.Tensor:
    """Inverse of tiles_to_image, padding the partial tiles with zeros."""
    rest = img.shape[2:]
    H, W = bins.tiles_y * TILE_SIZE, bins.tiles_x * TILE_SIZE
    full = img.new_zeros((H, W) + rest)
    full[: img.shape[0], : img.shape[1]] = img
    x = full.reshape((bins.tiles_y, TILE_SIZE, bins.tiles_x, TILE_SIZE) + rest).transpose(1, 2)
    return x.reshape((bins.tiles_y * bins.tiles_x, PIX) + rest)


class _TorchBlend(torch.autograd.Function):
    @staticmethod
    def forward(ctx, Tm, opac, feat, nrm, bins: TileBins, s: BlendSettings):
        with torch.no_grad():
            maps, saved = _forward(Tm, opac, feat, nrm, bins, s)
        ctx.bins, ctx.settings, ctx.saved = bins, s, saved
        ctx.save_for_backward(Tm, opac, feat, nrm)
        return tuple(tiles_to_image(x, bins) for x in maps)

    @staticmethod
    def backward(ctx, gF, gT, gD, gN, gMed, gDist):
        Tm, opac, feat, nrm = ctx.saved_tensors
        bins = ctx.bins
        grads = tuple(image_to_tiles(g.contiguous(), bins) for g in (gF, gT, gD, gN, gMed, gDist))
        dTm, dop, dfeat, dnrm = _backward(Tm, opac, feat, nrm, bins, ctx.settings, ctx.saved, grads)
        return dTm, dop, dfeat, dnrm, None, None


def blend_torch(
    ray_transform: torch.Tensor,  # [N, 3, 3]
    opacities: torch.Tensor,  # [N]
    features: torch.Tensor,  # [N, F]
    normals: torch.Tensor,  # [N, 3]
    bins: TileBins,
    settings: BlendSettings,
) -> tuple[torch.Tensor, ...]:
    """Blend the binned splats: features [H, W, F], final transmittance [H, W], sum w z [H, W],
    normal [H, W, 3], median depth [H, W], distortion [H, W] (module docstring for the formulas)."""
    return _TorchBlend.apply(ray_transform.reshape(-1, 9), opacities, features, normals, bins, settings)
