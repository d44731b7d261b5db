"""The report builds from a tiny run: a few training steps on synthetic64 (gt masks standing in for the
bake_normals ones), rendered back from the saved files, measured by the stage's own functions and turned
into metrics.json, Markdown and a self-contained HTML page."""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import re

import numpy as np
import pytest
from PIL import Image

from facade_pipeline.bake.maps import BakedPrior
from facade_pipeline.config import to_dict
from facade_pipeline.errors import InputError
from facade_pipeline.evaluation.building import evaluate_split, metrics_header, write_reports
from facade_pipeline.evaluation.metrics import psnr, ssim
from facade_pipeline.evaluation.render_views import (
    align_trained,
    from_trainer,
    load_trained,
    render_trained,
)
from facade_pipeline.scene import ImportedScene
from facade_pipeline.splatting.types import LOWPASS_SIGMA_PX
from facade_pipeline.training.trained import TrainedModelFiles
from stages import evaluate as stage
from stages._runner import load_params


def test_saved_variant_renders_like_the_trainer(tiny):
    layout, data, tr = tiny
    split = {
        "train": [data.views[i].stem for i in data.train_idx],
        "test": [data.views[i].stem for i in data.test_idx],
    }
    folder = layout.path("variant_dir", variant="tiny")

    def save(params):
        strategy = tr.params.reflection_strategy(data.bounds)
        TrainedModelFiles.variant(folder, params).save(tr.state.model, tr.state.reflection, strategy,
                                                       data.bounds, split)  # fmt: skip

    save(to_dict(tr.params))
    variant = TrainedModelFiles.from_dir(folder)
    assert variant.name == "tiny" and variant.split_stems() == split
    loaded = load_trained(variant)
    live = from_trainer(tr, "live")
    v = data.views[data.test_idx[0]]
    a, b = render_trained(loaded, v.camera, v.facade_mask), render_trained(live, v.camera, v.facade_mask)
    assert a.rgb.shape == (v.camera.height, v.camera.width, 3)
    assert float(a.alpha.max()) > 0.1  # the facade is in view: something was rendered
    np.testing.assert_allclose(a.rgb, b.rgb, atol=1e-5)  # PLY stores activated values: float32 round trip
    # a variant trained with supersampling is rendered with it
    params = to_dict(tr.params) | {"supersample": 2}
    save(params)
    ss = load_trained(TrainedModelFiles.from_dir(folder))
    assert ss.shading.supersample == 2
    live2 = dataclasses.replace(live, shading=dataclasses.replace(live.shading, supersample=2))
    c = render_trained(ss, v.camera, v.facade_mask)
    np.testing.assert_allclose(c.rgb, render_trained(live2, v.camera, v.facade_mask).rgb, atol=1e-5)
    assert float(np.abs(c.rgb - a.rgb).max()) > 1e-3  # and that is not the one-sample render
    # ... and one trained with another low-pass sigma with that sigma; one saved before the key, with 2DGS's
    save(to_dict(tr.params) | {"lowpass_sigma_px": 0.4})
    lp = load_trained(TrainedModelFiles.from_dir(folder))
    assert lp.lowpass_sigma_px == 0.4
    d = render_trained(lp, v.camera, v.facade_mask)
    live3 = dataclasses.replace(live, lowpass_sigma_px=0.4)
    np.testing.assert_allclose(d.rgb, render_trained(live3, v.camera, v.facade_mask).rgb, atol=1e-5)
    assert float(np.abs(d.rgb - a.rgb).max()) > 1e-3
    old = {k: v for k, v in to_dict(tr.params).items() if k != "lowpass_sigma_px"}
    save(old)
    assert load_trained(TrainedModelFiles.from_dir(folder)).lowpass_sigma_px == LOWPASS_SIGMA_PX
    (folder / "params.json").write_text("{not json")
    with pytest.raises(InputError, match="params.json"):
        TrainedModelFiles.from_dir(folder)


def test_report_builds_from_a_tiny_run(tiny):
    layout, data, tr = tiny
    params = load_params(stage, "synthetic64")
    scene_views = {v.stem: v for v in ImportedScene.load(layout).uav_views}
    views = [scene_views[data.views[i].stem] for i in data.test_idx]
    tm = from_trainer(tr, "tiny_run")
    measured, written = evaluate_split(layout, params, tm, views, "test")
    result, aligned = measured["test"], measured["test_aligned"]
    metrics = metrics_header(layout, params, 4)
    metrics["variants"]["tiny_run"] = {"reflection_model": "mlp", "architecture": None, **measured}
    outputs = write_reports(layout, params, metrics)
    assert all(p.is_file() for p in outputs + written)

    # the figures are those of the render against the photo over the (gt) facade mask
    row = result["views"][0]
    v = data.views[data.test_idx[0]]
    r = render_trained(tm, v.camera, v.facade_mask)
    mask = BakedPrior.load(layout, v.stem, None, ("facade_mask",)).facade
    assert row["metrics"]["facade"]["psnr"] == pytest.approx(psnr(r.rgb, v.image, mask), abs=1e-3)
    assert row["metrics"]["facade"]["ssim"] == pytest.approx(
        ssim(r.rgb, v.image, mask, border="renormalize"), abs=1e-5
    )
    saved = json.loads(layout.path("eval_metrics").read_text())
    assert saved["variants"]["tiny_run"]["test"]["mean"] == json.loads(json.dumps(result["mean"]))

    # the aligned figures: the same views, each fitted to the model no worse than as imported (in the
    # L1 it is fitted on), and the render from the fitted camera and gain is what was measured
    assert [a["view"] for a in aligned["views"]] == [r["view"] for r in result["views"]]
    for a in aligned["views"]:
        fit = a["alignment"]
        assert fit["align_l1_after"] <= fit["align_l1_before"] and len(fit["align_gain"]) == 3
    fitted = align_trained(tm, v.camera, v.image, mask, params.align)
    assert aligned["views"][0]["metrics"]["facade"]["psnr"] == pytest.approx(
        psnr(fitted.render.rgb, v.image, mask), abs=1e-3
    )

    md = layout.path("eval_report_md").read_text()
    table_row, aligned_row = [line for line in md.splitlines() if line.startswith("| tiny_run")]
    assert f"{result['mean']['facade']['psnr']:.2f}" in table_row
    assert f"{aligned['mean']['facade']['psnr']:.2f}" in aligned_row
    assert md.index("aligned to the model") < md.index(aligned_row)
    for link in re.findall(r"!\[[^]]*\]\(([^)]+)\)", md):
        assert (layout.path("eval_report_md").parent / link).is_file()

    page = layout.path("eval_report_html").read_text()
    assert "<svg" in page and "Table 1" in page
    srcs = re.findall(r"src='([^']+)'", page)
    assert len(srcs) == len(views) and all(
        s.startswith("data:image/png;base64,") for s in srcs
    )  # self-contained
    img = np.array(Image.open(io.BytesIO(base64.b64decode(srcs[0].split(",", 1)[1]))))
    assert img.shape == (v.camera.height, 3 * v.camera.width + 4, 3)  # photo | render | heat map


def test_fly_through_video_of_a_tiny_run(tiny, tmp_path):
    """A 10-frame orbit rendered by the trained model: an MP4 of 10 frames of the path's size whose frames
    differ (the camera moves), a looping WebP clip, and the report embedding it."""
    from facade_pipeline.evaluation.report import build_html, build_markdown
    from facade_pipeline.evaluation.video import (
        look_target,
        merge_films,
        orbit_path,
        read_mp4,
        render_path,
        write_clip,
        write_mp4,
    )

    layout, data, tr = tiny
    cams = [v.camera for v in data.views]
    path = orbit_path(cams, 10, scale=1.0)
    target = look_target(cams)
    centres = np.array([c.center for c in cams])
    for cam in path:  # each frame looks at the target, from within the training cameras' range
        d = target - cam.center
        assert np.dot(d / np.linalg.norm(d), cam.forward) > 0.9999
        assert centres[:, 2].min() - 1e-6 <= cam.center[2] <= centres[:, 2].max() + 1e-6
    tm = from_trainer(tr, "tiny_run")
    frames = render_path(path, lambda c, m: render_trained(tm, c, m).rgb, lambda c: None)
    mp4 = tmp_path / "flythrough.mp4"
    write_mp4(mp4, frames, fps=8)
    back = read_mp4(mp4)
    assert len(back) == 10 and back[0].shape == (path[0].height, path[0].width, 3)
    assert np.abs(back[0].astype(int) - back[5].astype(int)).mean() > 1.0  # the view changes
    assert np.abs(back[0].astype(int) - frames[0].astype(int)).mean() < 8.0  # H.264 keeps the picture
    clip = tmp_path / "clip.webp"
    write_clip(clip, frames, n=5, width_px=32, fps=8)
    with Image.open(clip) as im:
        assert im.n_frames == 5 and im.size[0] == 32
    pair = merge_films([frames, frames])
    assert len(pair) == 10 and pair[0].shape[1] >= 2 * frames[0].shape[1] and pair[0].shape[1] % 2 == 0
    lpips = {"conventions": ["vgg_3dgs"], "status": {"vgg_3dgs": "unavailable"}}
    metrics = {"building": "x", "test_every": 4, "lpips": lpips, "heatmap_max_error": 0.2, "variants": {},
               "video": {"variants": ["07_train"], "frames": 10, "size_px": [64, 64], "fps": 8,
                         "file": "flythrough.mp4", "clip": "clip.webp"}}  # fmt: skip
    page = build_html(metrics, (), clip)
    assert "data:image/webp;base64," in page and "href='flythrough.mp4'" in page
    assert "![fly-through](clip.webp)" in build_markdown(metrics)
    assert "an orbit through the training cameras' range" in build_markdown(metrics)
    metrics["video"]["path"] = ["uav_0001", "uav_0003"]
    assert "a path through the views uav_0001, uav_0003" in build_markdown(metrics)


def test_a_path_through_views_shows_each_view_at_its_key_frame(tiny):
    """``path = [stems]``: the frames at the named views are those views' renders, and the frames between
    them change gradually (no cut: each frame is nearer its neighbours than the key views are)."""
    from facade_pipeline.evaluation.video import VideoParams, render_path, video_path

    _, data, tr = tiny
    tm = from_trainer(tr, "tiny_path")
    views = [(v.stem, v.camera) for v in data.views]
    names = [views[1][0], views[3][0], views[2][0]]
    params = VideoParams(frames=9, fps=8, scale=1.0, path=tuple(names))
    path = video_path(params, views)
    frames = render_path(path, lambda c, m: render_trained(tm, c, m).rgb, lambda c: None)
    assert len(frames) == 9
    by_stem = dict(views)
    met = []
    for name in names:
        own = (np.clip(render_trained(tm, by_stem[name], None).rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        met.append([i for i, f in enumerate(frames) if np.array_equal(f, own)])
    assert met[0] == [0] and met[-1] == [8] and len(met[1]) == 1 and 0 < met[1][0] < 8, met
    steps = [np.abs(a.astype(int) - b.astype(int)).mean() for a, b in zip(frames, frames[1:], strict=False)]
    keys_apart = np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean()
    assert max(steps) < keys_apart
