"""Per-view corrections: the rotation's exponential map, how a correction is applied, and the alignment
of a view to a frozen model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from facade_pipeline.training.corrections import ViewCorrections, align_view, so3_exp
from facade_pipeline.training.params import AlignParams


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
    poses = ViewCorrections(3, "cpu")
    assert torch.equal(poses.cam_from_world(1, M), M)  # zero correction: the imported pose, bit for bit
    with torch.no_grad():
        poses.rotation[2] = torch.tensor([0.0, 0.0, 0.01])
        poses.translation[2] = torch.tensor([0.05, 0.0, -0.02])
    D = torch.eye(4)
    D[:3, :3] = torch.as_tensor(Rotation.from_rotvec([0.0, 0.0, 0.01]).as_matrix(), dtype=torch.float32)
    D[:3, 3] = torch.tensor([0.05, 0.0, -0.02])
    assert torch.allclose(poses.cam_from_world(2, M), D @ M, atol=1e-6)
    assert torch.equal(poses.cam_from_world(0, M), M)


def _blob_renderer(points: torch.Tensor, colors: torch.Tensor, f: float, size: int, sigma_px: float = 2.5):
    """A tiny differentiable "model": coloured Gaussian blobs at projected 3D points, blended by weight."""
    ys, xs = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32),
                            indexing="ij")  # fmt: skip

    def render(M: torch.Tensor) -> torch.Tensor:
        pc = points @ M[:3, :3].T + M[:3, 3]
        u = f * pc[:, 0] / pc[:, 2] + size / 2
        v = f * pc[:, 1] / pc[:, 2] + size / 2
        d2 = (xs[..., None] - u) ** 2 + (ys[..., None] - v) ** 2  # [H, W, P]
        w = torch.exp(-0.5 * d2 / sigma_px**2)
        return (w @ colors) / (1.0 + w.sum(-1, keepdim=True))

    return render


def _scene():
    g = torch.Generator().manual_seed(0)
    points = torch.cat([torch.rand(40, 2, generator=g) * 4 - 2, 5 + torch.rand(40, 1, generator=g)], 1)
    colors = torch.rand(40, 3, generator=g) * 0.8 + 0.2
    return points, colors


def test_alignment_recovers_a_perturbed_pose_and_gain():
    points, colors = _scene()
    render = _blob_renderer(points, colors, f=40.0, size=48)
    M = torch.eye(4)
    truth = ViewCorrections(1, "cpu", pose=True, exposure=True)
    with torch.no_grad():
        truth.rotation[0] = torch.tensor([0.004, -0.006, 0.01])
        truth.translation[0] = torch.tensor([0.04, -0.03, 0.05])
        truth.log_gain[0] = torch.log(torch.tensor([1.2, 0.9, 1.05]))
        image = truth.expose(0, render(truth.cam_from_world(0, M)))
    mask = torch.ones(48, 48, dtype=torch.bool)
    params = AlignParams(steps=300, lr_rotation=1e-3, lr_translation=5e-3, lr_exposure=0.01, exposure=True)
    fit = align_view(render, M, image, mask, params)
    assert fit.loss_after < 0.05 * fit.loss_before
    np.testing.assert_allclose(fit.gain.numpy(), [1.2, 0.9, 1.05], rtol=0.02)
    assert torch.allclose(fit.cam_from_world, truth.cam_from_world(0, M).detach(), atol=5e-3)
    assert fit.rotation_deg == pytest.approx(np.degrees(np.linalg.norm([0.004, -0.006, 0.01])), rel=0.1)


def test_alignment_never_worse_than_the_given_pose_and_leaves_the_model_alone():
    """A rate that makes Adam overshoot wildly: the returned correction is the best one seen (at worst the
    given pose). The frozen tensors get no gradient and are trainable again afterwards."""
    points, colors = _scene()
    colors.requires_grad_(True)
    render = _blob_renderer(points, colors, f=40.0, size=32)
    M = torch.eye(4)
    with torch.no_grad():
        image = render(M)
    mask = torch.ones(32, 32, dtype=torch.bool)
    params = AlignParams(steps=5, lr_rotation=1.0, lr_translation=10.0, lr_exposure=5.0, exposure=True)
    fit = align_view(render, M, image, mask, params, frozen=[colors])
    assert fit.loss_after <= fit.loss_before < 1e-6
    assert torch.equal(fit.cam_from_world, M) and torch.equal(fit.gain, torch.ones(3))
    assert colors.grad is None and colors.requires_grad
    empty = align_view(render, M, image, torch.zeros_like(mask), params)  # nothing to align on
    assert torch.equal(empty.cam_from_world, M) and empty.rotation_deg == 0.0
    none = align_view(render, M, image, mask, dataclasses.replace(params, steps=0, exposure=False))
    assert torch.equal(none.cam_from_world, M) and torch.equal(none.gain, torch.ones(3))


def test_alignment_takes_a_pose_that_carries_autograd_history():
    """A pose computed from a trainable correction (a trainer's refined camera, outside ``no_grad``) is a
    starting point: the fit neither backpropagates into its history (which would fail at the second step)
    nor hands gradients back to the correction that made it."""
    points, colors = _scene()
    render = _blob_renderer(points, colors, f=40.0, size=32)
    refined = ViewCorrections(1, "cpu", pose=True, exposure=False)
    with torch.no_grad():
        refined.rotation[0] = torch.tensor([0.0, 0.003, -0.004])
        image = render(torch.eye(4))
    M = refined.cam_from_world(0, torch.eye(4))
    assert M.requires_grad
    mask = torch.ones(32, 32, dtype=torch.bool)
    params = AlignParams(steps=20, lr_rotation=1e-3, lr_translation=5e-3, lr_exposure=0.01, exposure=False)
    fit = align_view(render, M, image, mask, params)
    assert fit.loss_after < fit.loss_before
    assert not fit.cam_from_world.requires_grad
    assert refined.rotation.grad is None
