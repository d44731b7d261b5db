"""The web viewer as a user meets it: its cameras agree with the pipeline's, every map renders, and a browser
(headless Chromium) pointed at it shows the facade."""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
import urllib.request

import numpy as np
import pytest
from PIL import Image

from facade_pipeline.evaluation.render_views import from_trainer, render_trained
from facade_pipeline.view import (
    MODES,
    Scene,
    ViewCamera,
    Viewer,
    browser_screenshot,
    pose_of,
    render_image,
    viser_camera,
)


@pytest.fixture(scope="module")
def scene(tiny):
    _, data, tr = tiny
    cams = [
        ViewCamera(v.stem, "test" if i in data.test_idx else "train", v.camera,
                   (v.image * 255).astype(np.uint8))
        for i, v in enumerate(data.views)
    ]  # fmt: skip
    return Scene(from_trainer(tr, "tiny"), cams)


def test_viser_cameras_are_the_pipelines(scene):
    """A camera handed to the browser (pose_of) and read back (viser_camera) is the same camera."""
    for vc in scene.cameras:
        cam = vc.camera
        wxyz, pos = pose_of(cam)
        fov = 2 * np.arctan(0.5 * cam.height / cam.K[1, 1])
        back = viser_camera(pos, wxyz, fov, cam.width / cam.height, cam.width)
        assert np.allclose(back.cam_from_world, cam.cam_from_world, atol=1e-9)
        assert (back.width, back.height) == (cam.width, cam.height)
        assert np.allclose(back.K[[0, 1], [0, 1]], cam.K[[0, 1], [0, 1]], rtol=1e-9)


def test_every_mode_renders(scene):
    cam = scene.cameras[1].camera
    final = render_image(scene, cam, "final")
    ref = render_trained(scene.model, cam, None).rgb
    assert np.abs(final / 255.0 - ref).max() < 1 / 255 + 1e-6  # the model's own colour, rounded to 8 bits
    for mode in MODES:
        img = render_image(scene, cam, mode)
        assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.uint8, mode
        if mode != "normals (prior)":  # (no corrected mesh in this scene: the prior is empty)
            assert img.std() > 1.0, mode


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_browser_shows_the_facade(scene, tmp_path):
    """The viewer serves its page; headless Chromium opens it, the server renders the browser's camera
    (a training camera on connect) and the screenshot shows the facade's colours, not a blank canvas."""
    viewer = Viewer(scene, port=_free_port(), width_px=256)
    try:
        url = f"http://127.0.0.1:{viewer.port}/"
        deadline = time.time() + 30
        while True:
            try:
                with urllib.request.urlopen(url, timeout=5) as r:
                    assert r.status == 200 and b"<html" in r.read().lower()
                break
            except OSError:
                assert time.time() < deadline, "the viewer did not answer"
                time.sleep(0.2)
        browser = shutil.which("chromium") or shutil.which("chromium-browser")
        if browser is None:
            pytest.skip("no Chromium: `make test` installs Debian's chromium package where apt can")
        shot = tmp_path / "shot.png"
        shot.write_bytes(browser_screenshot(browser, url, lambda: len(viewer.last_image) > 0, tmp_path))
        img = np.asarray(Image.open(shot).convert("RGB")).astype(float)
        assert img.std() > 5.0, "a blank screenshot"
        # the canvas shows what the server rendered for this browser: compare brightness patterns where no
        # overlay covers the canvas (the sidebar is top right, the frustums are thin lines)
        (sent,) = viewer.last_image.values()
        h, w = img.shape[:2]
        sent = np.asarray(Image.fromarray(sent).resize((w, h), Image.Resampling.BILINEAR)).astype(float)
        region = (slice(h // 2, h - 40), slice(110, w // 2))
        a, b = img[region].mean(axis=2).ravel(), sent[region].mean(axis=2).ravel()
        corr = np.corrcoef(a, b)[0, 1]
        assert corr > 0.7, f"the screenshot does not show the render (correlation {corr:.2f})"
    finally:
        viewer.stop()


def test_a_building_without_a_trained_model_is_one_line(tmp_path):
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "facade_pipeline.view", "--building", "nothing", "--data-root", str(tmp_path)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().count("\n") == 0 and "doit train_gs" in out.stderr
