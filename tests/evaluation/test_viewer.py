"""The web viewer as a user meets it: its cameras agree with the pipeline's, every map renders, the field of
view magnifies, frames are smaller while the camera moves, a selected camera's photo shows beside the
render, the mesh and panel overlays appear where their data exists, and a browser (headless Chromium)
pointed at it shows the facade, takes the field of view from the slider, looks through a clicked camera
and reads out a frame rate."""

from __future__ import annotations

import io
import json
import re
import shutil
import socket
import subprocess
import time
import urllib.request

import cv2
import numpy as np
import pytest
from PIL import Image

from facade_pipeline import view as view_module
from facade_pipeline.evaluation.render_views import from_trainer, render_trained
from facade_pipeline.geometry.frames import invert_rigid, transform_points
from facade_pipeline.io.meshes import read_mesh
from facade_pipeline.meshing.correct import FRAME, GLASS
from facade_pipeline.scene import ImportedScene
from facade_pipeline.view import (
    MODES,
    MOVING_SECONDS,
    SHOWN_CORRELATION,
    Scene,
    ViewCamera,
    Viewer,
    browser_screenshot,
    fov_of,
    headless_page,
    pose_of,
    rate_text,
    render_image,
    render_width,
    shown_correlation,
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


@pytest.fixture(scope="module")
def scene_with_overlays(tiny, scene):
    """The same model and cameras with a labelled mesh (the true glass and frames, standing in for the
    corrected mesh) and the true panels, moved into the local frame as the pipeline's own are."""
    layout, _, _ = tiny
    local_from_georef = invert_rigid(ImportedScene.load(layout).georef_from_local)
    verts, tris, labels = [], [], []
    for key, label in (("gt_glass_mesh", GLASS), ("gt_frame_mesh", FRAME)):
        m = read_mesh(layout.path(key))
        tris.append(np.asarray(m.triangles) + sum(len(v) for v in verts))
        verts.append(transform_points(local_from_georef, np.asarray(m.vertices)))
        labels.append(np.full(len(tris[-1]), label))
    panels = json.loads(layout.path("gt_panels").read_text())["panels"]
    corners = np.array([transform_points(local_from_georef, np.array(p["corners"], float)) for p in panels])
    mesh = (np.concatenate(verts), np.concatenate(tris), np.concatenate(labels))
    return Scene(scene.model, scene.cameras, mesh, corners)


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


def test_a_narrower_field_of_view_magnifies(scene):
    """Halving tan(fov / 2) at the same pose and width shows the middle half of the wider view, twice as
    large: the narrow render, halved, matches the wide render's middle and not the wide render whole."""
    cam = scene.cameras[2].camera
    wxyz, pos = pose_of(cam)
    wide_fov = fov_of(cam)
    narrow_fov = 2 * np.arctan(0.5 * np.tan(0.5 * wide_fov))
    aspect, w = cam.width / cam.height, 128
    wide = render_image(scene, viser_camera(pos, wxyz, wide_fov, aspect, w), "final").astype(float)
    narrow = render_image(scene, viser_camera(pos, wxyz, narrow_fov, aspect, w), "final").astype(float)
    assert wide.shape == narrow.shape  # the same frame size: only the field of view changed
    h = wide.shape[0]
    middle = wide[h // 4 : h // 4 + h // 2, w // 4 : w // 4 + w // 2]
    halved = cv2.resize(narrow, (middle.shape[1], middle.shape[0]), interpolation=cv2.INTER_AREA)
    whole = cv2.resize(wide, (middle.shape[1], middle.shape[0]), interpolation=cv2.INTER_AREA)
    assert np.abs(halved - middle).mean() < 0.5 * np.abs(halved - whole).mean()
    assert np.corrcoef(halved.ravel(), middle.ravel())[0, 1] > 0.95


def test_frames_are_smaller_while_the_camera_moves():
    """The render-size policy: the moving fraction of the width (32 px at least) until the camera has kept
    still for MOVING_SECONDS, then the full width."""
    assert render_width(512, 0.5, 0.0) == 256
    assert render_width(512, 0.5, MOVING_SECONDS - 1e-3) == 256
    assert render_width(512, 0.5, MOVING_SECONDS) == 512
    assert render_width(512, 0.5, 10.0) == 512
    assert render_width(128, 0.125, 0.0) == 32  # never smaller than 32 px
    assert render_width(512, 1.0, 0.0) == 512


def test_the_frame_rate_reads_below_one():
    """A slow CPU frame reads as its rate with two decimals, not as a whole number rounded to 0."""
    assert rate_text(2.4, 512, 384) == "0.42 (2400 ms, 512 x 384 px)"
    assert rate_text(0.25, 256, 192).startswith("4.00 ")


def test_a_selected_camera_shows_its_photo_beside_the_render(scene, monkeypatch):
    """After a frustum is selected, a frame from that camera is its photo, a gap and the render through
    it; a pose from before the click, reported just after it, does not drop the photo; once the camera
    moves away the photo goes (and stays gone when it comes back)."""
    viewer = Viewer(scene, port=_free_port(), width_px=64)
    try:
        vc = scene.cameras[3]
        cam = vc.camera
        wxyz, pos = pose_of(cam)
        args = (wxyz, fov_of(cam), cam.width / cam.height, cam.width)
        viewer.select(7, vc)
        img = viewer.frame(7, pos, *args)
        render = render_image(scene, cam, "final")
        photo_w = round(vc.photo.shape[1] * cam.height / vc.photo.shape[0])
        assert img.shape == (cam.height, photo_w + 4 + cam.width, 3)
        assert np.array_equal(img[:, -cam.width :], render)
        assert np.abs(img[:, :photo_w].astype(float) - vc.photo.astype(float)).mean() < 2.0
        assert np.array_equal(viewer.frame(8, pos, *args), render)  # another browser: no photo
        assert viewer.frame(7, pos + [0.5, 0, 0], *args).shape == render.shape  # a stale report
        assert viewer.frame(7, pos, *args).shape == img.shape  # the photo is still selected
        monkeypatch.setattr(view_module, "SELECT_GRACE_SECONDS", 0.0)  # the grace period is over
        assert viewer.frame(7, pos + [0.5, 0, 0], *args).shape == render.shape
        assert np.array_equal(viewer.frame(7, pos, *args), render)
    finally:
        viewer.stop()


def test_overlays_appear_where_their_data_exists(scene, scene_with_overlays):
    """With a corrected mesh and 3D panels the viewer adds both overlays (the mesh hidden until its box is
    ticked, the panels shown, each panel's four edges), the prior's normals render from the mesh and the
    facade mask comes from it; without them neither overlay exists."""
    plain = Viewer(scene, port=_free_port(), width_px=64)
    try:
        assert plain.mesh_overlay is None and plain.panels_overlay is None
    finally:
        plain.stop()
    s = scene_with_overlays
    viewer = Viewer(s, port=_free_port(), width_px=64)
    try:
        mesh, panels = viewer.mesh_overlay, viewer.panels_overlay
        assert mesh is not None and panels is not None
        assert np.allclose(mesh.vertices, s.mesh[0], atol=1e-4) and len(mesh.faces) == len(s.mesh[1])
        assert panels.points.shape == (4 * len(s.panels), 2, 3)
        assert np.allclose(panels.points[:4, 0], s.panels[0], atol=1e-4)
        assert not mesh.visible and panels.visible
        viewer.show_mesh.value, viewer.show_panels.value = True, False
        assert mesh.visible and not panels.visible
    finally:
        viewer.stop()
    cam = s.cameras[1].camera
    mask = s.facade_mask(cam)
    assert 0.05 < mask.mean() < 1.0  # the facade covers part of the view
    n = render_image(s, cam, "normals (prior)").astype(float) / 255.0 * 2.0 - 1.0
    length = np.linalg.norm(n, axis=2)
    assert np.abs(length[mask] - 1.0).max() < 0.05 and length[~mask].max() < 0.05  # unit on the facade


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

        # what --screenshot takes: the page looked at until it shows the server's render (a TimeoutError
        # names the last correlation otherwise)
        png = browser_screenshot(browser, url, lambda: next(iter(viewer.last_image.values()), None), tmp_path,
                                 timeout=WAIT_S)  # fmt: skip
        img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(float)
        assert img.std() > 5.0, "a blank screenshot"
    finally:
        viewer.stop()


def test_the_screenshot_check_sees_a_dark_render_through_lines_and_jpeg():
    """``shown_correlation`` as the browser tests meet it: a dark, low-contrast render (a barely trained
    model) shown at the page's size through JPEG, with a frustum's bright edge drawn across the compared
    region, counts as shown; the same render mirrored or moved by a fifth of its width does not."""
    rng = np.random.default_rng(3)
    blobs = cv2.GaussianBlur(rng.random((146, 256)), (0, 0), 6)
    blobs = (blobs - blobs.min()) / np.ptp(blobs)
    render = np.repeat((8 + 60 * blobs)[..., None], 3, axis=2).astype(np.uint8)
    page = cv2.resize(render, (800, 457), interpolation=cv2.INTER_LINEAR)
    _, jpeg = cv2.imencode(".jpg", page[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 60])
    shot = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)
    cv2.line(shot, (170, 0), (170, 456), (230, 160, 60), 3)  # the frustum's edge: 5 px, light blue (BGR)
    png = cv2.imencode(".png", shot)[1].tobytes()
    assert shown_correlation(png, render) > SHOWN_CORRELATION
    assert shown_correlation(png, render[:, ::-1].copy()) < SHOWN_CORRELATION
    assert shown_correlation(png, np.roll(render, 51, axis=1)) < SHOWN_CORRELATION
    blank = cv2.imencode(".png", np.zeros_like(shot))[1].tobytes()
    assert shown_correlation(blank, render) == 0.0


def test_a_building_without_a_trained_model_is_one_line(tmp_path):
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "facade_pipeline.view", "--building", "nothing", "--data-root", str(tmp_path)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().count("\n") == 0 and "doit train_gs" in out.stderr


def _same(img: np.ndarray, expect: np.ndarray) -> bool:
    """The same frame, up to the rounding of a render to 8 bits."""
    return img.shape == expect.shape and np.abs(img.astype(int) - expect.astype(int)).max() <= 1


#: how long a state may take to come: software WebGL beside other work is slow, and a wait ends as soon as
#: the state is there, so a long bound costs a passing run nothing
WAIT_S = 180.0


def _wait(what: str, ok, timeout: float = WAIT_S, found=lambda: "") -> None:
    deadline = time.time() + timeout
    while not ok():
        assert time.time() < deadline, f"timed out waiting until {what} {found()}"
        time.sleep(0.1)


def test_a_browser_follows_the_slider_and_a_clicked_camera(scene, tmp_path):
    """In headless Chromium: once the first frame is shown the sidebar reads a real frame rate; moving the
    field-of-view slider changes the browser's camera (it reports the new angle back) and the next frame
    is rendered with it; clicking a frustum (its click handler, as the browser's click calls it) puts the
    browser's camera at that camera and the frames show its photo beside the render at full width."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("no Chromium: `make test` installs Debian's chromium package where apt can")
    from viser import SceneNodePointerEvent

    viewer = Viewer(scene, port=_free_port(), width_px=96)
    try:
        with headless_page(browser, f"http://127.0.0.1:{viewer.port}/", tmp_path) as call:
            _wait("the first frame is sent", lambda: sum(viewer.frames_sent.values()) > 0)
            (client,) = viewer.server.get_clients().values()
            cid = client.client_id
            home = viewer._home().camera

            def at_home() -> bool:
                # the browser opens at its own default camera and reports it until the server's pose comes
                return abs(client.camera.fov - fov_of(home)) < 1e-6

            _wait("the browser's camera is the home camera", at_home,
                  found=lambda: f"(its field of view {np.degrees(client.camera.fov):.1f} degrees)")
            assert viewer.fov.value == round(np.degrees(fov_of(home)))

            def readout() -> str:
                js = "Array.from(document.querySelectorAll('input')).map(e => e.value).join('|')"
                return call("Runtime.evaluate", expression=js, returnByValue=True)["result"]["value"]

            rate = re.compile(r"(\d+\.\d\d) \(\d+ ms, \d+ x \d+ px\)")
            _wait("the page shows the frame rate", lambda: rate.search(readout()) is not None)
            assert float(rate.search(readout()).group(1)) > 0

            reported = []
            client.camera.on_update(lambda cam: reported.append(cam.fov))
            sent = viewer.frames_sent[cid]
            viewer.fov.value = 25.0
            _wait("the browser reports the slider's field of view",
                  lambda: any(abs(f - np.radians(25.0)) < 1e-4 for f in reported))  # fmt: skip
            _wait("a frame with it", lambda: viewer.frames_sent[cid] > sent + 1 and
                  time.monotonic() - viewer._dirty[cid] > MOVING_SECONDS + 0.5)  # fmt: skip
            cam = client.camera
            narrow = viser_camera(cam.position, cam.wxyz, np.radians(25.0), cam.aspect, 96)
            expect = render_image(scene, narrow, "final")
            # (an earlier full-size frame, of the wider field of view, has the same size: wait for this one)
            _wait("the full-size frame with it", lambda: _same(viewer.last_image[cid], expect))

            vc = scene.cameras[0]
            frustum = viewer._frustums[0]
            event = SceneNodePointerEvent(
                client=client, client_id=cid, event="click", target=frustum, ray_origin=(0, 0, 0),
                ray_direction=(0, 0, 1), screen_pos=(0.5, 0.5), instance_index=None, modifier=None,
            )  # fmt: skip
            for entry in frustum._impl.click_cb:
                entry.callback(event)
            wxyz, pos = pose_of(vc.camera)

            def at_clicked_camera() -> bool:  # a report of the browser's pose from before the click may come
                c = client.camera
                return (np.allclose(c.position, pos, atol=1e-6) and abs(c.fov - fov_of(vc.camera)) < 1e-6
                        and abs(abs(np.dot(c.wxyz, wxyz)) - 1.0) < 1e-6)  # the same rotation (q or -q)

            _wait("the browser's camera is the clicked one", at_clicked_camera,
                  found=lambda: f"({np.linalg.norm(client.camera.position - pos):.2g} m away)")  # fmt: skip
            assert viewer.fov.value == round(np.degrees(fov_of(vc.camera)))  # the slider follows
            # the render keeps the browser's aspect; the photo is scaled to the render's height beside it
            through = viser_camera(pos, wxyz, fov_of(vc.camera), client.camera.aspect, 96)
            render = render_image(scene, through, "final")
            photo_w = round(vc.photo.shape[1] * render.shape[0] / vc.photo.shape[0])
            left = cv2.resize(vc.photo, (photo_w, render.shape[0]), interpolation=cv2.INTER_AREA)

            def photo_beside_render() -> bool:
                img = viewer.last_image[cid]
                return (img.shape == (render.shape[0], photo_w + 4 + 96, 3) and _same(img[:, -96:], render)
                        and np.array_equal(img[:, :photo_w], left))  # fmt: skip

            _wait("the photo beside a full-size frame", photo_beside_render,
                  found=lambda: f"(frame {viewer.last_image[cid].shape}, camera "
                          f"{np.linalg.norm(client.camera.position - pos):.2g} m from the clicked one)",
                  )  # fmt: skip
    finally:
        viewer.stop()
