"""A proxy of the near-field environment for the reflection MLP: where a reflected ray lands.

A glass facade mirrors what stands in front of it: the ground at its foot (roads, lawns, courts), nearby
buildings and trees, the sky. The paper's MLP sees the surface point X_r and the direction w_r and has to
learn, from a few dozen views, that rays from different points meeting on the same patch of ground carry the
same colour; on a CPU budget it learns the mean colour and little else (benchmarks/RESULTS.md). Here each ray
is cast against the surroundings as photogrammetry reconstructs them in the coarse point cloud
(``shading.surroundings``: a surface model of its trees and buildings, and the ground at the facade's foot),
out to ``proxy_reach_m`` from the facade's centre. Learnable feature maps on the floor (x, y) and on a wall
around the eye (azimuth, elevation angle; the sky above what stands there) are read at the hit, and the MLP
gets them beside gamma(X_r) and gamma(w_r). Rays from many views that meet on the same spot read the same
texels, whatever their direction: parallax is right by construction for everything in the surface model,
and each texel learns at the rate of a splat colour rather than through the MLP's weights.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from facade_pipeline.shading.surroundings import Surroundings

#: The surface model and the floor reach this many times the facade bounds' horizontal half-diagonal from
#: their centre (1.5 times a cylinder of twice it, the reach every proxy figure in benchmarks/RESULTS.md was
#: measured with); beyond it the floor maps are clamped.
REACH_FACTOR = 3.0


def proxy_reach_m(lo: Tensor, hi: Tensor) -> float:
    """How far from the centre of the facade bounds [lo, hi] (m) the proxy reaches (m)."""
    lo_, hi_ = lo.detach().double().cpu(), hi.detach().double().cpu()
    return REACH_FACTOR * float(0.5 * (hi_[:2] - lo_[:2]).norm())


class ProxyFeatures(nn.Module):
    """Learnable multi-resolution feature maps on the proxy's floor and wall, read bilinearly where the
    rays meet ``surroundings``.

    ``levels`` maps per part, each a quarter of the resolution of the one before and summed; the floor's
    finest is ``resolution`` x ``resolution`` texels over its diameter, the wall's ``resolution`` around by
    ``resolution / 4`` up. Output per ray: floor features where it hits the floor (else 0), wall features
    where it hits the surroundings or the sky (else 0) and a 0/1 floor flag: ``2 channels + 1`` values. The
    surroundings' heights are saved with the maps."""

    def __init__(
        self,
        surroundings: Surroundings,
        channels: int,
        resolution: int,
        levels: int,
        init_std: float,
    ):
        super().__init__()
        if channels < 1 or levels < 1 or resolution >> (2 * (levels - 1)) < 4:
            raise ValueError(
                f"proxy features need channels >= 1, levels >= 1 and a coarsest map of at least 4 texels, "
                f"got channels={channels}, resolution={resolution}, levels={levels}"
            )
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
        on_floor, floor_uv, wall_uv = self.surroundings.hit(x, w)
        f = on_floor.unsqueeze(-1).to(x.dtype)
        return torch.cat(
            [f * self._sample(self.floor, floor_uv), (1.0 - f) * self._sample(self.wall, wall_uv), f], dim=-1
        )
