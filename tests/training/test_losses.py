"""Losses (Eq. 11-13) and schedules against slow references; empty sets; gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from facade_pipeline.training import losses
from facade_pipeline.training.schedule import at_fraction, exp_decay, step_schedule


def _img(seed: int, h: int = 24, w: int = 20) -> torch.Tensor:
    return torch.rand(h, w, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_masked_mean_empty_mask_is_zero_not_nan():
    x = _img(0).requires_grad_()
    m = torch.zeros(24, 20, dtype=torch.bool)
    v = losses.masked_mean(x, m)
    v.backward()
    assert float(v.detach()) == 0.0 and torch.isfinite(x.grad).all()


def test_ssim_matches_skimage_inside_the_border():
    a, b = _img(1, 40, 36), _img(2, 40, 36) * 0.5 + _img(1, 40, 36) * 0.5
    ours = losses.ssim_map(a, b).numpy()
    _, ref = structural_similarity(
        a.numpy(),
        b.numpy(),
        channel_axis=2,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        full=True,
    )
    ref = ref.mean(-1)
    # zero padding (ours, as 3DGS) and skimage's edge handling differ within 5 px of the border
    assert np.allclose(ours[5:-5, 5:-5], ref[5:-5, 5:-5], atol=1e-6)
    assert np.allclose(losses.ssim_map(a, a).numpy(), 1.0)


def test_high_frequency_loss_matches_a_loop_and_handles_empty_sets():
    pred, gt = _img(3), _img(4)
    mask = torch.rand(24, 20, generator=torch.Generator().manual_seed(5)) > 0.3
    tau = 0.3
    r = (pred - gt).abs().mean(-1).numpy()
    sel = (r > tau) & mask.numpy()
    expected = r[sel].sum() / (sel.sum() + 1e-6)
    assert float(losses.high_frequency_loss(pred, gt, mask, tau)) == pytest.approx(expected, rel=1e-12)
    # empty set: a perfect image, or tau above every residual: exactly 0 with a finite (zero) gradient
    p = gt.clone().requires_grad_()
    v = losses.high_frequency_loss(p, gt, mask, 0.09)
    v.backward()
    assert float(v) == 0.0 and torch.all(p.grad == 0)
    assert float(losses.high_frequency_loss(pred, gt, mask, 10.0)) == 0.0


def test_normal_prior_loss_is_mean_l1_over_valid_pixels():
    n = torch.zeros(2, 2, 3)
    n[..., 2] = 1.0
    prior = torch.zeros(2, 2, 3)
    prior[..., 1] = 1.0
    valid = torch.tensor([[True, False], [False, False]])
    assert float(losses.normal_prior_loss(n, prior, valid)) == pytest.approx(2.0)
    assert float(losses.normal_prior_loss(n, prior, torch.zeros_like(valid))) == 0.0


def test_normal_prior_loss_reads_the_rendered_normal_s_direction_only():
    """The alpha-blended normal is as long as the pixel's alpha: the prior compares its direction, so a
    half-transparent pixel whose normal points along the prior costs nothing and pulls no opacity up."""
    prior = torch.nn.functional.normalize(torch.randn(3, 4, 3), dim=-1)
    valid = torch.ones(3, 4, dtype=torch.bool)
    alpha = torch.full((3, 4, 1), 0.4, requires_grad=True)
    loss = losses.normal_prior_loss(alpha * prior, prior, valid)
    loss.backward()
    assert float(loss) == pytest.approx(0.0, abs=1e-6)
    assert float(alpha.grad.abs().max()) == pytest.approx(0.0, abs=1e-6)
    tilted = torch.nn.functional.normalize(prior + 0.3 * torch.randn(3, 4, 3), dim=-1)
    assert float(losses.normal_prior_loss(0.4 * tilted, prior, valid)) == pytest.approx(
        float(losses.normal_prior_loss(tilted, prior, valid)), rel=1e-5
    )


def test_depth_normals_of_a_plane_face_the_camera():
    # points of a tilted plane seen by a camera at the origin looking along +z (OpenCV axes)
    ys, xs = torch.meshgrid(
        torch.linspace(-1, 1, 9, dtype=torch.float64),
        torch.linspace(-1, 1, 11, dtype=torch.float64),
        indexing="ij",
    )
    normal = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64)  # facing the camera: n_z < 0
    normal = normal / normal.norm()
    z = 5.0 - (normal[0] * xs + normal[1] * ys) / normal[2]  # the plane n . (X - (0, 0, 5)) = 0
    pts = torch.stack([xs, ys, z], -1)
    dn = losses.depth_normals(pts)
    inner = dn[1:-1, 1:-1].reshape(-1, 3)
    assert torch.allclose(inner, normal.expand_as(inner), atol=1e-12)
    assert torch.all(dn[0] == 0) and torch.all(dn[:, -1] == 0)


def test_normal_consistency_zero_when_aligned():
    n = torch.zeros(5, 5, 3)
    n[..., 2] = -1
    assert float(losses.normal_consistency_loss(n, n.clone(), torch.ones(5, 5, dtype=torch.bool))) == 0.0
    assert float(losses.normal_consistency_loss(n, -n, torch.ones(5, 5, dtype=torch.bool))) == 2.0


def test_color_loss_and_psnr():
    a, b = _img(6), _img(7)
    m = torch.ones(24, 20, dtype=torch.bool)
    assert float(losses.color_loss(a, a, m, 0.2)) == pytest.approx(0.0, abs=1e-12)
    l1 = float((a - b).abs().mean())
    assert float(losses.color_loss(a, b, m, 0.0)) == pytest.approx(l1)
    mse = float(((a - b) ** 2).mean())
    assert losses.psnr(a, b, m) == pytest.approx(-10 * np.log10(mse))
    assert np.isnan(losses.psnr(a, b, ~m))
    x, y, mm = a[:7, :6].clone().requires_grad_(), b[:7, :6], m[:7, :6]
    assert torch.autograd.gradcheck(lambda x: losses.color_loss(x, y, mm, 0.2), (x,))


def test_step_schedules_of_the_paper():
    # tau 0.2 -> 0.09 and lambda_hf 1 -> 10 in 4 stages over the run
    vals = [step_schedule(0.2, 0.09, 4, it, 1000) for it in range(0, 1001, 10)]
    assert vals[0] == 0.2 and vals[-1] == pytest.approx(0.09)
    assert len(set(np.round(vals, 12))) == 4 and all(x >= y for x, y in zip(vals, vals[1:], strict=False))
    lam = [step_schedule(1.0, 10.0, 4, it, 1000) for it in (0, 249, 250, 600, 1000)]
    assert lam == [1.0, 1.0, 4.0, 7.0, 10.0]
    assert step_schedule(1.0, 10.0, 1, 900, 1000) == 1.0
    assert at_fraction(0.2333, 30000) == 6999
    assert exp_decay(1e-2, 1e-4, 0, 100) == pytest.approx(1e-2)
    assert exp_decay(1e-2, 1e-4, 100, 100) == pytest.approx(1e-4)
    assert exp_decay(1e-2, 1e-4, 50, 100) == pytest.approx(1e-3)


def test_a_clipped_channel_pulls_a_darker_render_up_and_lets_a_brighter_one_be():
    """The camera's clipping (``recorded``): in a clipped channel a render at least as bright as the photo
    costs nothing and a darker one is pulled up; unclipped channels compare the render itself."""
    gt = torch.tensor([[[1.0, 0.5, 0.99]]], dtype=torch.float64)
    clipped = torch.tensor([[[True, False, True]]])
    pred = torch.tensor([[[1.4, 0.7, 0.6]]], dtype=torch.float64, requires_grad=True)
    seen = losses.recorded(pred, gt, clipped)
    assert torch.allclose(seen, torch.tensor([[[1.0, 0.7, 0.6]]], dtype=torch.float64))
    losses.l1_loss(seen, gt, torch.ones(1, 1, dtype=torch.bool)).backward()
    assert pred.grad[0, 0, 0] == 0.0  # brighter than the clipped photo: no pull
    assert pred.grad[0, 0, 1] > 0.0  # unclipped, too bright: pulled down
    assert pred.grad[0, 0, 2] < 0.0  # clipped, darker: pulled up
    assert losses.recorded(pred, gt, None) is pred


def test_opacity_loss_pulls_facade_pixels_up_and_leaves_the_rest_alone():
    """Mean of 1 - A over the facade's pixels: its gradient is -1 / (facade pixels) on each of them and
    exactly 0 off the facade, so a pixel outside the facade is never pulled toward opaque."""
    alpha = torch.rand(5, 6, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    facade = torch.zeros(5, 6, dtype=torch.bool)
    facade[1:4, 2:5] = True
    a = alpha.clone().requires_grad_()
    loss = losses.opacity_loss(a, facade)
    loss.backward()
    values = [1.0 - float(alpha[y, x]) for y in range(5) for x in range(6) if facade[y, x]]
    assert float(loss) == pytest.approx(sum(values) / len(values), rel=1e-12)
    assert torch.all(a.grad[facade] == -1.0 / 9.0) and torch.all(a.grad[~facade] == 0.0)
    assert float(losses.opacity_loss(alpha, torch.zeros_like(facade))) == 0.0


def test_clipped_floor_pulls_the_view_independent_part_of_clipped_pixels_off_the_glass():
    """Against a loop: in a channel the photo clipped off the glass, max(0, photo - (1 - r) D), summed and
    divided by the loss pixels' channels; nothing on the glass, unclipped or outside the loss mask counts,
    and only a view-independent part below the photo is pulled (up, through D and down through r)."""
    g = torch.Generator().manual_seed(11)
    h, w = 6, 7
    diffuse = torch.rand(h, w, 3, generator=g, dtype=torch.float64) * 1.2
    refl = torch.rand(h, w, generator=g, dtype=torch.float64)
    gt = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    clipped = torch.rand(h, w, 3, generator=g) > 0.5
    gt[clipped] = 1.0
    glass = torch.rand(h, w, generator=g) > 0.6
    mask = torch.rand(h, w, generator=g) > 0.2
    d, r = diffuse.clone().requires_grad_(), refl.clone().requires_grad_()
    loss = losses.clipped_floor_loss(d, r, gt, clipped, ~glass, mask)
    total = 0.0
    for y in range(h):
        for x in range(w):
            for c in range(3):
                if clipped[y, x, c] and mask[y, x] and not glass[y, x]:
                    total += max(0.0, float(gt[y, x, c]) - (1 - float(refl[y, x])) * float(diffuse[y, x, c]))
    assert float(loss) == pytest.approx(total / (3 * int(mask.sum())), rel=1e-12) and total > 0
    loss.backward()
    base = (1 - refl).unsqueeze(-1) * diffuse
    pulled = clipped & (mask & ~glass).unsqueeze(-1) & (base < gt)
    assert torch.all(d.grad[pulled] < 0) and torch.all(d.grad[~pulled] == 0)
    assert torch.all(r.grad[pulled.any(-1)] > 0) and torch.all(r.grad[~pulled.any(-1)] == 0)
    none = torch.zeros_like(clipped)
    assert float(losses.clipped_floor_loss(diffuse, refl, gt, none, ~glass, mask)) == 0.0
