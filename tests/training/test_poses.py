"""Per-view pose corrections: the rotation's exponential map and how a correction is applied."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from facade_pipeline.training.poses import PoseCorrections, so3_exp


def test_so3_exp_matches_scipy_and_is_a_rotation():
    rng = np.random.default_rng(0)
    omegas = np.concatenate([rng.normal(size=(20, 3)), 1e-7 * rng.normal(size=(5, 3)), np.zeros((1, 3))])
    R = so3_exp(torch.as_tensor(omegas))
    np.testing.assert_allclose(R.numpy(), Rotation.from_rotvec(omegas).as_matrix(), atol=1e-12)
    eye = torch.eye(3, dtype=torch.float64).expand(len(omegas), 3, 3)
    assert torch.allclose(R @ R.transpose(1, 2), eye, atol=1e-12)
    assert torch.equal(so3_exp(torch.zeros(3)), torch.eye(3))  # exactly the identity at zero


def test_so3_exp_gradients_at_and_away_from_zero():
    for omega in (torch.zeros(3, dtype=torch.float64), torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)):
        assert torch.autograd.gradcheck(so3_exp, (omega.clone().requires_grad_(),))


def test_corrections_apply_in_the_camera_frame():
    M = torch.eye(4)
    M[:3, :3] = torch.as_tensor(Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix(), dtype=torch.float32)
    M[:3, 3] = torch.tensor([1.0, -2.0, 30.0])
    poses = PoseCorrections(3, "cpu")
    assert torch.equal(poses.apply(1, M), M)  # zero correction: the imported pose, bit for bit
    with torch.no_grad():
        poses.rotation[2] = torch.tensor([0.0, 0.0, 0.01])
        poses.translation[2] = torch.tensor([0.05, 0.0, -0.02])
    D = torch.eye(4)
    D[:3, :3] = torch.as_tensor(Rotation.from_rotvec([0.0, 0.0, 0.01]).as_matrix(), dtype=torch.float32)
    D[:3, 3] = torch.tensor([0.05, 0.0, -0.02])
    assert torch.allclose(poses.apply(2, M), D @ M, atol=1e-6)
    assert torch.equal(poses.apply(0, M), M)
