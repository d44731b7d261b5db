"""The trainer: reflection models, pixel selection, held-out views, numerical stability on hard scenes,
divergence reporting, the full-size MLP on tiny inputs, and exact resume from checkpoints."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest
import torch

from facade_pipeline.errors import PipelineError
from facade_pipeline.splatting.types import NEAR_M
from facade_pipeline.training import densify, exposure, losses, monitor
from facade_pipeline.training import trainer as trainer_module
from facade_pipeline.training.batches import camera
from facade_pipeline.training.checkpoints import save_checkpoint
from facade_pipeline.training.exposure import ExposureParams
from facade_pipeline.training.losses import compute_losses
from facade_pipeline.training.params import facade_size
from facade_pipeline.training.render import Camera, random_subset, render_view, splatting_rasterizer
from facade_pipeline.training.schedule import step_schedule
from facade_pipeline.training.trainer import (
    TrainingDivergedError,
    build_trainer,
    load_checkpoint,
    render_window,
    train,
)
from tests.splatting.dense_reference import render_dense
from tests.training.conftest import small_params
from tests.training.scenes import hard_scene

RASTER = splatting_rasterizer("auto")


def _mean_psnr(tr, indices) -> float:
    """Mean PSNR of whole views over their facade masks (what training sees; measuring a model as the
    pipeline reports it is the evaluation package's, tested there)."""
    out = []
    for i in indices:
        cam = tr.cameras[i]
        with torch.no_grad():
            r, vt = render_window(tr, i, (0, 0, cam.width, cam.height))
        out.append(losses.psnr(r.rgb.clamp(0, 1), vt.image, vt.mask))
    return float(np.mean(out))


def _finite_state(tr) -> bool:
    ok = all(torch.isfinite(p).all() for p in tr.state.model.params().values())
    if tr.state.reflection is not None:
        ok &= all(torch.isfinite(p).all() for p in tr.state.reflection.parameters())
    return bool(ok)


@pytest.mark.parametrize("sigma", [None, 0.45])
def test_adapter_matches_the_dense_reference(data64, sigma):
    """Our reading of facade_pipeline.splatting through the Rasterizer adapter (window, expected depth,
    camera-facing normals, premultiplied features, the low-pass sigma) against the splatting tests' dense
    float64 reference."""
    p = small_params()
    tr = build_trainer(p, data64, RASTER)
    cam, m = tr.cameras[1], tr.state.model
    feats = torch.rand(m.n, 7, generator=torch.Generator().manual_seed(0))
    tensors = [
        t.detach().double()
        for t in (m.means, m.unit_quats(), m.scales(), m.opacities(), feats, cam.cam_from_world, cam.K)
    ]
    raster = splatting_rasterizer("torch") if sigma is None else splatting_rasterizer("torch", sigma)
    a = raster(*tensors, cam.width, cam.height, NEAR_M, (8, 16, 40, 32))
    b = render_dense(*tensors, cam.width, cam.height, near=NEAR_M, x0=8, y0=16, crop_w=40, crop_h=32,
                     lowpass_sigma_px=sigma)
    for ours, theirs in (
        ("features", "features"),
        ("alpha", "alpha"),
        ("normal", "normal"),
        ("depth", "depth_expected"),
        ("distortion", "distortion"),
    ):
        # 1e-5: the renderer's own tolerance against this reference (tests/splatting)
        assert torch.allclose(getattr(a, ours), b[theirs], atol=1e-5), ours


def test_supersampled_render_is_the_mean_of_sub_pixel_renders(data64, monkeypatch):
    """supersample = 2 against its definition: the mean of four one-sample renders whose pixel centres are
    moved to the sub-pixel positions (x + 0.25, x + 0.75) by the principal point; a crop window, the
    facade-masked specular term and every map the losses read."""
    # the splats this test was made with: from the coarse points within 1 m of synthetic64's facade (with
    # fewer, a few opaque pixels of the window differ by up to 0.02 m in depth between the two renders)
    monkeypatch.setattr(trainer_module, "INIT_BOUNDS_MARGIN", 1.0 / facade_size(data64.bounds))
    p = small_params(mlp_max_pixels=0, supersample=2)
    tr = build_trainer(p, data64, RASTER)
    with torch.no_grad():
        tr.state.model.opacity_logits.fill_(2.0)  # opaque splats: sharp edges, where the samples differ most
        # splats wider than the 2DGS low-pass filter (sigma 0.71 px of the render, so 0.35 px of the
        # pixel at s = 2), so that filter takes no part and the definition above is exact
        tr.state.model.log_scales.add_(math.log(3.0))
    window, index = (8, 16, 40, 32), 1
    cam, tm = tr.cameras[index], tr.state.model
    x0, y0, w, h = window
    spec = torch.as_tensor(data64.views[index].facade_mask[y0 : y0 + h, x0 : x0 + w])
    one = dataclasses.replace(tr.shading, supersample=1)
    args = (tr.state.reflection, RASTER, NEAR_M, p.sh_degree)
    with torch.no_grad():
        fine = render_view(tm, args[0], cam, window, args[1], args[2], args[3], tr.shading, spec)
        subs = []
        for dy in (-0.25, 0.25):
            for dx in (-0.25, 0.25):
                K = cam.K.clone()
                K[0, 2] -= dx
                K[1, 2] -= dy
                c = Camera(K, cam.cam_from_world, cam.width, cam.height)
                subs.append(render_view(tm, args[0], c, window, args[1], args[2], args[3], one, spec))
    for name in ("rgb", "diffuse", "refl", "alpha", "normal", "depth", "points"):
        ref = torch.stack([getattr(r, name) for r in subs]).mean(0)
        # float32 rounding of the two cameras' rays (depths of 20 m): 1e-3 absolute, 1e-4 relative
        assert torch.allclose(getattr(fine, name), ref, atol=1e-3, rtol=1e-4), name
    assert torch.equal(fine.spec_pixels, torch.stack([r.spec_pixels for r in subs]).any(0))
    assert bool(fine.spec_pixels.any()) and not bool(fine.spec_pixels[~spec].any())
    # the samples differ (by 10x the tolerance above): a supersampled pixel is not any one of them
    assert max(float((fine.rgb - r.rgb).abs().max()) for r in subs) > 0.01


def test_supersampled_training_and_evaluation_stay_finite(data64):
    p = small_params(iterations=6, supersample=2)
    tr = build_trainer(p, data64, RASTER)
    train(tr)
    assert _finite_state(tr)
    assert np.isfinite(_mean_psnr(tr, data64.test_idx))
    with pytest.raises(PipelineError, match="supersample"):
        build_trainer(small_params(supersample=0), data64, RASTER)


@pytest.mark.parametrize("model", ["sh", "envmap", "mlp"])
def test_reflection_models_train_and_only_mlp_envmap_use_reflectivity(data64, model):
    p = small_params(reflection_model=model, iterations=4)
    tr = build_trainer(p, data64, RASTER)
    assert (tr.state.reflection is None) == (model == "sh")
    r, vt = render_window(tr, 1, (16, 16, 32, 32))
    compute_losses(p, r, vt, 0)["loss"].backward()
    g = tr.state.model.refl_logits.grad
    if model == "sh":
        assert g is None or torch.all(g == 0)  # vanilla 2DGS: I = D
    else:
        assert bool(r.spec_pixels.any()) and float(g.abs().sum()) > 0
    tr.state.opt.zero_grad()
    train(tr)
    assert tr.state.iteration == 4 and _finite_state(tr)


def test_mlp_runs_only_on_selected_reflective_facade_pixels(data64):
    p = small_params(mlp_max_pixels=50)
    tr = build_trainer(p, data64, RASTER)
    tr.shading = dataclasses.replace(tr.shading, refl_threshold=0.05)
    calls = []
    inner = tr.state.reflection

    class Counting(torch.nn.Module):
        def forward(self, x, w):
            calls.append(x.shape[0])
            return inner(x, w)

    tr.state.reflection = Counting()
    gen = torch.Generator().manual_seed(0)
    r, vt = render_window(tr, 1, (0, 0, 64, 64), select=lambda c: random_subset(c, 50, gen))
    eligible = vt.mask & (r.refl.detach() > 0.05)
    assert calls == [int(r.spec_pixels.sum())] and 0 < calls[0] <= 50
    assert not bool((r.spec_pixels & ~eligible).any())
    assert torch.equal(r.skipped, eligible & ~r.spec_pixels)  # the rest leave this step's loss
    calls.clear()
    tr.shading = dataclasses.replace(tr.shading, refl_threshold=1.0)  # nothing reflects: no MLP call at all
    render_window(tr, 1, (0, 0, 64, 64))
    assert calls == []


def test_held_out_views_are_never_trained_on(data64):
    seen = []

    def recording(*args):
        seen.append(args[5].clone())
        return RASTER(*args)

    tr = build_trainer(small_params(iterations=12), data64, recording)
    train(tr)
    test_poses = [tr.cameras[i].cam_from_world for i in data64.test_idx]
    assert data64.test_idx == (0, 8) and len(seen) == 12
    assert not any(torch.equal(s, t) for s in seen for t in test_poses)


@pytest.mark.parametrize("refl", [-30.0, 30.0])  # reflectivity 0 or 1 everywhere
@pytest.mark.parametrize("model", ["envmap", "mlp", "mlp+proxy"])
def test_hard_scene_stays_finite(model, refl):
    """Grazing and from-behind views, pixels no splat covers, reflectivity 0 or 1, an empty high-frequency
    set (tau above any residual): every loss, gradient and parameter stays finite."""
    data = hard_scene()
    p = small_params(
        reflection_model=model.split("+")[0],
        proxy_channels=4 if model.endswith("proxy") else 0,
        proxy_resolution_px=64,
        iterations=8,
        patch_px=0,
        mask_by_facade=False,
        hf_tau_start=5.0,
        hf_tau_end=5.0,
        densify_interval=4,
    )
    tr = build_trainer(p, data, RASTER)
    with torch.no_grad():
        tr.state.model.refl_logits.fill_(refl)
    for idx in (2, 3, 4):  # grazing, behind, sky
        r, vt = render_window(tr, idx, (0, 0, 24, 24))
        terms = compute_losses(p, r, vt, p.iterations - 1)  # late: every term is on
        assert {"normal", "normal_prior", "hf"} <= set(terms)
        assert terms["hf"] == 0.0 and all(torch.isfinite(t) for t in terms.values())
        assert bool((r.alpha == 0).any()) or idx != 4  # the sky view has pixels with no splat
        terms["loss"].backward()
        assert all(q.grad is None or torch.isfinite(q.grad).all() for q in tr.state.model.params().values())
        tr.state.opt.zero_grad()
    train(tr, log_every=5)
    assert tr.state.log and _finite_state(tr) and all(np.isfinite(rec["loss"]) for rec in tr.state.log)
    assert np.isfinite(_mean_psnr(tr, (0,)))


def test_proxy_features_train_at_their_own_rate(data64):
    """With proxy features the reflection optimiser has two groups: the network's decaying rate and the
    feature maps' constant one; a few steps move both."""
    p = small_params(proxy_channels=4, proxy_resolution_px=64, iterations=6, mlp_max_pixels=0)
    tr = build_trainer(p, data64, RASTER)
    groups = {g["name"]: g for g in tr.state.opt_refl.param_groups}
    assert set(groups) == {"reflection", "proxy"} and groups["proxy"]["lr"] == p.lr.proxy
    maps = [q.detach().clone() for q in tr.state.reflection.proxy.parameters()]
    train(tr)
    assert groups["proxy"]["lr"] == p.lr.proxy and groups["reflection"]["lr"] < p.lr.reflection_init
    after = tr.state.reflection.proxy.parameters()
    assert any(not torch.equal(a, b) for a, b in zip(maps, after, strict=True))
    assert _finite_state(tr)


@pytest.mark.parametrize("normal_grad", [True, False])
def test_reflection_normal_grad_switch(data64, normal_grad):
    """``reflection_normal_grad`` false: the specular term sends no gradient into the rendered normal."""
    seen = {}

    def keeping(*args):
        out = RASTER(*args)
        out.normal.retain_grad()
        seen["normal"] = out.normal
        return out

    p = small_params(reflection_normal_grad=normal_grad)
    tr = build_trainer(p, data64, keeping)
    with torch.no_grad():
        tr.state.model.refl_logits.fill_(2.0)
    r, vt = render_window(tr, 1, (0, 0, 64, 64))
    assert bool(r.spec_pixels.any())
    (r.rgb * vt.mask.unsqueeze(-1)).sum().backward()
    g = seen["normal"].grad
    moved = g is not None and float(g.abs().sum()) > 0
    assert moved == normal_grad


def test_pose_corrections_move_training_views_only(data64, monkeypatch):
    """Training views' pose corrections move; held-out views keep the imported pose exactly; without
    refinement the trainer renders the imported poses as they are, and nothing corrects exposure."""
    monkeypatch.setattr(trainer_module, "LR_POSE_ROTATION", 1e-3)  # faster than the default, to see moves
    monkeypatch.setattr(trainer_module, "LR_POSE_TRANSLATION", 1e-3)  # times the scene extent
    tr = build_trainer(small_params(iterations=10, pose_refinement=True), data64, RASTER)
    train(tr)
    c = tr.state.corrections
    train_idx, test_idx = list(data64.train_idx), list(data64.test_idx)
    for t in (c.rotation, c.translation):
        moved = t.detach().abs().sum(-1) > 0
        assert bool(moved[train_idx].any()) and not bool(moved[test_idx].any())
    for i in test_idx:
        seen = camera(tr.cameras[i], tr.state.corrections, i)
        assert torch.equal(seen.cam_from_world, tr.cameras[i].cam_from_world)
    assert c.log_gain is None
    plain = build_trainer(small_params(), data64, RASTER)
    assert plain.state.corrections is None
    assert camera(plain.cameras[1], plain.state.corrections, 1) is plain.cameras[1]


def test_estimated_exposure_renders_a_darker_training_view_darker(data64, monkeypatch):
    """``exposure_estimate``: one training photo at 0.6 times the exposure of the others is found from the
    frames before training (log gain -0.51 against the others' median), and that view renders at its gain;
    held-out views render unchanged."""
    dark = data64.train_idx[2]
    views = list(data64.views)
    views[dark] = dataclasses.replace(views[dark], image=views[dark].image * 0.6)
    data = dataclasses.replace(data64, views=tuple(views))
    est = ExposureParams(samples=40000, min_samples=10)  # small photos
    monkeypatch.setattr(exposure, "EXPOSURE_ESTIMATE", est)
    p = small_params(exposure_estimate=True)
    with pytest.raises(PipelineError, match="exposure estimate"):
        build_trainer(p, data, RASTER)  # the estimate travels with the data
    data = exposure.with_exposure_estimate(data, p.seed)
    tr = build_trainer(p, data, RASTER)
    assert tr.state.corrections is None
    g = torch.as_tensor(tr.exposure.log_gain).mean(-1)
    others = [i for i in data.train_idx if i != dark]
    assert abs(float(g[dark] - g[others].median()) - math.log(0.6)) < 0.05
    plain = build_trainer(small_params(), data, RASTER)
    win = (0, 0, 32, 24)
    with torch.no_grad():
        for i, gain in ((dark, torch.as_tensor(tr.exposure.log_gain[dark]).exp()), (data.test_idx[0], None)):
            a, _ = render_window(tr, i, win)
            b, _ = render_window(plain, i, win)
            torch.testing.assert_close(a.rgb, b.rgb if gain is None else b.rgb * gain)


def test_cos_theta_negative_normals_are_clamped():
    """A splat normal facing away (the rasterizer flips per splat, but blends of flipped and unflipped
    normals can point away): Fresnel stays in [F0, 1]."""
    from facade_pipeline.shading import deferred

    n = torch.tensor([[0.0, 0.0, 1.0]], requires_grad=True)
    w_o = torch.tensor([[0.0, 0.0, -1.0]])
    F = deferred.schlick_fresnel(torch.full((1, 3), 0.04), deferred.cos_theta(n, w_o))
    F.sum().backward()
    assert torch.allclose(F, torch.ones(1, 3)) and torch.isfinite(n.grad).all()


def test_exploding_learning_rate_is_caught_and_reported():
    data = hard_scene()
    p = small_params(iterations=5, patch_px=0)
    tr = build_trainer(dataclasses.replace(p, lr=dataclasses.replace(p.lr, position_init=1e6)), data, RASTER)
    with pytest.raises(TrainingDivergedError, match="position_init"):
        train(tr)
    tr = build_trainer(
        dataclasses.replace(p, lr=dataclasses.replace(p.lr, reflectivity=float("inf"))), data, RASTER
    )
    with pytest.raises(TrainingDivergedError, match="refl_logits"):
        train(tr)


def test_full_size_mlp_on_tiny_inputs():
    """The paper's configuration (8 x 512, L = 12, skip) through two training steps on a 24 px scene."""
    p = small_params(
        iterations=2,
        patch_px=8,
        mlp_depth=8,
        mlp_width=512,
        mlp_fourier_levels=12,
        mlp_skip=True,
        proxy_channels=0,
        mask_by_facade=False,
    )
    tr = build_trainer(p, hard_scene(), RASTER)
    assert sum(q.numel() for q in tr.state.reflection.parameters()) == 1_951_235
    with torch.no_grad():
        tr.state.model.refl_logits.fill_(2.0)
    before = [q.detach().clone() for q in tr.state.reflection.parameters()]
    train(tr)
    assert _finite_state(tr)
    assert any(not torch.equal(a, b) for a, b in zip(before, tr.state.reflection.parameters(), strict=True))


def _states_equal(a, b) -> None:
    for name, t in a.state.model.params().items():
        assert torch.equal(t, getattr(b.state.model, name)), name
    for (ka, va), (kb, vb) in zip(
        a.state.reflection.state_dict().items(), b.state.reflection.state_dict().items(), strict=True
    ):
        assert ka == kb and torch.equal(va, vb), ka
    assert torch.equal(a.state.generator.get_state(), b.state.generator.get_state())
    assert a.state.log == b.state.log
    assert (a.state.corrections is None) == (b.state.corrections is None)
    if a.state.corrections is not None:
        for (ka, va), (kb, vb) in zip(
            a.state.corrections.state_dict().items(), b.state.corrections.state_dict().items(), strict=True
        ):
            assert ka == kb and torch.equal(va, vb), ka


@pytest.mark.parametrize("refine", ["none", "pose", "estimate"])
def test_resume_from_checkpoint_equals_uninterrupted(data64, tmp_path, refine):
    p = small_params(  # densification every 5 falls between checkpoints
        iterations=14,
        pose_refinement=refine == "pose",
        exposure_estimate=refine == "estimate",
    )
    if p.exposure_estimate:
        data64 = exposure.with_exposure_estimate(data64, p.seed)
    every = {"log_every": 5, "checkpoint_every": 3}
    ref = train(build_trainer(p, data64, RASTER), **every)
    ckpt = tmp_path / "ckpt.pt"
    part = train(build_trainer(p, data64, RASTER), ckpt, "fp", stop_at=7, **every)  # saves at 3, 6 and 7
    assert part.state.iteration == 7
    resumed = load_checkpoint(ckpt, p, data64, RASTER, "cpu", "fp")
    assert resumed.state.iteration == 7 and resumed.state.model.n == part.state.model.n
    train(resumed, ckpt, "fp", **every)
    _states_equal(ref, resumed)
    assert load_checkpoint(ckpt, p, data64, RASTER, "cpu", "other") is None  # other parameters or inputs
    assert load_checkpoint(tmp_path / "none.pt", p, data64, RASTER, "cpu", "fp") is None
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")  # moved aside, training starts afresh
    assert load_checkpoint(tmp_path / "bad.pt", p, data64, RASTER, "cpu", "fp") is None
    assert (tmp_path / "bad.pt.bad").is_file() and not (tmp_path / "bad.pt").exists()


def test_a_checkpoint_not_resumed_says_why_in_the_log(data64, tmp_path, caplog):
    """Another fingerprint: the log names the parameters that changed, or says that the inputs or the code
    did; another format says so; a checkpoint that matches is resumed and logged."""
    p = small_params(iterations=4)
    ckpt = tmp_path / "ckpt.pt"
    train(build_trainer(p, data64, RASTER), ckpt, "fp")
    caplog.set_level(logging.INFO, logger="facade_pipeline.training.checkpoints")
    assert load_checkpoint(ckpt, p, data64, RASTER, "cpu", "fp").state.iteration == 4
    assert "resuming from the checkpoint of iteration 4" in caplog.text
    caplog.clear()
    wider = small_params(iterations=4, lambda_normal=0.5, mlp_width=16)
    assert load_checkpoint(ckpt, wider, data64, RASTER, "cpu", "other") is None
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lines) == 1 and "\n" not in lines[0] and str(ckpt) in lines[0]
    assert "lambda_normal 0.05 -> 0.5" in lines[0] and "reflection.mlp.width 32 -> 16" in lines[0]
    assert "iteration 4 not resumed" in lines[0] and "starts from iteration 0" in lines[0]
    caplog.clear()
    assert load_checkpoint(ckpt, p, data64, RASTER, "cpu", "other inputs") is None
    assert "same parameters, other inputs or code" in caplog.text
    caplog.clear()
    state = torch.load(ckpt, weights_only=True)
    torch.save({**state, "format": 1}, ckpt)
    assert load_checkpoint(ckpt, p, data64, RASTER, "cpu", "fp") is None
    assert "format 1" in caplog.text and ckpt.is_file()  # an older format is left in place, not moved


def test_training_improves_the_training_views(data64):
    p = small_params(iterations=30)
    tr = build_trainer(p, data64, RASTER)
    idx = data64.train_idx[:3]
    before = _mean_psnr(tr, idx)
    train(tr)
    assert _mean_psnr(tr, idx) > before + 1.0


def test_save_checkpoint_is_atomic(data64, tmp_path, monkeypatch):
    tr = build_trainer(small_params(), data64, RASTER)
    ckpt = tmp_path / "c.pt"
    save_checkpoint(tr.state, tr.params, ckpt, "fp")
    good = ckpt.read_bytes()

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", boom)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tr.state, tr.params, ckpt, "fp")
    assert ckpt.read_bytes() == good and [q.name for q in tmp_path.iterdir()] == ["c.pt"]


def test_reflection_evaluated_everywhere_and_masked_equals_gathered(data64, monkeypatch):
    """R at every pixel kept where chosen (the GPU's way, ``render.gathers_chosen``) renders and
    differentiates as R at the chosen pixels only (the CPU's), the environment proxy included."""
    from facade_pipeline.training import render

    tr = build_trainer(small_params(proxy_channels=2, mlp_max_pixels=0), data64, RASTER)
    index = data64.train_idx[0]
    out = []
    for gathered in (True, False):
        monkeypatch.setattr(render, "gathers_chosen", lambda device, g=gathered: g)
        r, _ = render_window(tr, index, (0, 0, 48, 40))
        (r.rgb * torch.linspace(0.5, 1.5, r.rgb.numel()).view_as(r.rgb)).sum().backward()
        params = [*tr.state.model.params().values(), *tr.state.reflection.parameters()]
        out.append((r.rgb.detach(), r.spec_pixels, [q.grad.clone() for q in params if q.grad is not None]))
        for q in params:
            q.grad = None
    (a, chosen_a, grads_a), (b, chosen_b, grads_b) = out
    assert bool(chosen_a.any()) and torch.equal(chosen_a, chosen_b)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert len(grads_a) == len(grads_b)
    for ga, gb in zip(grads_a, grads_b, strict=True):
        torch.testing.assert_close(ga, gb, rtol=1e-4, atol=1e-6)


def test_whole_view_psnr_rises_and_never_falls_a_db_below_its_best(data64):
    """The stability of item 4 on synthetic64 at a tiny budget: the PSNR over whole training views, logged
    every ``log_every`` iterations, ends above where it began and no check falls more than 1 dB below the
    best before it (the patch PSNR may jump; this may not)."""
    p = small_params(iterations=60)
    tr = build_trainer(p, data64, RASTER)
    train(tr, log_every=10)
    vp = [r["view_psnr"] for r in tr.state.log]
    assert len(vp) == 6 and all(v is not None for v in vp)
    assert vp[-1] > vp[0] + 0.5
    for k in range(1, len(vp)):
        assert vp[k] >= max(vp[:k]) - 1.0, vp


def test_a_densification_that_clones_leaves_the_fit_where_it_was(data64):
    """A clone and its copy share the splat's opacity, so cloning every splat (a first densification of
    demo's budget clones most of them) moves the whole-view PSNR by hundredths of a dB, not by the 1-3 dB
    of copies that each keep the opacity and composite to 1 - (1 - a)^2."""
    from facade_pipeline.training.densify import DensifyStats, densify_and_prune

    p = small_params(iterations=200, densify_interval=0, densify_max_gaussians=10_000)
    tr = build_trainer(p, data64, RASTER)
    train(tr, stop_at=30)
    s, n = tr.state, tr.state.model.n
    before = monitor.whole_view_psnr(tr)
    opaque = int((s.model.opacities() >= 0.05).sum())
    hot = DensifyStats(torch.ones(n), torch.ones(n))
    huge = 1e9  # an extent beside which every splat is small: all are cloned, none split
    counts = densify_and_prune(s.model, s.opt, hot, tr.params.densify, huge, False, s.generator)
    assert counts["cloned"] == n and counts["split"] == 0 and s.model.n == 2 * opaque
    assert abs(monitor.whole_view_psnr(tr) - before) < 0.1


def test_whole_view_psnr_pools_the_monitored_views(data64):
    """Against the obvious reference: every monitored view rendered whole, squared errors over their loss
    masks summed, one PSNR of the sum."""
    tr = build_trainer(small_params(), data64, RASTER)

    def reference(idx):
        se, n = 0.0, 0
        for i in idx:
            cam = tr.cameras[i]
            with torch.no_grad():
                r, vt = render_window(tr, i, (0, 0, cam.width, cam.height))
            m = (vt.mask & ~r.skipped).numpy()
            d = r.rgb.clamp(0, 1).double().numpy() - vt.image.double().numpy()
            se += float((d[m] ** 2).sum())
            n += 3 * int(m.sum())
        return 10 * math.log10(n / se)

    idx = monitor.monitor_indices(tr.data.train_idx)
    assert len(idx) == min(monitor.MONITOR_VIEWS, len(tr.data.train_idx)) and len(set(idx)) == len(idx)
    assert math.isclose(monitor.whole_view_psnr(tr), reference(idx), rel_tol=1e-9)
    # the views asked for instead (the benchmark's fit of every training view)
    every = tr.data.train_idx
    assert len(every) > len(idx)
    assert math.isclose(monitor.whole_view_psnr(tr, every), reference(every), rel_tol=1e-9)
    assert not math.isclose(monitor.whole_view_psnr(tr, every[:1]), reference(every), rel_tol=1e-6)


def test_a_nan_stops_training_naming_the_iteration_and_keeps_the_last_good_checkpoint(data64, tmp_path):
    p = small_params(iterations=30)
    tr = build_trainer(p, data64, RASTER)
    ckpt = tmp_path / "c.pt"
    train(tr, ckpt, "fp", stop_at=10, log_every=5, checkpoint_every=5)
    with torch.no_grad():
        tr.state.model.sh_dc.fill_(float("nan"))  # a colour gone NaN: the next step's loss is NaN
    with pytest.raises(TrainingDivergedError, match="at iteration 11") as e:
        train(tr, ckpt, "fp", log_every=5, checkpoint_every=5)
    assert "NaN" in str(e.value) and "\n" not in str(e.value)
    back = load_checkpoint(ckpt, p, data64, RASTER, "cpu", "fp")
    assert back is not None and back.state.iteration == 10 and _finite_state(back)


def test_a_whole_view_psnr_far_below_its_best_stops_training(data64, monkeypatch):
    tr = build_trainer(small_params(), data64, RASTER)
    tr.state.log = [{"iteration": 5, "view_psnr": 21.0}, {"iteration": 10, "view_psnr": 24.0}]
    tr.state.iteration = 15
    monkeypatch.setattr(monitor, "whole_view_psnr", lambda tr: 24.0 - monitor.DIVERGENCE_DROP_DB + 0.1)
    assert monitor.monitored(tr, {"iteration": 15})["view_psnr"] < 24.0
    monkeypatch.setattr(monitor, "whole_view_psnr", lambda tr: 24.0 - monitor.DIVERGENCE_DROP_DB - 0.1)
    with pytest.raises(TrainingDivergedError, match="at iteration 15"):
        monitor.monitored(tr, {"iteration": 15})
    monkeypatch.setattr(monitor, "whole_view_psnr", lambda tr: math.nan)
    with pytest.raises(TrainingDivergedError, match="NaN"):
        monitor.monitored(tr, {"iteration": 15})


def test_the_checks_after_an_opacity_reset_are_judged_against_each_other(data64, monkeypatch):
    """A reset clamps every opacity to 0.01: the views go nearly black by design, so a check at or after it
    is not a divergence against the checks before it; against those after it, it is."""
    p = small_params(iterations=40, densify_opacity_reset_interval=10)
    tr = build_trainer(p, data64, RASTER)
    assert densify.last_opacity_reset(p.densify, p.iterations, 15) == 10
    tr.state.log = [{"iteration": 5, "view_psnr": 24.0}]
    tr.state.iteration = 10  # the check of the reset's own step
    monkeypatch.setattr(monitor, "whole_view_psnr", lambda tr: 6.0)
    tr.state.log.append(monitor.monitored(tr, {"iteration": 10}))
    tr.state.iteration = 15
    monkeypatch.setattr(monitor, "whole_view_psnr", lambda tr: 20.0)
    tr.state.log.append(monitor.monitored(tr, {"iteration": 15}))
    tr.state.iteration = 20  # the next reset: again nothing before it counts
    monkeypatch.setattr(monitor, "whole_view_psnr", lambda tr: 6.5)
    tr.state.log.append(monitor.monitored(tr, {"iteration": 20}))
    tr.state.iteration = 25  # densification, and the resets with it, ended at 20: 6.5 dB is the best since
    monkeypatch.setattr(monitor, "whole_view_psnr", lambda tr: 18.0)
    tr.state.log.append(monitor.monitored(tr, {"iteration": 25}))
    tr.state.iteration = 30
    monkeypatch.setattr(monitor, "whole_view_psnr", lambda tr: 18.0 - monitor.DIVERGENCE_DROP_DB - 0.1)
    with pytest.raises(TrainingDivergedError, match="at iteration 30"):
        monitor.monitored(tr, {"iteration": 30})


def test_the_last_opacity_reset_is_where_training_made_it(data64, monkeypatch):
    """``last_opacity_reset`` (what the divergence check counts from) against the iterations at which a run
    actually reset its opacities, recorded as it trains."""
    made: list[int] = []
    real = trainer_module.reset_opacity
    for interval, iterations in ((4, 30), (7, 30), (10, 19), (0, 20)):
        made.clear()
        p = small_params(iterations=iterations, densify_interval=3, densify_opacity_reset_interval=interval)
        tr = build_trainer(p, data64, RASTER)
        monkeypatch.setattr(trainer_module, "reset_opacity",
                            lambda m, o, v, tr=tr: (made.append(tr.state.iteration), real(m, o, v)))
        train(tr)
        assert (interval == 0) == (not made)
        for it in range(iterations + 1):
            expected = max((r for r in made if r <= it), default=0)
            assert densify.last_opacity_reset(p.densify, iterations, it) == expected, (interval, it)


def test_training_is_the_same_on_the_same_scene_at_1_to_25(data64):
    """Every length of training follows from the scene: synthetic64 shrunk to 1:25 (cameras, points, mesh)
    trains step for step as at full size (the same losses and PSNR), the splats 25 times closer."""
    from tests.training.test_data import scaled_scene

    p = small_params(iterations=8, reflection_model="sh")
    small = scaled_scene(data64, 1.0 / 25.0)
    a, b = build_trainer(p, data64, RASTER), build_trainer(p, small, RASTER)
    assert a.state.model.n == b.state.model.n
    train(a, log_every=4)
    train(b, log_every=4)
    for ra, rb in zip(a.state.log, b.state.log, strict=True):
        for key in ("loss", "psnr", "view_psnr"):
            assert math.isclose(ra[key], rb[key], rel_tol=2e-3, abs_tol=2e-4), (key, ra, rb)
    assert torch.allclose(b.state.model.means * 25.0, a.state.model.means, atol=1e-3 * data64.extent)


def _with_clipped_corner(data, size: int):
    """``data`` whose views' photos clipped every channel in their top-left ``size`` x ``size`` pixels."""
    views = []
    for v in data.views:
        clipped = np.zeros(v.image.shape, bool)
        clipped[:size, :size] = True
        image = np.where(clipped, 1.0, v.image).astype(v.image.dtype)
        views.append(dataclasses.replace(v, image=image, clipped=clipped))
    return dataclasses.replace(data, views=tuple(views))


def test_a_window_without_clipped_channels_skips_the_clipping_with_the_same_loss_and_gradients(data64):
    """A window in which the photo clipped nothing gets no clipped channels (``batches.view_tensors``), and
    its loss and gradients are those of the clipping applied with its all-False channels; a window that
    holds some keeps them."""
    data = _with_clipped_corner(data64, 8)
    tr = build_trainer(small_params(), data, RASTER)
    index = data.train_idx[0]
    window = (20, 16, 24, 20)
    out = []
    for keep in (False, True):
        r, vt = render_window(tr, index, window)
        assert vt.clipped is None
        if keep:  # the device's channels of the window, all False: the clipping as it was applied
            x0, y0, w, h = window
            vt = dataclasses.replace(vt, clipped=tr.views[index].clipped[y0 : y0 + h, x0 : x0 + w])
            assert vt.clipped is not None and not bool(vt.clipped.any())
        terms = compute_losses(tr.params, r, vt, tr.params.iterations)
        terms["loss"].backward()
        params = [*tr.state.model.params().values(), *tr.state.reflection.parameters()]
        out.append((terms["loss"].detach(), [q.grad.clone() for q in params if q.grad is not None]))
        for q in params:
            q.grad = None
    (loss_a, grads_a), (loss_b, grads_b) = out
    torch.testing.assert_close(loss_a, loss_b, rtol=1e-6, atol=0.0)
    assert len(grads_a) == len(grads_b) > 0
    for ga, gb in zip(grads_a, grads_b, strict=True):
        torch.testing.assert_close(ga, gb, rtol=1e-5, atol=1e-9)
    _, vt = render_window(tr, index, (0, 0, 24, 20))
    assert vt.clipped is not None and bool(vt.clipped[:8, :8].all()) and not bool(vt.clipped[8:].any())


def test_the_step_psnr_only_in_logged_steps_trains_the_same(data64):
    """``train`` asks for the window's PSNR only in the steps it logs; the model, the reflection and the
    random state after training are the same logging every step as logging none."""
    data = _with_clipped_corner(data64, 12)
    p = small_params(iterations=12)
    every, none = (train(build_trainer(p, data, RASTER), log_every=k) for k in (1, 0))
    assert len(every.state.log) == 12 and all(r["psnr"] is not None for r in every.state.log)
    assert none.state.log == []
    for name, t in every.state.model.params().items():
        assert torch.equal(t, getattr(none.state.model, name)), name
    for (ka, va), (kb, vb) in zip(
        every.state.reflection.state_dict().items(), none.state.reflection.state_dict().items(), strict=True
    ):
        assert ka == kb and torch.equal(va, vb), ka
    assert torch.equal(every.state.generator.get_state(), none.state.generator.get_state())


def test_opacity_term_adds_its_own_pull_and_lambda_zero_is_the_loss_without_it(data64):
    """``lambda_opacity`` 0 leaves the loss as it was (no term, the same total); a weight adds exactly
    lambda times the facade's mean 1 - alpha, whose gradient raises splats' opacities and lowers none;
    a view without facade pixels gets no pull at all."""
    p0 = small_params(lambda_opacity=0.0)
    tr = build_trainer(p0, data64, RASTER)
    r, vt = render_window(tr, 1, (8, 8, 40, 40))
    assert bool(vt.facade.any()) and not bool(vt.facade.all())
    t0 = compute_losses(p0, r, vt, p0.iterations - 1)
    assert "opacity" not in t0
    it = p0.iterations - 1
    lam_hf = step_schedule(p0.lambda_hf_start, p0.lambda_hf_end, p0.hf_steps, it, p0.iterations)
    old = t0["color"] + p0.lambda_normal * t0["normal"] + p0.lambda_normal_prior * t0["normal_prior"]
    old = old + lam_hf * t0["hf"]
    assert float(t0["loss"]) == float(old)
    lam = 0.5
    t1 = compute_losses(dataclasses.replace(p0, lambda_opacity=lam), r, vt, p0.iterations - 1)
    a, f = r.alpha.detach().double(), vt.facade
    pull = float((1.0 - a[f]).sum() / f.sum())
    assert float(t1["opacity"]) == pytest.approx(pull, rel=1e-6)
    assert float(t1["loss"] - t0["loss"]) == pytest.approx(lam * pull, rel=1e-5)
    logits = tr.state.model.opacity_logits
    (g,) = torch.autograd.grad(losses.opacity_loss(r.alpha, vt.facade), logits, retain_graph=True)
    assert float(g.max()) <= 0.0 and float(g.min()) < 0.0
    (g,) = torch.autograd.grad(losses.opacity_loss(r.alpha, torch.zeros_like(vt.facade)), logits)
    assert torch.all(g == 0)
