"""Real spherical harmonics up to degree 3 for the diffuse colour D of Eq. 5/7.

The basis is the standard real SH basis (constants from the closed forms of the Legendre functions), in the
sign convention common to Gaussian-splatting viewers so that a PLY's ``f_dc``/``f_rest`` mean the same thing
there. Colour = 0.5 + sum_k c_k Y_k(d), clamped at 0, with d the unit direction from the camera to the splat.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

C0 = 0.5 * math.sqrt(1.0 / math.pi)
C1 = math.sqrt(3.0 / (4.0 * math.pi))
C2 = (
    0.5 * math.sqrt(15.0 / math.pi),
    -0.5 * math.sqrt(15.0 / math.pi),
    0.25 * math.sqrt(5.0 / math.pi),
    -0.5 * math.sqrt(15.0 / math.pi),
    0.25 * math.sqrt(15.0 / math.pi),
)
C3 = (
    -0.25 * math.sqrt(35.0 / (2.0 * math.pi)),
    0.5 * math.sqrt(105.0 / math.pi),
    -0.25 * math.sqrt(21.0 / (2.0 * math.pi)),
    0.25 * math.sqrt(7.0 / math.pi),
    -0.25 * math.sqrt(21.0 / (2.0 * math.pi)),
    0.25 * math.sqrt(105.0 / math.pi),
    -0.25 * math.sqrt(35.0 / (2.0 * math.pi)),
)


def num_sh_coeffs(degree: int) -> int:
    """(degree + 1)^2 coefficients per colour channel."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:  # dirs [N, 3] unit -> [N, (degree+1)^2]
    """The real SH basis functions Y_k(d) for k < (degree+1)^2."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Diffuse colour [N, 3] from SH coefficients ``coeffs`` [N, K, 3] (K >= (degree+1)^2; higher bands
    beyond ``degree`` are ignored, which is how the active degree grows during training) and unit view
    directions ``dirs`` [N, 3]. Returns 0.5 + sum_k c_k Y_k(d), clamped at 0 (Eq. 5 colour term)."""
    k = num_sh_coeffs(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(f"need {k} SH coefficients for degree {degree}, got {coeffs.shape[-2]}")
    basis = sh_basis(degree, dirs)  # [N, K]
    rgb = (basis.unsqueeze(-1) * coeffs[:, :k, :]).sum(dim=-2) + 0.5
    return rgb.clamp_min(0.0)


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:  # [N, 3] -> [N, 3]
    """The degree-0 coefficient that reproduces ``rgb`` in every direction."""
    return (rgb - 0.5) / C0
