"""Brute-force dense 2DGS renderer for the tests: every splat at every pixel, float64, plain autograd.

Written for clarity and independently of the library's ray-transform formulation: each pixel's ray is
intersected with each splat's plane in the world frame. Semantics (shared/DESIGN.md "Reference 2DGS
semantics"): splats sorted by centre depth (stable); for each pixel and splat

    X = o + t d with t = n.(p - o) / n.d    (skip when n.d = 0 or a scale is 0: the splat is seen edge-on)
    u = t_u.(X - p) / s_u,  v = t_v.(X - p) / s_v,  rho_3d = u^2 + v^2
    rho_2d = |x - proj(p)|^2 / s^2 when p is beyond the near plane, else infinite (s the low-pass sigma,
             sqrt(1/2) px by default: 2 |x - proj(p)|^2 as in 2DGS)
    rho = min(rho_3d, rho_2d); depth z = camera z of X, or of p when the low-pass term wins
    alpha = min(0.99, o exp(-rho / 2)); skip when alpha < 1/255 or z < near
    stop before a splat that would bring the transmittance below 1e-4.
"""

from __future__ import annotations

import torch


def _rotation(quats: torch.Tensor) -> torch.Tensor:  # [N, 3, 3], columns t_u, t_v, n
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)  # fmt: skip
    return R


def _safe(x: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """x where ok, else 1 (a denominator that keeps masked-out branches finite under autograd)."""
    return torch.where(ok, x, torch.ones_like(x))


def render_dense(means, quats, scales, opacities, features, cam_from_world, K, width, height,
                 near=0.2, far=100.0, x0=0, y0=0, crop_w=None, crop_h=None,
                 lowpass_sigma_px=None) -> dict[str, torch.Tensor]:
    """Maps of the window [x0, x0 + crop_w) x [y0, y0 + crop_h) (default: the whole image)."""
    crop_w = width if crop_w is None else crop_w
    crop_h = height if crop_h is None else crop_h
    R_cw, t_cw = cam_from_world[:3, :3], cam_from_world[:3, 3]
    o = -R_cw.T @ t_cw  # camera centre, world
    ys, xs = torch.meshgrid(torch.arange(crop_h, dtype=means.dtype) + y0 + 0.5,
                            torch.arange(crop_w, dtype=means.dtype) + x0 + 0.5, indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(-1, 3)  # [P, 3]
    d = (pix @ torch.linalg.inv(K).T) @ R_cw  # [P, 3] world ray directions (z_cam = 1 per unit t)
    rot = _rotation(quats)
    t_u, t_v, n = rot[:, :, 0], rot[:, :, 1], rot[:, :, 2]  # [N, 3]
    n_facing = n * torch.where(((o - means) * n).sum(-1, keepdim=True) >= 0, 1.0, -1.0).detach()
    centre_cam = means @ R_cw.T + t_cw  # [N, 3]
    centre_px = centre_cam @ K.T
    order = torch.sort(centre_cam[:, 2].detach(), stable=True).indices

    P = pix.shape[0]
    T = torch.ones(P, dtype=means.dtype)
    done = torch.zeros(P, dtype=torch.bool)
    out = {"features": torch.zeros(P, features.shape[1], dtype=means.dtype), "depth_sum": torch.zeros(P),
           "normal": torch.zeros(P, 3), "median": torch.zeros(P), "distortion": torch.zeros(P),
           "M1": torch.zeros(P), "M2": torch.zeros(P)}
    out = {k: v.to(means.dtype) for k, v in out.items()}
    for i in order.tolist():
        nd = d @ n[i]  # [P]
        flat = (scales[i, 0] != 0) & (scales[i, 1] != 0)
        hit = (nd != 0) & flat
        t = (n[i] @ (means[i] - o)) / _safe(nd, hit)
        X = o + t[:, None] * d
        u = ((X - means[i]) @ t_u[i]) / _safe(scales[i, 0], flat)
        v = ((X - means[i]) @ t_v[i]) / _safe(scales[i, 1], flat)
        rho3 = torch.where(hit, u * u + v * v, torch.full_like(u, torch.inf))
        z3 = (X @ R_cw.T + t_cw)[:, 2]
        front = centre_cam[i, 2] >= near
        c = centre_px[i, :2] / _safe(centre_px[i, 2], front)
        k = 2.0 if lowpass_sigma_px is None else 1.0 / lowpass_sigma_px**2
        rho2 = torch.where(front, k * ((pix[:, :2] - c) ** 2).sum(-1), torch.full_like(u, torch.inf))
        use3 = hit & (rho3 <= rho2)
        rho = torch.where(use3, rho3, rho2)
        z = torch.where(use3, z3, centre_cam[i, 2])
        ok = (use3 | front) & torch.isfinite(rho) & (z >= near)
        rho = torch.where(ok, rho, torch.zeros_like(rho))
        alpha = torch.clamp(opacities[i] * torch.exp(-0.5 * rho), max=0.99)
        ok = ok & (alpha >= 1 / 255) & ~done
        T_next = T * (1 - alpha)
        stop = ok & (T_next < 1e-4)
        done = done | stop
        blend = ok & ~stop
        w = torch.where(blend, alpha * T, torch.zeros_like(alpha))
        z = torch.where(blend, z, torch.full_like(z, near))
        m = far / (far - near) * (1 - near / z)
        out["distortion"] = out["distortion"] + w * (m * m * (1 - T) + out["M2"] - 2 * m * out["M1"])
        out["median"] = torch.where(blend & (T > 0.5), z, out["median"])
        out["M1"] = out["M1"] + w * m
        out["M2"] = out["M2"] + w * m * m
        out["depth_sum"] = out["depth_sum"] + w * z
        out["features"] = out["features"] + w[:, None] * features[i]
        out["normal"] = out["normal"] + w[:, None] * n_facing[i]
        T = torch.where(blend, T_next, T)
    alpha = 1 - T
    has = alpha > 0
    H, W = crop_h, crop_w
    return {
        "features": out["features"].reshape(H, W, -1),
        "alpha": alpha.reshape(H, W),
        "depth_expected": torch.where(has, out["depth_sum"] / _safe(alpha, has), 0.0).reshape(H, W),
        "depth_median": out["median"].reshape(H, W),
        "normal": out["normal"].reshape(H, W, 3),
        "distortion": out["distortion"].reshape(H, W),
    }
