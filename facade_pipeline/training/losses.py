"""Training losses (Eq. 11-13) over a masked image window, and ``compute_losses``, their weighted sum for
one rendered window (Eq. 13): L = L_c + lambda_n L_n + lambda_np L_np + lambda_hf L_hf + lambda_o L_o, with
L_c = 0.8 L1 + 0.2 D-SSIM, the 2DGS normal consistency L_n, the normal prior L_np (Eq. 11), the
high-frequency loss L_hf (Eq. 12) and the facade's pull toward opaque L_o (ours), all over the facade mask.
Images are [H, W, 3] in [0, 1]; masks [H, W] bool. Every mean is over the pixels of its mask and returns 0
(not NaN) on an empty mask."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from facade_pipeline.shading.deferred import safe_normalize
from facade_pipeline.training.compiling import torch_compiled
from facade_pipeline.training.schedule import at_fraction, step_schedule

if TYPE_CHECKING:  # annotations only: the metrics of evaluation use these losses without the trainer's data
    from facade_pipeline.training.batches import ViewTensors
    from facade_pipeline.training.params import TrainParams
    from facade_pipeline.training.render import Render

#: Weight of D-SSIM in L_c = (1 - w) L1 + w D-SSIM: the paper's (Eq. 13, after 2DGS), never tuned here.
LAMBDA_DSSIM = 0.2
#: Normal consistency from this fraction of the run: 2DGS's 7k of 30k iterations (a fraction, so that short
#: runs keep its schedule), never tuned here.
NORMAL_START_FRACTION = 0.2333


def masked_mean(x: Tensor, mask: Tensor) -> Tensor:  # [H, W] or [H, W, C], [H, W] -> []
    """Mean of ``x`` over the pixels of ``mask`` (and its channels); 0 for an empty mask."""
    m = mask.to(x.dtype)
    if x.dim() == 3:
        m = m.unsqueeze(-1).expand_as(x)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def l1_loss(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """Mean absolute error over the masked pixels and channels."""
    return masked_mean((pred - gt).abs(), mask)


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2.0
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(3, 1, size, size).contiguous()


def ssim_map(pred: Tensor, gt: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:  # -> [H, W]
    """SSIM per pixel (Gaussian window 11 x 11, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, zero padding), averaged
    over the channels."""
    x = pred.permute(2, 0, 1).unsqueeze(0)
    y = gt.permute(2, 0, 1).unsqueeze(0)
    w = _gaussian_window(window, sigma, x.dtype, x.device)
    pad = window // 2
    mu_x = F.conv2d(x, w, padding=pad, groups=3)
    mu_y = F.conv2d(y, w, padding=pad, groups=3)
    sxx = F.conv2d(x * x, w, padding=pad, groups=3) - mu_x * mu_x
    syy = F.conv2d(y * y, w, padding=pad, groups=3) - mu_y * mu_y
    sxy = F.conv2d(x * y, w, padding=pad, groups=3) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2))
    return s[0].mean(0)


def color_loss(pred: Tensor, gt: Tensor, mask: Tensor, lambda_dssim: float) -> Tensor:
    """L_c = (1 - lambda) L1 + lambda (1 - SSIM) (2DGS, lambda = 0.2), both on the masked images (pixels
    outside the mask are zeroed in both, as the paper masks its images)."""
    m = mask.unsqueeze(-1).to(pred.dtype)
    pm, gm = pred * m, gt * m
    l1 = l1_loss(pred, gt, mask)
    if lambda_dssim == 0.0:
        return l1
    dssim = masked_mean(1.0 - ssim_map(pm, gm), mask)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * dssim


#: epsilon of Eq. 12's denominator: only keeps an empty selection at exactly 0 (the numerator is 0 there)
HF_EPS = 1e-6


def high_frequency_loss(pred: Tensor, gt: Tensor, mask: Tensor, tau: float) -> Tensor:
    """Eq. 12: the mean L1 residual over the pixels whose residual (the mean over RGB) exceeds ``tau``. The
    selection is a constant indicator (no gradient through it); an empty selection gives exactly 0."""
    r = (pred - gt).abs().mean(-1)  # [H, W]
    sel = (mask & (r.detach() > tau)).to(r.dtype)
    return (sel * r).sum() / (sel.sum() + HF_EPS)


def normal_prior_loss(normal: Tensor, prior: Tensor, valid: Tensor) -> Tensor:
    """Eq. 11: mean over valid pixels of || n - n_hat ||_1, n the direction of the rendered world normal,
    n_hat the baked one. The direction, not the alpha-blended normal itself: that one is as long as the
    pixel's accumulated alpha, so a unit prior would also pull every splat's opacity up whatever the photos
    show, and the training views' fit fell for a hundred steps under that pull (docs/method.md). The pull
    toward opaque is a term of its own, ``opacity_loss``, with its own weight."""
    return masked_mean((safe_normalize(normal) - prior).abs().sum(-1), valid)


def opacity_loss(alpha: Tensor, facade: Tensor) -> Tensor:
    """Mean over the facade's pixels of 1 - A, A the pixel's accumulated alpha: the facade is an opaque
    surface in every view, and a pixel left transparent shows the black of the masked photos, which dark
    glass matches about as well as the glass itself. Pixels off the facade are not pulled."""
    return masked_mean(1.0 - alpha, facade)


def clipped_floor_loss(
    diffuse: Tensor, refl: Tensor, gt: Tensor, clipped: Tensor, off_glass: Tensor, mask: Tensor
) -> Tensor:
    """Mean over the loss pixels ``mask`` [H, W] and channels of max(0, photo - (1 - r) D) where the photo
    ``gt`` [H, W, 3] clipped the channel (``clipped`` [H, W, 3]) off the glass (``off_glass`` [H, W]): a
    frame or wall clipped white is a diffuse surface at least that bright from every direction, so its
    view-independent part (1 - r) D (``refl`` [H, W], ``diffuse`` [H, W, 3]) must reach the photo without the
    reflection term, which on a view no training view had renders it darker (benchmarks/RESULTS.md, gcw_dev:
    "Where `mlp` loses to `sh`"). Glass is left out: what it shows clipped is a reflection, view-dependent.
    0 where nothing off the glass clipped."""
    floor = (gt - (1.0 - refl).unsqueeze(-1) * diffuse).clamp(min=0.0)
    where = clipped & (off_glass & mask).unsqueeze(-1)
    return (floor * where).sum() / (3.0 * mask.sum()).clamp_min(1.0)


def depth_normals(points: Tensor) -> Tensor:  # [H, W, 3] surface points -> [H, W, 3]
    """Normals of the surface given by per-pixel points, from central differences (the 2DGS 'surface
    normal'); unit, oriented like the image axes' cross product (toward the camera for OpenCV axes);
    zero on the border pixels and where the differences vanish."""
    out = torch.zeros_like(points)
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    n = safe_normalize(torch.cross(dy, dx, dim=-1))
    out[1:-1, 1:-1] = n
    return out


def normal_consistency_loss(normal: Tensor, surf_normal: Tensor, mask: Tensor) -> Tensor:
    """2DGS normal consistency: mean over the mask of 1 - n . N, with n the alpha-blended splat normal and
    N the normal of the rendered depth (``surf_normal``, held as a target-free geometric quantity: the
    gradient reaches both, as in 2DGS)."""
    border = torch.zeros_like(mask)
    border[1:-1, 1:-1] = True
    return masked_mean(1.0 - (normal * surf_normal).sum(-1), mask & border)


def psnr(pred: Tensor, gt: Tensor, mask: Tensor, data_range: float = 1.0) -> float:
    """PSNR (dB) over the masked pixels and all channels, 10 log10(R^2 / MSE) with MSE in float64: the one
    PSNR of the project (training logs, ``evaluation.metrics.psnr`` through its input checks). pred, gt:
    [H, W, C]; mask: [H, W] bool. +inf for a perfect match, NaN for an empty mask."""
    return float(psnr_tensor(pred, gt, mask, data_range))


def psnr_tensor(pred: Tensor, gt: Tensor, mask: Tensor, data_range: float = 1.0) -> Tensor:
    """``psnr`` as a float64 tensor on the inputs' device, for a loop that reads it only now and then."""
    d = pred.detach().double() - gt.detach().double()
    m = mask.to(d.dtype).unsqueeze(-1).expand_as(d)
    mse = (d * d * m).sum() / m.sum()  # 0 / 0: NaN for an empty mask
    return 10.0 * torch.log10(data_range * data_range / mse)


def recorded(pred: Tensor, gt: Tensor, clipped: Tensor | None) -> Tensor:
    """What the camera would record of the render ``pred`` [H, W, 3]: the render itself, except in the
    channels the photo ``gt`` clipped (``clipped`` [H, W, 3] bool; None: none), where the sensor saturated
    and records min(render, photo): there a render at least as bright as the photo matches it and only a
    darker one is pulled up (a clipped pixel tells that the light was at least that bright, not its
    colour)."""
    if clipped is None:
        return pred
    return torch.where(clipped, torch.minimum(pred, gt), pred)


def compute_losses(
    p: TrainParams, r: Render, vt: ViewTensors, iteration: int, compiled: bool = False
) -> dict[str, Tensor]:
    """The terms of Eq. 13 for one rendered window and the weighted total (key ``loss``); the photometric
    terms compare the photo with what the camera would record of the render (``recorded``). ``compiled``:
    the colour and normal terms through ``torch.compile`` (``training.compiling``)."""
    loss_mask = vt.mask & ~r.skipped
    with_normal = p.lambda_normal > 0 and iteration >= at_fraction(NORMAL_START_FRACTION, p.iterations)
    with_prior = p.lambda_normal_prior > 0
    terms_of = torch_compiled(_terms, False) if compiled else _terms
    rgb, terms = terms_of(
        r.rgb,
        r.normal,
        r.points,
        vt.image,
        vt.clipped,
        loss_mask,
        vt.prior,
        vt.prior_valid,
        vt.mask,
        with_normal,
        with_prior,
    )
    total = terms["color"]
    if with_normal:
        total = total + p.lambda_normal * terms["normal"]
    if with_prior:
        total = total + p.lambda_normal_prior * terms["normal_prior"]
    # at the L1's weight: the photometric term's lower bound, moved to D; with no reflection term (sh)
    # (1 - r) D is the render, which the photometric term bounds already
    if vt.clipped is not None and p.reflection.model != "sh":
        terms["clipped_floor"] = clipped_floor_loss(
            r.diffuse, r.refl, vt.image, vt.clipped, vt.facade & ~vt.glass, loss_mask
        )
        total = total + (1.0 - LAMBDA_DSSIM) * terms["clipped_floor"]
    if p.lambda_opacity > 0:  # eager: the accumulated alpha needs no shading
        terms["opacity"] = opacity_loss(r.alpha, vt.facade)
        total = total + p.lambda_opacity * terms["opacity"]
    tau = step_schedule(p.hf_tau_start, p.hf_tau_end, p.hf_steps, iteration, p.iterations)
    lam = step_schedule(p.lambda_hf_start, p.lambda_hf_end, p.hf_steps, iteration, p.iterations)
    if lam > 0:  # eager: its threshold changes along the run, which would recompile a compiled graph
        terms["hf"] = high_frequency_loss(rgb, vt.image, loss_mask, tau)
        total = total + lam * terms["hf"]
    terms["loss"] = total + r.rgb.new_zeros(())
    return terms


def _terms(
    rgb: Tensor,
    normal: Tensor,
    points: Tensor,
    image: Tensor,
    clipped: Tensor | None,
    loss_mask: Tensor,
    prior: Tensor,
    prior_valid: Tensor,
    mask: Tensor,
    with_normal: bool,
    with_prior: bool,
) -> tuple[Tensor, dict[str, Tensor]]:
    """What the camera would record of ``rgb`` and the unweighted colour, normal consistency and normal
    prior terms (the last two where asked for)."""
    rgb = recorded(rgb, image, clipped)
    terms = {"color": color_loss(rgb, image, loss_mask, LAMBDA_DSSIM)}
    if with_normal:
        terms["normal"] = normal_consistency_loss(normal, depth_normals(points), loss_mask)
    if with_prior:
        terms["normal_prior"] = normal_prior_loss(normal, prior, prior_valid & mask)
    return rgb, terms
