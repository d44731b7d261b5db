"""Fourier feature encoding of the reflection MLP's inputs (Eq. 10)."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def fourier_features(p: Tensor, levels: int) -> Tensor:  # p [P, D] -> [P, 2 * levels * D]
    """gamma(p) = (sin(2^0 pi p), cos(2^0 pi p), ..., sin(2^(L-1) pi p), cos(2^(L-1) pi p)) per coordinate
    (Eq. 10), ordered frequency-major: [sin f0, cos f0, sin f1, cos f1, ...] each over the D coordinates."""
    if levels < 1:
        raise ValueError(f"Fourier levels must be >= 1, got {levels}")
    freqs = (2.0 ** torch.arange(levels, dtype=p.dtype, device=p.device)) * math.pi  # [L]
    angles = p.unsqueeze(-2) * freqs.unsqueeze(-1)  # [P, L, D]
    return torch.stack([angles.sin(), angles.cos()], dim=-2).flatten(-3)  # [P, L * 2 * D]


def fourier_dim(levels: int, dims: int = 3) -> int:
    return 2 * levels * dims
