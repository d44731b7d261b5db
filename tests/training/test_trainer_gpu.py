"""The trainer on a CUDA device (the ``device = "cuda"`` / ``raster_backend = "gsplat"`` path of train_gs):
hard scenes stay finite, a short run lowers the loss, a checkpoint made on the GPU resumes on the CPU, and a
step never waits for the device.
These tests skip without CUDA (and, for gsplat, without the ``gpu`` extra)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch._dynamo.utils import counters

from facade_pipeline.shading.params import ReflectionMLP
from facade_pipeline.shading.reflection import ReflectionMLPModule
from facade_pipeline.splatting import gsplat_backend
from facade_pipeline.training.checkpoints import save_checkpoint
from facade_pipeline.training.data import ExposureEstimate
from facade_pipeline.training.losses import NORMAL_START_FRACTION, compute_losses
from facade_pipeline.training.render import splatting_rasterizer
from facade_pipeline.training.schedule import at_fraction
from facade_pipeline.training.trainer import build_trainer, load_checkpoint, render_window, step, train
from tests.training.conftest import small_params
from tests.training.scenes import hard_scene

pytestmark = pytest.mark.gpu


@pytest.fixture(params=["gsplat", "torch"])
def raster_backend(request, cuda_device):
    if request.param == "gsplat" and not gsplat_backend.available():
        pytest.skip("gsplat is not installed")
    return request.param


def _finite(tr) -> bool:
    tensors = list(tr.state.model.params().values())
    if tr.state.reflection is not None:
        tensors += list(tr.state.reflection.parameters())
    return all(bool(torch.isfinite(t).all()) for t in tensors)


@pytest.mark.parametrize("refl", [-30.0, 30.0])  # reflectivity 0 or 1 everywhere
def test_hard_scene_stays_finite_on_cuda(cuda_device, raster_backend, refl):
    """Grazing and from-behind views and pixels with no splat, on the GPU: losses, gradients, parameters
    finite, as on the CPU (test_trainer.test_hard_scene_stays_finite)."""
    p = small_params(reflection_model="mlp", iterations=6, patch_px=0, mask_by_facade=False,
                     densify_interval=3)  # fmt: skip
    tr = build_trainer(p, hard_scene(), splatting_rasterizer(raster_backend), cuda_device)
    with torch.no_grad():
        tr.state.model.refl_logits.fill_(refl)
    for idx in (2, 3, 4):  # grazing, behind, sky
        r, vt = render_window(tr, idx, (0, 0, 24, 24))
        terms = compute_losses(p, r, vt, 0)
        assert all(bool(torch.isfinite(t)) for t in terms.values())
        terms["loss"].backward()
        grads = [q.grad for q in tr.state.model.params().values()]
        assert all(g is None or bool(torch.isfinite(g).all()) for g in grads)
        tr.state.opt.zero_grad()
    train(tr)
    assert tr.state.iteration == 6 and _finite(tr) and tr.state.model.means.device.type == "cuda"


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
    save_checkpoint(tr.state, tr.params, ckpt, "fp")
    back = load_checkpoint(ckpt, p, data, splatting_rasterizer("torch"), torch.device("cpu"), "fp")
    assert back is not None and back.state.iteration == tr.state.iteration
    for name, value in tr.state.model.params().items():
        assert torch.equal(value.detach().cpu(), back.state.model.params()[name].detach()), name


def _with_surroundings(data):
    """``data`` with coarse points of a block 2.5-4.5 m in front of the facade, 4 m high (within the
    proxy's reach of this small facade): the environment proxy's surroundings then have a block that
    reflected rays are cast against."""
    rng = np.random.default_rng(0)
    block = np.column_stack([rng.uniform(-2, 2, 3000), rng.uniform(2.5, 4.5, 3000), rng.uniform(0, 4, 3000)])
    init = data.init
    points = np.concatenate([init.points, block])
    colors = np.concatenate([init.colors, np.full_like(block, 0.5)])
    return dataclasses.replace(data, init=dataclasses.replace(init, points=points, colors=colors))


@pytest.mark.parametrize("compile", [False, True])
def test_steps_on_cuda_never_wait_for_the_device(cuda_device, compile):
    """Whole-image steps with the reflection MLP, its environment proxy (the surroundings' ray cast) and
    the estimated exposures, between log lines and densifications, under
    ``torch.cuda.set_sync_debug_mode("error")``: any read of a value on the device, and any copy of host
    values to it, raises. The rasterizer is exempt: gsplat reads how many tile intersections it has to
    sort once per render, which is gsplat's (its own one wait, not the step's); without gsplat the exact
    torch backend renders, exempt likewise. Eager and compiled (``[run] compile``)."""
    data = _with_surroundings(hard_scene())
    data = dataclasses.replace(data, exposure=ExposureEstimate(np.zeros((len(data.views), 3), np.float32),
                                                               np.full(len(data.views), 100)))  # fmt: skip
    p = small_params(reflection_model="mlp", proxy_channels=2, iterations=12, patch_px=0, mlp_max_pixels=0,
                     densify_interval=0, exposure_estimate=True, mask_by_facade=False)  # fmt: skip
    raster = splatting_rasterizer("gsplat" if gsplat_backend.available() else "torch")

    def rasterize(*args, **kwargs):
        mode = torch.cuda.get_sync_debug_mode()
        torch.cuda.set_sync_debug_mode(0)
        try:
            return raster(*args, **kwargs)
        finally:
            torch.cuda.set_sync_debug_mode(mode)

    tr = build_trainer(p, data, rasterize, cuda_device, compile)
    assert tr.state.reflection.proxy.surroundings.blocks() is not None
    # first calls: kernels load, memory pools fill, and (compiled) every graph the checked steps run is
    # made, the normal terms' among them: the compiler itself reads the device
    warm = at_fraction(NORMAL_START_FRACTION, p.iterations) + 1
    train(tr, stop_at=warm)
    torch.cuda.synchronize()
    graphs = counters["stats"]["unique_graphs"]
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(p.iterations - warm):
            out = step(tr)
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert counters["stats"]["unique_graphs"] == graphs  # the checked steps compiled nothing
    assert tr.state.iteration == p.iterations and all(bool(torch.isfinite(v)) for v in out.values())


def test_supersampled_training_renders_through_gsplat(cuda_device):
    """``supersample`` renders a camera of s times the resolution through the same rasterizer, so gsplat
    runs it: a frontal view at 2 x 2 samples per pixel through gsplat against the exact torch backend, on
    the diffuse model (no reflection MLP, which reads gsplat's centre depths). The scene is built in memory,
    so the test needs torch and gsplat alone. The tolerance is ten times the mean gap of tilted splats in
    tests/splatting/test_gsplat.py (gsplat's fainter rims)."""
    if not gsplat_backend.available():
        pytest.skip("gsplat is not installed")
    data = hard_scene()
    p = small_params(reflection_model="sh", supersample=2)
    frontal = [v.stem for v in data.views].index("frontal")
    cam = data.views[frontal].camera
    maps = []
    for backend in ("torch", "gsplat"):
        tr = build_trainer(p, data, splatting_rasterizer(backend), cuda_device)
        with torch.no_grad():
            r, _ = render_window(tr, frontal, (0, 0, cam.width, cam.height))
        assert r.rgb.shape[:2] == (cam.height, cam.width)
        maps.append(r.rgb)
    assert float((maps[0] - maps[1]).abs().mean()) < 5e-3


def test_the_reflection_mlp_in_bfloat16_follows_float32_on_cuda(cuda_device):
    """The reflection MLP's products in bfloat16 on CUDA (``reflection.CUDA_MATMUL_DTYPE``) against the same
    module in float32, at the defaults' size (8 x 512, 12 frequencies), on 4096 random rays: R within a few
    8-bit photo steps, and the gradients of R's sum (first and last layer, the positions) pointing the same
    way with a similar length. The CPU never takes the bfloat16 path."""
    torch.manual_seed(0)
    m = ReflectionMLPModule(ReflectionMLP(12, 8, 512, True, None, 0.0)).to(cuda_device)
    x = (torch.rand(4096, 3, device=cuda_device) * 2 - 1).requires_grad_(True)
    w = torch.nn.functional.normalize(torch.randn(4096, 3, device=cuda_device), dim=-1)
    out = {}
    for dtype in (torch.bfloat16, None):
        m.cuda_matmul_dtype = dtype
        m.zero_grad()
        x.grad = None
        r = m(x, w)
        r.sum().backward()
        out[dtype] = (r.detach(), m.first[0].weight.grad.clone(), m.out.weight.grad.clone(), x.grad.clone())
    low, ref = out[torch.bfloat16], out[None]
    assert low[0].dtype == torch.float32
    err = (low[0] - ref[0]).abs()
    assert float(err.max()) < 8 / 255 and float(err.mean()) < 1 / 255, (float(err.max()), float(err.mean()))
    for a, b in zip(low[1:], ref[1:], strict=True):
        cos = torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0)
        ratio = a.norm() / b.norm()
        assert float(cos) > 0.97 and 0.9 < float(ratio) < 1.1, (float(cos), float(ratio))
    cpu = ReflectionMLPModule(ReflectionMLP(4, 4, 32, True, None, 0.0))
    xc, wc = x.detach().cpu()[:64], w.cpu()[:64]
    bf = cpu(xc, wc)
    cpu.cuda_matmul_dtype = None
    assert torch.equal(bf, cpu(xc, wc))
