"""The evaluation core (``evaluation.core``): its figures equal a slow reference computed here from rendered
images with the formulas train_gs used before the core existed (float32 torch PSNR, the masked SSIM,
glass interior by max-pooling, the normal error, alignment by ``align_view`` with the gain before the
clip), through both of its callers (train_gs's held-out check and the evaluate stage's splits); the glass
interior region; alignment of a held-out view whose pose is off."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from facade_pipeline.config import default_run_settings
from facade_pipeline.evaluation import building as eval_building
from facade_pipeline.evaluation import metrics
from facade_pipeline.evaluation.building import evaluate_split
from facade_pipeline.evaluation.core import EvalView, evaluate_views, headline, views_of
from facade_pipeline.evaluation.image_eval import INTERIOR_MARGIN_PX, LpipsSetting, erode, region_masks
from facade_pipeline.evaluation.render_views import from_trainer
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.io.images import read_image
from facade_pipeline.scene import ImportedScene
from facade_pipeline.splatting.types import NEAR_M
from facade_pipeline.training.corrections import align_view, so3_exp
from facade_pipeline.training.data import CLIP_LEVEL, TrainView
from facade_pipeline.training.params import AlignParams
from facade_pipeline.training.render import Camera, render_view, splatting_rasterizer
from facade_pipeline.training.schedule import active_sh_degree
from facade_pipeline.training.trainer import build_trainer, train
from stages import evaluate as evaluate_stage
from stages import train_gs
from stages._runner import load_params
from tests.training.conftest import data64, small_params, synth64  # noqa: F401 (fixtures)

NO_LPIPS = LpipsSetting(())
ALIGN = AlignParams(steps=3, lr_rotation=2e-4, lr_translation=5e-3, lr_exposure=0.01, exposure=True)


# ------------------------------------------------------------------------ the reference (slow, plain)


def _ref_psnr(rgb: torch.Tensor, image: torch.Tensor, mask: torch.Tensor) -> float | None:
    """PSNR as the trainer computed it: float32 mean of squared errors over the mask and channels."""
    if not bool(mask.any()):
        return None
    m = mask.unsqueeze(-1).expand_as(rgb).float()
    mse = float(((rgb - image) ** 2 * m).sum() / m.sum())
    return -10.0 * math.log10(mse)


def _ref_erode(mask: torch.Tensor, px: int) -> torch.Tensor:
    """The trainer's erosion: max-pooling the outside, and the image border dropped."""
    near = torch.nn.functional.max_pool2d((~mask).float()[None, None], 2 * px + 1, 1, px)[0, 0] > 0
    border = torch.ones_like(mask)
    border[px:-px, px:-px] = False
    return mask & ~near & ~border


def _ref_view(tr, index: int, align: AlignParams | None) -> dict:
    """One held-out view measured as the trainer did: render whole (aligned first, the gain applied before
    the clip), then PSNR over the facade, glass and glass interior, masked SSIM, normal error on glass."""
    p, v = tr.params, tr.data.views[index]
    raster = splatting_rasterizer(default_run_settings().raster_backend, p.lowpass_sigma_px)
    f32 = {"dtype": torch.float32}
    cam = Camera(torch.as_tensor(v.camera.K, **f32), torch.as_tensor(v.camera.cam_from_world, **f32),
                 v.camera.width, v.camera.height)  # fmt: skip
    image, facade = torch.as_tensor(v.image), torch.as_tensor(v.facade_mask)
    glass, prior = torch.as_tensor(v.glass_mask) & facade, torch.as_tensor(v.normal_prior)
    clipped = torch.as_tensor(v.image >= CLIP_LEVEL).any(-1)  # the photo's own clipped pixels, any channel

    def render(cam_from_world):
        posed = Camera(cam.K, cam_from_world, cam.width, cam.height)
        sh = active_sh_degree(p.sh_degree, p.sh_degree_interval, tr.state.iteration)
        window = (0, 0, cam.width, cam.height)
        return render_view(tr.state.model, tr.state.reflection, posed, window, raster, NEAR_M, sh, tr.shading,
                           spec_mask=facade, chunk=65536)  # fmt: skip

    gain = torch.ones(3)
    if align is None:
        r = render(cam.cam_from_world)
    else:
        frozen = [*tr.state.model.params().values(), *tr.state.reflection.parameters()]
        fit = align_view(lambda M: render(M).rgb, cam.cam_from_world, image, facade, align, frozen=frozen)
        r, gain = render(fit.cam_from_world), fit.gain
    with torch.no_grad():
        rgb = (r.rgb * gain).clamp(0, 1)
        n = torch.nn.functional.normalize(r.normal, dim=-1)
        ok = glass & torch.as_tensor(v.normal_valid)
        ang = torch.rad2deg(torch.arccos((n * prior).sum(-1).clamp(-1, 1)[ok]))
    return {
        "psnr": _ref_psnr(rgb, image, facade),
        "ssim": metrics.ssim(rgb.numpy(), v.image, v.facade_mask, border="renormalize"),
        "psnr_glass": _ref_psnr(rgb, image, glass),
        "psnr_glass_interior": _ref_psnr(rgb, image, _ref_erode(glass, INTERIOR_MARGIN_PX)),
        "psnr_unclipped": _ref_psnr(rgb, image, facade & ~clipped),
        "normal_error_glass_deg": float(ang.mean()) if len(ang) else None,
    }


def _close(row: dict, ref: dict) -> None:
    regions = {"psnr": "facade", "psnr_glass": "glass", "psnr_glass_interior": "glass_interior",
               "psnr_unclipped": "unclipped"}  # fmt: skip
    for key, region in regions.items():
        m = row["metrics"][region]
        assert (m is None) == (ref[key] is None), key
        if m is not None:  # the core rounds PSNR to 1e-4 dB and computes in float64
            assert m["psnr"] == pytest.approx(ref[key], abs=2e-4), key
    assert row["metrics"]["facade"]["ssim"] == pytest.approx(ref["ssim"], abs=1e-6)  # rounded to 1e-6


@pytest.mark.parametrize("align", [None, ALIGN], ids=["as imported", "aligned"])
def test_core_equals_the_trainer_formulas_for_both_callers(tiny, align):
    layout, data, tr = tiny
    refs = [_ref_view(tr, i, align) for i in data.test_idx]
    assert any(r["psnr_glass_interior"] is not None for r in refs)  # the region is there to compare

    # train_gs's held-out check (as imported) and the benchmarks' core call (both)
    result = evaluate_views(from_trainer(tr, "tiny"), views_of(data, data.test_idx), NO_LPIPS, align)
    for row, ref in zip(result["views"], refs, strict=True):
        _close(row, ref)
        assert row["normal_error_glass_deg"] == pytest.approx(ref["normal_error_glass_deg"], abs=1e-4)
    means = headline(result)
    for key in ("psnr", "psnr_glass", "psnr_glass_interior", "psnr_unclipped", "normal_error_glass_deg"):
        vals = [r[key] for r in refs if r[key] is not None]
        assert means[key] == pytest.approx(float(np.mean(vals)), abs=2e-4), key
    assert means["ssim"] == pytest.approx(float(np.mean([r["ssim"] for r in refs])), abs=1e-6)
    if align is None:
        stage_check = train_gs.held_out_evaluation(tr, default_run_settings().raster_backend)
        assert {k: stage_check[k] for k in means} == means and stage_check["views"] == result["views"]

    # the evaluate stage's split, from the photos and masks on disk
    no_align = dataclasses.replace(ALIGN, steps=0)
    params = dataclasses.replace(load_params(evaluate_stage, "synthetic64"), align=align or no_align)
    by_stem = {v.stem: v for v in ImportedScene.load(layout).uav_views}
    views = [by_stem[data.views[i].stem] for i in data.test_idx]
    measured, _ = evaluate_split(layout, params, from_trainer(tr, "tiny"), views, "test")
    rows = measured["test_aligned" if align else "test"]["views"]
    for row, ref in zip(rows, refs, strict=True):
        _close(row, ref)
        assert "normal_error_glass_deg" not in row  # the stage reads no normal prior


def test_glass_interior_region_is_the_eroded_glass():
    rng = np.random.default_rng(3)
    for _ in range(5):
        facade = rng.random((20, 24)) > 0.1
        glass = rng.random((20, 24)) > 0.3
        m = region_masks(facade, glass)
        ref = _ref_erode(torch.as_tensor(facade & glass), INTERIOR_MARGIN_PX).numpy()
        assert np.array_equal(m["glass_interior"], ref) and not (m["glass_interior"] & ~m["glass"]).any()
    block = np.zeros((12, 12), bool)
    block[2:10, 3:9] = True  # 8 x 6 block
    expected = np.zeros_like(block)
    expected[4:8, 5:7] = True
    assert np.array_equal(erode(block, 2), expected) and np.array_equal(erode(block, 0), block)
    expected = np.zeros((12, 12), bool)
    expected[2:10, 2:10] = True  # a mask reaching the border loses the border too
    assert np.array_equal(erode(np.ones((12, 12), bool), 2), expected)


def test_the_unclipped_region_leaves_out_every_pixel_with_a_clipped_channel():
    """``unclipped`` is the facade less the pixels the photo clipped in any channel; a view that carries
    no clipped mask has no such region, and a training view whose clipped channels are None (none clipped)
    has all of its facade in it."""
    rng = np.random.default_rng(5)
    facade, glass = rng.random((16, 20)) > 0.2, rng.random((16, 20)) > 0.5
    channels = rng.random((16, 20, 3)) > 0.8
    m = region_masks(facade, glass, channels.any(-1))
    expected = np.array([[f and not channels[y, x].any() for x, f in enumerate(row)] for y, row in
                         enumerate(facade)])  # fmt: skip
    assert np.array_equal(m["unclipped"], expected) and "unclipped" not in region_masks(facade, glass)
    cam = PinholeCamera(np.array([[20.0, 0, 10], [0, 20.0, 8], [0, 0, 1]]), np.eye(4), 20, 16)
    image = rng.random((16, 20, 3)).astype(np.float32)
    normals = np.zeros((16, 20, 3), np.float32)
    view = TrainView("v", cam, image, facade, glass, normals, np.zeros((16, 20), bool), channels)
    assert np.array_equal(EvalView.of_train_view(view).clipped, channels.any(-1))
    none = EvalView.of_train_view(dataclasses.replace(view, clipped=None))
    assert np.array_equal(region_masks(none.facade_mask, none.glass_mask, none.clipped)["unclipped"], facade)


def test_a_photo_measured_at_a_pixel_budget_is_clipped_where_any_pixel_of_its_block_is(tiny, monkeypatch):
    """The evaluate stage's view: the photo's clipped pixels (a channel at 250 or more, of 255), and at a
    pixel budget a measured pixel clipped where any photo pixel of its block is, as training's views."""
    layout, _, _ = tiny
    view = ImportedScene.load(layout).uav_views[0]
    photo = np.array(read_image(layout.root / view.image))
    photo[:3, :3] = (255, 40, 40)  # one channel clipped
    photo[6, 9] = (10, 251, 10)  # one pixel of a block
    monkeypatch.setattr(eval_building, "read_image", lambda path: photo)
    full = eval_building.load_eval_view(layout, view)
    assert np.array_equal(full.clipped, (photo >= 250).any(-1)) and full.clipped.sum() >= 10
    h, w = photo.shape[:2]
    half = eval_building.load_eval_view(layout, view, max_pixels=(w // 2) * (h // 2))
    blocks = (photo[: h // 2 * 2, : w // 2 * 2] >= 250).any(-1).reshape(h // 2, 2, w // 2, 2)
    assert np.array_equal(half.clipped, blocks.any(axis=(1, 3))) and half.clipped[3, 4]


def test_core_aligns_a_held_out_view_whose_pose_is_off(data64):  # noqa: F811
    """A held-out view's imported pose turned by 0.05 rad: measured as imported it scores worse than after
    the core aligns it to the frozen model, which finds most of the turn; the model is untouched."""
    p = small_params(iterations=60, patch_px=0)
    raster = splatting_rasterizer(default_run_settings().raster_backend, p.lowpass_sigma_px)
    tr = train(build_trainer(p, data64, raster))
    tm = from_trainer(tr, "t")
    before = {n: t.detach().clone() for n, t in tr.state.model.params().items()}
    (true_view,) = views_of(data64, (data64.test_idx[1],))
    cam = true_view.camera
    turn = np.eye(4)
    turn[:3, :3] = so3_exp(torch.tensor([0.0, 0.05, 0.0])).double().numpy()
    off = PinholeCamera(cam.K, turn @ cam.cam_from_world, cam.width, cam.height)
    off_view = dataclasses.replace(true_view, camera=off)
    align = AlignParams(steps=60, lr_rotation=2e-3, lr_translation=1e-2, lr_exposure=0.01, exposure=True)
    true = headline(evaluate_views(tm, [true_view], NO_LPIPS))
    raw = headline(evaluate_views(tm, [off_view], NO_LPIPS))
    aligned = evaluate_views(tm, [off_view], NO_LPIPS, align)
    fit = aligned["views"][0]["alignment"]
    assert raw["psnr"] < true["psnr"] - 1.0
    assert headline(aligned)["psnr"] > raw["psnr"] + 1.0
    assert fit["align_rotation_deg"] == pytest.approx(np.degrees(0.05), rel=0.3)
    assert fit["align_l1_after"] < fit["align_l1_before"]
    # fitted on the view at half its side (a pixel budget), measured at its size: the same turn found
    half = dataclasses.replace(align, max_pixels=(cam.width // 2) * (cam.height // 2))
    coarse = evaluate_views(tm, [off_view], NO_LPIPS, half)
    assert coarse["views"][0]["alignment"]["align_rotation_deg"] == pytest.approx(np.degrees(0.05), rel=0.3)
    assert headline(coarse)["psnr"] > raw["psnr"] + 1.0
    for n, t in tr.state.model.params().items():
        assert torch.equal(t, before[n]) and t.requires_grad and t.grad is None, n


def test_held_out_views_of_a_pose_refined_model_align_without_touching_it(data64):  # noqa: F811
    """Aligning the held-out views of a model trained with pose corrections: finite figures, every view
    aligned, and the (frozen) corrections unchanged."""
    tr = train(build_trainer(small_params(iterations=4, pose_refinement=True), data64,
                             splatting_rasterizer("auto")))  # fmt: skip
    before = tr.state.corrections.rotation.detach().clone()
    out = evaluate_views(from_trainer(tr, "t"), views_of(data64, data64.test_idx), NO_LPIPS, ALIGN)
    assert math.isfinite(headline(out)["psnr"])
    assert all(v["alignment"]["align_translation_m"] is not None for v in out["views"])
    assert torch.equal(tr.state.corrections.rotation.detach(), before)
