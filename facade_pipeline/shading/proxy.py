"""A proxy of the near-field environment for the reflection MLP: where a reflected ray lands.

A glass facade mirrors what stands in front of it: the ground at its foot (roads, lawns, courts), nearby
buildings and trees, the sky. The paper's MLP sees the surface point X_r and the direction w_r and has to
learn, from a few dozen views, that rays from different points meeting on the same patch of ground carry the
same colour; on a CPU budget it learns the mean colour and little else (benchmarks/RESULTS.md). Here each ray
is intersected with a simple proxy of the surroundings, a cylindrical "room" around the facade:

- a floor, the ground plane at the facade's foot (z = ground_z), out to ``radius`` from the facade's centre;
- a wall, the vertical cylinder of that radius, of unbounded height (the sky lies on it at high elevations).

Every ray from a point inside hits exactly one of them. Learnable feature maps on the floor (x, y) and on
the wall (azimuth, elevation angle) are read at the hit, and the MLP gets them beside gamma(X_r) and
gamma(w_r). Rays from many views that meet on the same spot of ground read the same texels, whatever their
direction: parallax is right by construction for everything that lies on the proxy and approximately right
near it, and each texel learns at the rate of a splat colour rather than through the MLP's weights.

With ``surroundings`` the rays meet the trees and buildings reconstructed in the coarse point cloud instead of
the wall (``shading.surroundings``: a surface model), so that parallax is right for them too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from facade_pipeline.shading.surroundings import Surroundings

#: Below this, a ray's horizontal (vertical) component counts as zero: it never meets the wall (floor).
_EPS = 1e-6


@dataclass(frozen=True)
class ProxyGeometry:
    """The cylindrical room, in metres in the training frame (z up)."""

    centre_xy: tuple[float, float]
    ground_z: float
    radius: float

    @staticmethod
    def around(lo: Tensor, hi: Tensor, radius: float = 0.0) -> ProxyGeometry:
        """The room around a facade with bounds [lo, hi]: centred on them, floor at their bottom; radius
        ``radius`` or, when 0, twice the bounds' horizontal half-diagonal."""
        lo_, hi_ = lo.detach().double().cpu(), hi.detach().double().cpu()
        c = 0.5 * (lo_ + hi_)
        half = float(0.5 * (hi_[:2] - lo_[:2]).norm())
        r = radius if radius > 0 else 2.0 * half
        if not r > half:
            raise ValueError(f"proxy radius {r:.3g} m must exceed the facade's half-diagonal {half:.3g} m")
        return ProxyGeometry((float(c[0]), float(c[1])), float(lo_[2]), float(r))

    def hit(self, x: Tensor, w: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Intersect rays x + t w (t > 0; x [P, 3] inside the room, w [P, 3] unit).

        Returns ``on_floor`` [P] bool, the floor coordinates [P, 2] ((x, y) - centre) / radius in [-1, 1],
        and the wall coordinates [P, 2] (azimuth / pi, 2 elevation / (pi / 2) - 1) in [-1, 1], where the
        elevation is that of the hit seen from the floor's rim, atan((z - ground) / radius). Each set is
        meaningful only where the ray hits that part; values are finite everywhere, gradients too."""
        c = x.new_tensor(self.centre_xy)
        rel = x[:, :2] - c  # [P, 2]
        height = (x[:, 2] - self.ground_z).clamp_min(0.0)
        wxy = w[:, :2]
        # Wall: |rel + t wxy| = radius, the positive root (rel is inside, so the product of roots is < 0).
        a = (wxy * wxy).sum(-1)
        horizontal = a > _EPS * _EPS
        a_safe = torch.where(horizontal, a, torch.ones_like(a))
        b = (rel * wxy).sum(-1)
        cc = (rel * rel).sum(-1) - self.radius**2  # < 0 inside
        disc = (b * b - a_safe * cc).clamp_min(_EPS)  # > 0 for points inside the room
        t_wall = torch.where(horizontal, (-b + disc.sqrt()) / a_safe, torch.full_like(a, math.inf))
        # Floor: z + t w_z = ground, for rays going down.
        down = w[:, 2] < -_EPS
        wz_safe = torch.where(down, w[:, 2], -torch.ones_like(a))
        t_floor = torch.where(down, height / -wz_safe, torch.full_like(a, math.inf))
        on_floor = t_floor < t_wall
        t_f = torch.where(on_floor, t_floor, torch.zeros_like(a))
        floor_uv = ((rel + t_f.unsqueeze(-1) * wxy) / self.radius).clamp(-1.0, 1.0)
        # Wall coordinates: the hit's azimuth about the centre and its elevation seen from the rim; a vertical
        # ray (no wall hit at finite t) goes to the top row with the azimuth of its own tiny x, y.
        t_w = torch.where(horizontal & ~on_floor, t_wall, torch.zeros_like(a))
        p = rel + t_w.unsqueeze(-1) * wxy
        p = torch.where(horizontal.unsqueeze(-1), p, wxy + _EPS)
        pole = p.abs().sum(-1) < _EPS
        px = torch.where(pole, torch.full_like(a, _EPS), p[:, 0])
        azimuth = torch.atan2(p[:, 1], px) / math.pi
        z_hit = height + t_w * w[:, 2]
        elevation = torch.where(
            horizontal, torch.atan2(z_hit, torch.full_like(a, self.radius)), torch.full_like(a, math.pi / 2)
        )
        wall_uv = torch.stack([azimuth, 4.0 * elevation / math.pi - 1.0], dim=-1).clamp(-1.0, 1.0)
        return on_floor, floor_uv, wall_uv


class ProxyFeatures(nn.Module):
    """Learnable multi-resolution feature maps on the proxy's floor and wall, read bilinearly at the hits.

    ``levels`` maps per part, each a quarter of the resolution of the one before and summed; the floor's
    finest is ``resolution`` x ``resolution`` texels over its diameter, the wall's ``resolution`` around by
    ``resolution / 4`` up. Output per ray: floor features where it hits the floor (else 0), wall features
    where it hits the wall (else 0) and a 0/1 floor flag: ``2 channels + 1`` values. With ``surroundings``
    the rays are cast against it (and its ground) instead of the room; its heights are saved with the maps."""

    def __init__(
        self,
        geometry: ProxyGeometry,
        channels: int,
        resolution: int,
        levels: int,
        init_std: float,
        surroundings: Surroundings | None = None,
    ):
        super().__init__()
        if channels < 1 or levels < 1 or resolution >> (2 * (levels - 1)) < 4:
            raise ValueError(
                f"proxy features need channels >= 1, levels >= 1 and a coarsest map of at least 4 texels, "
                f"got channels={channels}, resolution={resolution}, levels={levels}"
            )
        self.geometry = geometry
        self.surroundings = surroundings
        self.channels = channels
        sizes = [resolution >> (2 * i) for i in range(levels)]
        self.floor = nn.ParameterList(nn.Parameter(torch.randn(1, channels, s, s) * init_std) for s in sizes)
        self.wall = nn.ParameterList(
            nn.Parameter(torch.randn(1, channels, max(2, s // 4), s) * init_std) for s in sizes
        )

    @property
    def out_dim(self) -> int:
        return 2 * self.channels + 1

    @staticmethod
    def _sample(maps: nn.ParameterList, uv: Tensor) -> Tensor:  # uv [P, 2] in [-1, 1] -> [P, C]
        grid = uv.view(1, 1, -1, 2)
        out = sum(
            F.grid_sample(m, grid, mode="bilinear", padding_mode="border", align_corners=False) for m in maps
        )
        return out.view(out.shape[1], -1).T

    def forward(self, x: Tensor, w: Tensor) -> Tensor:  # x [P, 3] metres, w [P, 3] unit -> [P, 2C + 1]
        shape = self.geometry if self.surroundings is None else self.surroundings
        on_floor, floor_uv, wall_uv = shape.hit(x, w)
        f = on_floor.unsqueeze(-1).to(x.dtype)
        return torch.cat(
            [f * self._sample(self.floor, floor_uv), (1.0 - f) * self._sample(self.wall, wall_uv), f], dim=-1
        )
