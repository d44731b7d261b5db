"""The trainer on a CUDA device (the ``device = "cuda"`` / ``raster_backend = "gsplat"`` path of train_gs):
hard scenes stay finite, a short run lowers the loss, and a checkpoint made on the GPU resumes on the CPU.
These tests skip without CUDA (and, for gsplat, without the ``gpu`` extra)."""

from __future__ import annotations

import pytest
import torch

from facade_pipeline.splatting import gsplat_backend
from facade_pipeline.training.checkpoints import save_checkpoint
from facade_pipeline.training.losses import compute_losses
from facade_pipeline.training.render import splatting_rasterizer
from facade_pipeline.training.trainer import build_trainer, load_checkpoint, render_window, train
from tests.training.conftest import small_params
from tests.training.scenes import hard_scene

pytestmark = pytest.mark.gpu


@pytest.fixture(params=["gsplat", "torch"])
def raster_backend(request, cuda_device):
    if request.param == "gsplat" and not gsplat_backend.available():
        pytest.skip("gsplat is not installed")
    return request.param


def _finite(tr) -> bool:
    tensors = list(tr.model.params().values())
    if tr.reflection is not None:
        tensors += list(tr.reflection.parameters())
    return all(bool(torch.isfinite(t).all()) for t in tensors)


@pytest.mark.parametrize("refl", [-30.0, 30.0])  # reflectivity 0 or 1 everywhere
def test_hard_scene_stays_finite_on_cuda(cuda_device, raster_backend, refl):
    """Grazing and from-behind views and pixels with no splat, on the GPU: losses, gradients, parameters
    finite, as on the CPU (test_trainer.test_hard_scene_stays_finite)."""
    p = small_params(reflection_model="mlp", iterations=6, patch_px=0, mask_by_facade=False,
                     densify_interval=3)  # fmt: skip
    tr = build_trainer(p, hard_scene(), splatting_rasterizer(raster_backend), cuda_device)
    with torch.no_grad():
        tr.model.refl_logits.fill_(refl)
    for idx in (2, 3, 4):  # grazing, behind, sky
        r, vt = render_window(tr, idx, (0, 0, 24, 24))
        terms = compute_losses(p, r, vt, 0)
        assert all(bool(torch.isfinite(t)) for t in terms.values())
        terms["loss"].backward()
        assert all(q.grad is None or bool(torch.isfinite(q.grad).all()) for q in tr.model.params().values())
        tr.opt.zero_grad()
    train(tr)
    assert tr.iteration == 6 and _finite(tr) and tr.model.means.device.type == "cuda"


def test_short_cuda_run_lowers_the_loss_and_resumes_on_cpu(cuda_device, raster_backend, tmp_path):
    """Training lowers the photometric loss of the hard scene's frontal view (its images are uniform noise,
    which smooth splats fit only partly: about 10 % in 60 steps on CPU and GPU alike); the checkpoint written
    on the GPU loads on the CPU at the same iteration with the same parameters."""
    p = small_params(reflection_model="mlp", iterations=60, patch_px=0, mask_by_facade=False,
                     lambda_normal_prior=0.0, densify_interval=0)  # fmt: skip
    data = hard_scene()
    tr = build_trainer(p, data, splatting_rasterizer(raster_backend), cuda_device)

    def loss_now() -> float:
        with torch.no_grad():
            r, vt = render_window(tr, 1, (0, 0, 24, 24))
            return float(compute_losses(p, r, vt, 0)["color"])

    before = loss_now()
    train(tr)
    after = loss_now()
    assert after < 0.95 * before, (before, after)
    ckpt = tmp_path / "ckpt.pt"
    save_checkpoint(tr, ckpt, "fp")
    back = load_checkpoint(ckpt, p, data, splatting_rasterizer("torch"), torch.device("cpu"), "fp")
    assert back is not None and back.iteration == tr.iteration
    for name, value in tr.model.params().items():
        assert torch.equal(value.detach().cpu(), back.model.params()[name].detach()), name
