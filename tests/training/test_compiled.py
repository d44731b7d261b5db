"""``[run] compile``: a training step through ``torch.compile`` (``training.compiling``) renders, scores and
differentiates as the eager step, and trains through densifications (the splat count changing) without
a recompilation per step."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from facade_pipeline.training.losses import compute_losses
from facade_pipeline.training.monitor import whole_view_psnr
from facade_pipeline.training.render import training_rasterizer
from facade_pipeline.training.trainer import build_trainer, render_window, train
from tests.training.conftest import small_params
from tests.training.scenes import hard_scene


@pytest.mark.slow
@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_a_compiled_step_equals_the_eager_step_and_trains_through_densification(device, request):
    """One window rendered, scored and differentiated (the MLP with its environment proxy, the normal
    terms) as the eager step does it, then a short run with densifications: the same splat count and fit.
    On the CPU inductor's C++ kernels, on CUDA its Triton kernels (with gsplat where installed)."""
    if device == "cuda":
        request.getfixturevalue("cuda_device")  # skips without CUDA
    data = hard_scene()  # in memory: the GPU machines have none of the I/O stack that builds synthetic64
    p = small_params(proxy_channels=2, mlp_max_pixels=0, iterations=12)
    index = data.train_idx[0]
    raster = training_rasterizer("auto", p.lowpass_sigma_px, torch.device(device))
    out = {}
    for compile in (False, True):
        tr = build_trainer(p, data, raster, device, compile)
        r, vt = render_window(tr, index, (4, 2, p.patch_px, p.patch_px))
        terms = compute_losses(p, r, vt, p.iterations - 1, compile)
        terms["loss"].backward()
        params = [*tr.state.model.params().values(), *tr.state.reflection.parameters()]
        grads = [q.grad.clone() for q in params if q.grad is not None]
        for q in params:
            q.grad = None
        n0 = tr.state.model.n
        train(tr)
        out[compile] = (r.rgb.detach(), {k: v.detach() for k, v in terms.items()}, grads, n0, tr)
    (rgb_a, terms_a, grads_a, n0, eager), (rgb_b, terms_b, grads_b, _, comp) = out[False], out[True]
    torch.testing.assert_close(rgb_b, rgb_a, rtol=1e-5, atol=1e-6)
    assert terms_a.keys() == terms_b.keys() and {"color", "normal", "normal_prior", "loss"} <= terms_a.keys()
    for k in terms_a:
        torch.testing.assert_close(terms_b[k], terms_a[k], rtol=1e-5, atol=1e-7)
    assert len(grads_a) == len(grads_b)
    for ga, gb in zip(grads_a, grads_b, strict=True):
        torch.testing.assert_close(gb, ga, rtol=1e-4, atol=1e-5 * float(ga.abs().max()))
    # the run densified (the splat count changed) and fits the training views as the eager run does (the
    # parameters themselves part by float rounding, which Adam's normalised steps enlarge where a gradient
    # is near 0)
    assert eager.state.model.n != n0 and comp.state.model.n == eager.state.model.n
    # (both measured eagerly: a whole view is another size, which the compiled functions would compile for)
    comp.shading = dataclasses.replace(comp.shading, compiled=False)
    fit = [whole_view_psnr(t, data.train_idx) for t in (eager, comp)]
    assert abs(fit[1] - fit[0]) < 0.05, fit
