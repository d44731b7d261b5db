"""Per-view camera pose corrections learnt with the splats (``pose_refinement``).

Photogrammetric poses carry errors of centimetres and hundredths of a degree. Splats fitted to slightly
misregistered views blur the frames' edges and, given more capacity, fit each view's misregistration and
generalise worse. A correction per view, a small rotation and translation applied in the camera frame,
``cam_from_world' = [exp(omega) | t] @ cam_from_world``, is optimised by the photometric loss. Views never
trained on (the held-out ones) keep a zero correction: their poses stay as imported.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

#: Below this squared angle (rad^2) the rotation uses its Taylor series (exact to float64 rounding).
_SMALL = 1e-8


def so3_exp(omega: Tensor) -> Tensor:  # [..., 3] axis-angle (rad) -> [..., 3, 3]
    """Rodrigues' formula, finite in value and gradient at omega = 0 (exactly the identity there)."""
    t2 = (omega * omega).sum(-1, keepdim=True).unsqueeze(-1)  # [..., 1, 1]
    small = t2 < _SMALL
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    t = t2_safe.sqrt()
    a = torch.where(small, 1.0 - t2 / 6.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(t)) / t2_safe)
    x, y, z = omega.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*omega.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(K)
    return eye + a * K + b * (K @ K)


class PoseCorrections(nn.Module):
    """One rotation (axis-angle, rad) and translation (m) per view, all zero at the start."""

    def __init__(self, n_views: int, device: torch.device | str):
        super().__init__()
        self.rotation = nn.Parameter(torch.zeros(n_views, 3, device=device))
        self.translation = nn.Parameter(torch.zeros(n_views, 3, device=device))

    def apply(self, index: int, cam_from_world: Tensor) -> Tensor:  # [4, 4] -> [4, 4]
        """View ``index``'s corrected pose."""
        top = torch.cat([so3_exp(self.rotation[index]), self.translation[index, :, None]], dim=1)
        bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype, device=top.device)
        return torch.cat([top, bottom]).to(cam_from_world.dtype) @ cam_from_world
