"""The evaluate stage's building blocks: metrics per region over masks, means, heat maps, geometry against a
known truth, and the report's tables (LPIPS never a number without weights; Table 3 only for an ablation)."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.evaluation import lpips as lpips_mod
from facade_pipeline.evaluation.geometry_eval import Truth, corner_error_px, point_errors
from facade_pipeline.evaluation.image_eval import (
    UNAVAILABLE,
    LpipsSetting,
    error_heatmap,
    mean_metrics,
    region_masks,
    side_by_side,
    view_metrics,
)
from facade_pipeline.evaluation.metrics import psnr
from facade_pipeline.evaluation.report import (
    architecture_label,
    build_html,
    build_markdown,
    pareto_front,
    table3_rows,
)
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.panels3d.model import Panel, PanelSet
from tests.evaluation.conftest import weights_or_skip

NO_LPIPS = LpipsSetting(())


def _pair(seed=0, h=32, w=40):
    rng = np.random.default_rng(seed)
    truth = rng.random((h, w, 3))
    render = np.clip(truth + rng.normal(0, 0.05, truth.shape), 0, 1)
    facade = np.zeros((h, w), bool)
    facade[4:28, 6:34] = True
    glass = np.zeros((h, w), bool)
    glass[8:24, 10:30] = True
    return render, truth, region_masks(facade, glass)


def test_regions_partition_the_facade():
    _, _, m = _pair()
    assert not (m["glass"] & m["frames"]).any()
    assert ((m["glass"] | m["frames"]) == m["facade"]).all()
    assert m["glass_interior"].any() and not (m["glass_interior"] & ~m["glass"]).any()


def test_metrics_ignore_pixels_outside_each_region():
    render, truth, masks = _pair()
    a = view_metrics(render, truth, masks, NO_LPIPS)
    wild = render.copy()
    wild[~masks["facade"]] = np.random.default_rng(5).random(wild[~masks["facade"]].shape)
    b = view_metrics(wild, truth, masks, NO_LPIPS)
    assert a == b
    # ... but a change on glass changes glass and facade, not frames
    c_img = render.copy()
    c_img[masks["glass"]] = 1 - c_img[masks["glass"]]
    c = view_metrics(c_img, truth, masks, NO_LPIPS)
    assert c["frames"] == a["frames"]
    assert c["glass"]["psnr"] < a["glass"]["psnr"] - 3 and c["facade"]["psnr"] < a["facade"]["psnr"]
    assert a["glass"]["psnr"] == pytest.approx(psnr(render, truth, masks["glass"]), abs=1e-4)


def test_lpips_over_mask_ignores_outside_when_weights_exist():
    weights_or_skip("vgg")
    render, truth, masks = _pair(h=64, w=64)
    setting = LpipsSetting(("vgg_3dgs",))
    a = view_metrics(render, truth, masks, setting)["facade"]["lpips"]["vgg_3dgs"]
    wild = render.copy()
    wild[~masks["facade"]] = 0.3
    b = view_metrics(wild, truth, masks, setting)["facade"]["lpips"]["vgg_3dgs"]
    assert isinstance(a, float) and a == pytest.approx(b, abs=1e-6)
    assert view_metrics(truth, truth, masks, setting)["facade"]["lpips"]["vgg_3dgs"] < 1e-6 < a


def test_empty_region_is_none_and_identical_images_give_inf():
    render, truth, masks = _pair()
    masks["glass"][:] = False
    out = view_metrics(truth, truth, masks, NO_LPIPS)
    assert out["glass"] is None
    assert out["facade"]["psnr"] == "inf" and out["facade"]["ssim"] == pytest.approx(1.0)


def test_means_skip_inf_and_propagate_unavailable():
    rows = [
        {
            "metrics": {
                "facade": {"psnr": 20.0, "ssim": 0.5, "lpips": {"c": 0.2}},
                "glass": None,
                "frames": None,
            }
        },
        {
            "metrics": {
                "facade": {"psnr": "inf", "ssim": 1.0, "lpips": {"c": UNAVAILABLE}},
                "glass": None,
                "frames": None,
            }
        },
    ]
    m = mean_metrics(rows, ("c",))
    assert m["facade"]["psnr"] == 20.0 and m["facade"]["ssim"] == 0.75
    assert m["facade"]["lpips"]["c"] == UNAVAILABLE and m["glass"] is None


def test_heatmap_ramp_and_outside_grey():
    truth = np.zeros((4, 4, 3))
    render = truth.copy()
    render[0, 0] = 1.0
    mask = np.ones((4, 4), bool)
    mask[3, 3] = False
    heat = error_heatmap(render, truth, mask, 0.5)
    assert tuple(heat[0, 0]) == (252, 255, 164)  # at or above max_error: top of the ramp
    assert tuple(heat[1, 1]) == (0, 0, 4)  # no error: bottom
    assert tuple(heat[3, 3]) == (128, 128, 128)
    with pytest.raises(ValueError):
        error_heatmap(render, truth, mask, 0.0)
    assert side_by_side(truth, render, heat).shape == (4, 3 * 4 + 4, 3)


def _square(x0, x1):
    v = np.array([[x0, 0, 0], [x1, 0, 0], [x1, 1, 0], [x0, 1, 0]], float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _truth():
    g, f = _square(0.0, 1.0), _square(1.2, 2.0)
    corners = np.array([[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]], float)
    return Truth(MeshRaycaster(*g), MeshRaycaster(*f), corners)


def test_point_errors_against_a_known_truth():
    truth = _truth()
    pts = np.array([[0.5, 0.5, 0.1], [0.2, 0.3, -0.1], [1.6, 0.5, 0.05], [5.0, 5.0, 5.0]])
    tilt = np.radians(10)
    nrm = np.array([[0, 0, 1], [0, np.sin(tilt), -np.cos(tilt)], [0, 0, 1], [0, 0, 1]], float)
    out = point_errors(pts, nrm, truth, max_match_m=0.5)
    assert out["glass_distance_mean_m"] == pytest.approx(0.1, abs=1e-5)
    assert out["frame_distance_mean_m"] == pytest.approx(0.05, abs=1e-5)
    assert out["glass_normal_error_mean_deg"] == pytest.approx(5.0, abs=1e-3)  # (0 + 10) / 2, unsigned
    assert out["samples_unmatched"] == 1


def test_corner_error_px_zero_for_true_panels_and_grows_with_offset():
    truth = _truth()
    cam = PinholeCamera(
        intrinsics(50, 50, 32, 32),
        look_at(np.array([0.5, 0.5, 3.0]), np.array([0.5, 0.5, 0.0]), np.array([0, 1.0, 0])),
        64,
        64,
    )

    def panels(shift):
        c = truth.panel_corners[0] + shift
        return PanelSet((), (Panel(0, 0, 0, c, np.array([0, 0, 1.0]), 0.0),))

    assert corner_error_px(panels(0.0), truth, [cam])["corner_error_mean_px"] == pytest.approx(0.0, abs=1e-6)
    moved = corner_error_px(panels(np.array([0.1, 0, 0])), truth, [cam])
    assert moved["corner_error_mean_px"] == pytest.approx(
        50 * 0.1 / 3.0, abs=1e-4
    )  # f dx / depth; rounded to 4 decimals
    far = PinholeCamera(cam.K, look_at(np.array([50.0, 0.5, 3.0]), np.array([60.0, 0.5, 0.0])), 64, 64)
    assert corner_error_px(panels(0.0), truth, [far])["corner_error_mean_px"] is None  # not seen


def _metrics(variants, conventions=("vgg_3dgs",), status="weights x"):
    return {
        "building": "b",
        "test_every": 8,
        "heatmap_max_error": 0.25,
        "variants": variants,
        "lpips": {"conventions": list(conventions), "status": {c: status for c in conventions}},
    }


def _variant(model, psnr_value, arch=None, lp=0.1):
    mean = {
        "facade": {"views": 1, "psnr": psnr_value, "ssim": 0.9, "lpips": {"vgg_3dgs": lp}},
        "glass": None,
        "frames": None,
    }
    return {"reflection_model": model, "architecture": arch, "test": {"views": [], "mean": mean}}


def test_report_says_unavailable_never_a_number(monkeypatch, tmp_path):
    monkeypatch.delenv(lpips_mod.WEIGHTS_DIR_ENV, raising=False)
    monkeypatch.setattr(lpips_mod, "default_repo_root", lambda: tmp_path / "checkout")
    render, truth, masks = _pair()
    out = view_metrics(render, truth, masks, LpipsSetting(("vgg_3dgs", "alex_official")))
    assert out["facade"]["lpips"] == {"vgg_3dgs": UNAVAILABLE, "alex_official": UNAVAILABLE}
    m = _metrics({"07_train": _variant("mlp", 25.0, lp=UNAVAILABLE)}, status=lpips_mod.UNAVAILABLE_TEXT)
    md, page = build_markdown(m), build_html(m)
    row = next(line for line in md.splitlines() if line.startswith("| 07_train"))
    assert row.split("|")[5].strip() == UNAVAILABLE
    assert "LPIPS unavailable (no weights)" in md and "LPIPS unavailable (no weights)" in page


def test_table3_only_for_an_mlp_ablation():
    arch = {"fourier_levels": 12, "mlp_depth": 8, "mlp_width": 512, "mlp_skip": True}
    one = {"07_train": _variant("mlp", 30.0, arch), "sh": _variant("sh", 22.0)}
    assert table3_rows(_metrics(one)) == []
    assert "Table 3" not in build_markdown(_metrics(one))
    two = {**one, "narrow": _variant("mlp", 29.0, {**arch, "mlp_width": 256, "mlp_skip": False})}
    rows = table3_rows(_metrics(two))
    assert [r[1] for r in rows] == [
        "L = 12, 8 layers, 256 hidden dim, w/o skip connection",
        "L = 12, 8 layers, 512 hidden dim, w/ skip connection",
    ]
    assert [r[2] for r in rows] == ["29.00", "30.00"]
    assert "Table 3" in build_html(_metrics(two))
    # a variant trained otherwise (longer, say) is not part of the ablation, whatever its architecture
    longer = {**_variant("mlp", 35.0, {**arch, "mlp_depth": 6}), "ablation_group": "other"}
    three = {name: {**v, "ablation_group": "g"} for name, v in two.items()} | {"longer": longer}
    assert [r[2] for r in table3_rows(_metrics(three))] == ["29.00", "30.00"]
    from facade_pipeline.evaluation.building import ablation_group

    base = {"iterations": 10, "seed": 0, **arch}
    assert ablation_group(base) == ablation_group({**base, "mlp_width": 64})
    assert ablation_group(base) != ablation_group({**base, "seed": 1})
    assert ablation_group(base) == ablation_group({**base, "mlp_self_hits": True})
    full = {**arch, "mlp_proxy_channels": 8, "mlp_self_hits": True}
    label = architecture_label(full)
    assert label.endswith("w/ skip connection, environment proxy (8 channels), facade self hits")
    label = architecture_label({**full, "mlp_proxy_surroundings": True})
    assert label.endswith("environment proxy (8 channels, surroundings), facade self hits")
    assert ablation_group(base) == ablation_group({**base, "mlp_proxy_surroundings": True})
    assert ablation_group(base) != ablation_group({**base, "iterations": 20})


def test_pareto_front():
    pts = [(1.0, 20.0), (2.0, 19.0), (3.0, 25.0), (3.0, 24.0), (0.5, 10.0)]
    assert pareto_front(pts) == [4, 0, 2]
