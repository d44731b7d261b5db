"""Deferred shading geometry and the compositing of Eq. 7-9.

Everything is per pixel, in world space (z up, metres), with OpenCV camera axes. ``depth`` is the rendered
depth along the camera z axis (as the rasterizer returns it), so a surface point is the camera centre plus
depth times the ray whose camera-frame z component is 1.
"""

from __future__ import annotations

import torch
from torch import Tensor

#: Below this length a rendered normal counts as missing (pixels with alpha 0 render a zero normal).
NORMAL_EPS = 1e-6


def safe_normalize(v: Tensor, eps: float = NORMAL_EPS) -> Tensor:  # [..., 3] -> [..., 3]
    """v / |v|, and 0 where |v| < eps (no NaN in value or gradient for zero vectors)."""
    sq = (v * v).sum(-1, keepdim=True)
    ok = sq > eps * eps
    inv = torch.rsqrt(torch.where(ok, sq, torch.ones_like(sq)))
    return torch.where(ok, v * inv, torch.zeros_like(v))


def pixel_rays(
    K: Tensor,  # [3, 3]
    cam_from_world: Tensor,  # [4, 4]
    window: tuple[int, int, int, int],  # (x0, y0, width, height) in pixels
) -> tuple[Tensor, Tensor]:
    """Rays through pixel centres (x + 0.5, y + 0.5) of ``window``.

    Returns the camera centre [3] and world-space rays [H, W, 3] scaled so that their camera-frame z
    component is 1: ``centre + depth * ray`` is the point at camera depth ``depth``."""
    x0, y0, w, h = window
    dt, dev = K.dtype, K.device
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=dt, device=dev) + (y0 + 0.5),
        torch.arange(w, dtype=dt, device=dev) + (x0 + 0.5),
        indexing="ij",
    )
    pix = torch.stack([xs, ys, torch.ones_like(xs)], dim=-1)  # [H, W, 3]
    # inv_ex: inv's result without its check for a singular matrix, a read of the device that would make every
    # step wait for it on CUDA (a camera's K is never singular)
    d_cam = pix @ torch.linalg.inv_ex(K).inverse.T  # [H, W, 3], z = 1
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    centre = -(R.T @ t)
    return centre, d_cam @ R  # d_world = R^T d_cam, written row-wise


def surface_points(
    centre: Tensor, rays: Tensor, depth: Tensor
) -> Tensor:  # [3], [H, W, 3], [H, W] -> [H, W, 3]
    """X_r = camera centre + depth * ray: the surface point that reflects into each pixel (section 3.2.2)."""
    return centre + depth.unsqueeze(-1) * rays


def directions_to_camera(rays: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
    """w_o: the unit direction from the surface toward the camera (opposite to the viewing ray)."""
    return -safe_normalize(rays)


def cos_theta(normal: Tensor, w_o: Tensor) -> Tensor:  # [..., 3], [..., 3] -> [...]
    """cos of the angle between the unit normal and w_o, clamped to [0, 1].

    A normal facing away from the camera (cos < 0) is treated as grazing (cos = 0): Schlick's formula is
    only defined on the front side, and a clamp keeps F in [F0, 1]."""
    return (normal * w_o).sum(-1).clamp(0.0, 1.0)


def schlick_fresnel(f0: Tensor, cos_t: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
    """Schlick's approximation F = F0 + (1 - F0)(1 - cos theta)^5 (Eq. 8)."""
    return f0 + (1.0 - f0) * (1.0 - cos_t).clamp(0.0, 1.0).pow(5).unsqueeze(-1)


def reflect(w_o: Tensor, normal: Tensor) -> Tensor:  # [..., 3], [..., 3] -> [..., 3]
    """The reflection direction w_r = 2 (w_o . n) n - w_o, unit (Eq. 9, written with the outgoing direction:
    the mirror of w_o about n). With a zero normal (no surface) it is -w_o, the continuing viewing ray."""
    d = (w_o * normal).sum(-1, keepdim=True)
    return safe_normalize(2.0 * d * normal - w_o)


def normalize_to_bounds(x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
    """Map points into [-1, 1]^3 by the facade's bounding box [lo, hi] (section 3.2.2), clamped so that a
    point off the facade (a pixel with no surface) stays inside the encoding's range."""
    span = (hi - lo).clamp_min(1e-6)
    return (2.0 * (x - lo) / span - 1.0).clamp(-1.0, 1.0)


def composite(diffuse: Tensor, refl: Tensor, fresnel: Tensor, specular: Tensor) -> Tensor:
    """I = (1 - refl) D + refl F R (Eq. 7).

    ``diffuse``, ``fresnel``, ``specular`` [..., 3]; ``refl`` [...]."""
    r = refl.unsqueeze(-1)
    return (1.0 - r) * diffuse + r * fresnel * specular
