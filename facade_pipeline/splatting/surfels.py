"""Per-splat projection of 2D Gaussians (surfels) into one pinhole camera (paper Eq. 1, 2 and 4).

Frames: splat centres, tangents and normals in the world frame (metres); the camera is ``cam_from_world``
[4, 4] with OpenCV axes (x right, y down, z forward) and ``K`` [3, 3] in pixels, pixel centres at +0.5.
Everything here is plain differentiable torch; the rasterizers take the ray transform from here.
"""

from __future__ import annotations

import torch

from facade_pipeline.splatting.types import ProjectedSurfels

QUAT_EPS = 1e-12
"""A zero quaternion would divide by zero; its norm is clamped to this (giving the identity rotation)."""


def quaternion_to_rotation(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] from quaternions [N, 4] (w, x, y, z), normalised here.

    Columns are the splat's tangent t_u, tangent t_v and normal t_u x t_v in the world frame."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(QUAT_EPS)  # [N, 4]
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))


def project_surfels(
    means: torch.Tensor,  # [N, 3] world
    quats: torch.Tensor,  # [N, 4] (w, x, y, z)
    scales: torch.Tensor,  # [N, 2] metres along t_u, t_v
    cam_from_world: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
) -> ProjectedSurfels:
    """The ray transform T = K [s_u R t_u | s_v R t_v | R p + t] (R, t from ``cam_from_world``), the world
    normal flipped to face the camera centre o (n . (o - p) >= 0) and the centre depth (sort key)."""
    n = means.shape[0]
    rot = quaternion_to_rotation(quats)  # [N, 3, 3]
    R_cw, t_cw = cam_from_world[:3, :3], cam_from_world[:3, 3]  # [3, 3], [3]
    # rows of local_to_cam^T: s_u t_u and s_v t_v (directions) and p (a point), all in the camera frame;
    # plain 2D matrix products (batched 3x3 products are slow on CPU)
    tangents = (rot[:, :, :2] * scales[:, None, :]).transpose(1, 2)  # [N, 2, 3] world s_u t_u, s_v t_v
    tangents_cam = (tangents.reshape(-1, 3) @ R_cw.T).reshape(n, 2, 3)  # [N, 2, 3]
    centre_cam = means @ R_cw.T + t_cw  # [N, 3]
    local_to_cam_t = torch.cat([tangents_cam, centre_cam[:, None, :]], dim=1)  # [N, 3 (u, v, 1), 3 (xyz)]
    ray_transform = (local_to_cam_t.reshape(-1, 3) @ K.T).reshape(n, 3, 3).transpose(1, 2)  # [N, 3, 3]
    camera_centre = -R_cw.T @ t_cw  # [3] world
    normal = rot[:, :, 2]  # [N, 3]
    facing = ((camera_centre - means) * normal).sum(-1) >= 0  # [N]
    sign = torch.where(facing, 1.0, -1.0).to(normal.dtype).detach()
    return ProjectedSurfels(
        ray_transform=ray_transform,
        normal_world=normal * sign[:, None],
        depth=centre_cam[:, 2].detach(),
    )
