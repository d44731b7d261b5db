"""Small random and hand-made splat scenes for the renderer tests."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

# Tolerances keyed on dtype: (outputs atol, outputs rtol, gradients relative to the largest gradient entry).
# float32 outputs are compared with the float64 dense reference at the 1e-5, plus 1e-5 relative for
# the expected depth (metres, divided by an alpha that can be as small as 1/255); float32 gradients carry
# float32 rounding through long products (ray transform, cross products, transmittance), hence 1e-3.
TOL = {torch.float64: (1e-9, 1e-9, 1e-7), torch.float32: (1e-5, 1e-5, 1e-3)}
MAP_NAMES = ("features", "alpha", "depth_expected", "depth_median", "normal", "distortion")


@dataclass(frozen=True)
class Scene:
    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4]
    scales: torch.Tensor  # [N, 2]
    opacities: torch.Tensor  # [N]
    features: torch.Tensor  # [N, F]
    cam_from_world: torch.Tensor  # [4, 4]
    K: torch.Tensor  # [3, 3]
    width: int
    height: int

    def params(self) -> list[torch.Tensor]:
        return [self.means, self.quats, self.scales, self.opacities, self.features]

    def to(self, dtype: torch.dtype) -> Scene:
        return replace(self, **{k: getattr(self, k).to(dtype) for k in
                                ("means", "quats", "scales", "opacities", "features", "cam_from_world", "K")})


def camera(width: int, height: int, f: float, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """A camera at the origin looking down +z (identity cam_from_world) with the principal point centred."""
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def random_scene(seed: int, n: int = 40, width: int = 37, height: int = 29, channels: int = 4,
                 dtype=torch.float64) -> Scene:
    """Splats 2-6 m in front of the camera, random orientations, scales 0.05-0.55 m, opacities 0.05-0.95;
    the image size is not a multiple of 16 (partial tiles)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.0, 0.8, 0.7], dtype=dtype)
    means[:, 2] += 4.0
    cw, K = camera(width, height, 0.8 * width, dtype)
    return Scene(
        means=means,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=0.05 + 0.5 * torch.rand(n, 2, generator=g, dtype=dtype),
        opacities=0.05 + 0.9 * torch.rand(n, generator=g, dtype=dtype),
        features=torch.rand(n, channels, generator=g, dtype=dtype),
        cam_from_world=cw, K=K, width=width, height=height,
    )


def quat_facing(normal: torch.Tensor) -> torch.Tensor:
    """A unit quaternion [4] (w, x, y, z) whose rotation takes local z to ``normal`` [3]."""
    n = normal / normal.norm()
    z = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype)
    axis = torch.linalg.cross(z, n)
    s, c = axis.norm(), (z * n).sum()
    if s < 1e-12:
        flip = [1.0, 0, 0, 0] if c > 0 else [0.0, 1, 0, 0]
        return torch.tensor(flip, dtype=n.dtype)
    angle = math.atan2(float(s), float(c))
    return torch.cat([torch.tensor([math.cos(angle / 2)], dtype=n.dtype), math.sin(angle / 2) * axis / s])


def hard_case(name: str) -> Scene:
    """Hand-made scenes for the issue's hard cases, mixed into a few ordinary splats (float64)."""
    base = random_scene(7, n=6, width=34, height=20)
    means, quats = base.means.clone(), base.quats.clone()
    scales, op = base.scales.clone(), base.opacities.clone()
    i = 0  # the splat made hard
    if name == "edge_on":  # plane through the camera centre and containing pixel column 17's rays
        means[i] = torch.tensor([0.0, 0.3, 3.0], dtype=means.dtype)
        quats[i] = quat_facing(torch.tensor([1.0, 0.0, 0.0], dtype=means.dtype))
    elif name == "nearly_edge_on":
        means[i] = torch.tensor([0.1, 0.0, 3.0], dtype=means.dtype)
        quats[i] = quat_facing(torch.tensor([1.0, 0.0, 1e-7], dtype=means.dtype))
    elif name == "behind_camera":
        means[i] = torch.tensor([0.2, -0.1, -2.0], dtype=means.dtype)
        means[1] = torch.tensor([0.0, 0.0, -0.1], dtype=means.dtype)
    elif name == "crossing_near_plane":
        means[i] = torch.tensor([0.1, 0.05, 0.15], dtype=means.dtype)
        quats[i] = quat_facing(torch.tensor([0.0, 1.0, 0.3], dtype=means.dtype))
        scales[i] = torch.tensor([0.5, 0.4], dtype=means.dtype)
        means[1] = torch.tensor([-0.1, 0.0, 0.3], dtype=means.dtype)
        quats[1] = quat_facing(torch.tensor([0.3, 0.2, -1.0], dtype=means.dtype))
        scales[1] = torch.tensor([0.3, 0.3], dtype=means.dtype)
    elif name == "zero_scale":
        scales[i] = 0.0
        scales[1, 0] = 0.0
    elif name == "huge_scale":
        scales[i] = torch.tensor([1e6, 3e5], dtype=means.dtype)
    elif name == "opacity_0_and_1":
        op[i], op[1], op[2] = 0.0, 1.0, 1.0
    elif name == "covers_image":
        means[i] = torch.tensor([0.0, 0.0, 2.0], dtype=means.dtype)
        quats[i] = quat_facing(torch.tensor([0.1, -0.2, -1.0], dtype=means.dtype))
        scales[i] = torch.tensor([20.0, 15.0], dtype=means.dtype)
        op[i] = 0.7
    elif name == "equal_depths":
        means[1, 2] = means[i, 2]
        means[2, 2] = means[i, 2]
        means[1, :2] = means[i, :2] + 0.05
    elif name == "far_outside":
        means[i] = torch.tensor([500.0, -300.0, 4.0], dtype=means.dtype)
        means[1] = torch.tensor([0.0, 0.0, 1e5], dtype=means.dtype)
    else:
        raise KeyError(name)
    return replace(base, means=means, quats=quats, scales=scales, opacities=op)


HARD_CASES = ("edge_on", "nearly_edge_on", "behind_camera", "crossing_near_plane", "zero_scale", "huge_scale",
              "opacity_0_and_1", "covers_image", "equal_depths", "far_outside")
