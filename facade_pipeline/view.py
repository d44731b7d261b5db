"""Fly around a trained facade in the browser, reflections included.

    python -m facade_pipeline.view --building demo [--variant NAME] [--port 8080] [--data-root DIR]

A viser server (the web viewer nerfstudio and gsplat use) shows the model rendered by this project's own
renderer and shading: each browser's camera is rendered on the server and sent as the scene's background,
at a lower resolution while the camera moves and at full resolution once it stops. The sidebar switches
between the final colour and the maps behind it (diffuse, specular, reflectivity, the splats' normals, the
baked prior's normals, depth), sets the camera's vertical field of view and reads out the frame rate; the
training and held-out cameras are frustums (click one to look through it, its photo beside the render);
the corrected mesh and the 3D panels are overlays. The specular term is
limited to the facade as in training: each frame's facade mask is cast from the corrected mesh.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from facade_pipeline.bake.maps import bake_view
from facade_pipeline.errors import PipelineError
from facade_pipeline.evaluation.render_views import TrainedModel, render_maps
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics
from facade_pipeline.geometry.raycast import MeshRaycaster

MODES = ("final", "diffuse", "specular", "reflectivity", "normals (splats)", "normals (prior)", "depth")
MOVING_SECONDS = 0.25
"""a camera updated more recently than this is moving: it is rendered at the lower resolution"""
SELECT_GRACE_SECONDS = 2.0
"""after a camera is selected, the browser's reports of a pose from before the click are not taken for a
move away from it for this long (s): its photo stays beside the render"""
FOV_RANGE_DEG = (10.0, 120.0)
"""the field-of-view slider's range (vertical, degrees)"""


@dataclass(frozen=True)
class ViewCamera:
    """A training or held-out camera shown as a frustum, with its photo."""

    stem: str
    split: str  # "train" or "test"
    camera: PinholeCamera
    photo: np.ndarray | None = None  # [H, W, 3] uint8


@dataclass
class Scene:
    """What the viewer shows: a trained model, its cameras, and the corrected mesh with its labels."""

    model: TrainedModel
    cameras: list[ViewCamera]
    mesh: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    """(vertices [V, 3], triangles [F, 3], labels [F]) of the corrected mesh: the facade masks and overlay"""
    panels: np.ndarray | None = None
    """[P, 4, 3] corners of the 3D panels (the overlay)"""
    _caster: MeshRaycaster | None = field(default=None, repr=False)

    def facade_mask(self, camera: PinholeCamera) -> np.ndarray | None:
        if self.mesh is None:
            return None
        if self._caster is None:
            self._caster = MeshRaycaster(self.mesh[0], self.mesh[1])
        return bake_view(self._caster, camera, 1 << 18, None, self.mesh[2]).label >= 1

    def prior_normals(self, camera: PinholeCamera) -> np.ndarray:
        if self.mesh is None:
            return np.zeros((camera.height, camera.width, 3), np.float32)
        if self._caster is None:
            self._caster = MeshRaycaster(self.mesh[0], self.mesh[1])
        return bake_view(self._caster, camera, 1 << 18, None, self.mesh[2]).normal


def viser_camera(position, wxyz, fov_y: float, aspect: float, width: int) -> PinholeCamera:
    """The pinhole camera of a viser camera (OpenCV axes: +z forward, +y down; ``fov_y`` vertical, rad)
    rendered ``width`` pixels wide."""
    h = max(2, round(width / aspect))
    fy = 0.5 * h / np.tan(0.5 * fov_y)
    w, x, y, z = (float(v) for v in wxyz)
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )  # world_from_cam rotation
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ np.asarray(position, float)
    return PinholeCamera(intrinsics(fy, fy, width / 2, h / 2), T, width, h)


def fov_of(camera: PinholeCamera) -> float:
    """Vertical field of view of ``camera`` (rad), as viser's camera has it."""
    return float(2 * np.arctan(0.5 * camera.height / camera.K[1, 1]))


def render_width(full_px: int, moving_factor: float, seconds_since_change: float) -> int:
    """Pixels across of the next frame: ``full_px`` once the camera has kept still for ``MOVING_SECONDS``,
    ``moving_factor`` of it (32 at least) while it moves, so that a moving camera gets frames quickly."""
    if seconds_since_change >= MOVING_SECONDS:
        return int(full_px)
    return max(32, int(full_px * moving_factor))


def rate_text(seconds: float, width: int, height: int) -> str:
    """The frame-rate readout of a frame that took ``seconds`` from reading the browser's camera to handing
    the image to its connection, with two decimals: a CPU frame of 2.4 s reads 0.42, where a whole number
    would read 0."""
    return f"{1.0 / max(seconds, 1e-6):.2f} ({1000 * seconds:.0f} ms, {width} x {height} px)"


def pose_of(camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of ``camera`` in viser's convention (world_from_cam, OpenCV axes)."""
    R = camera.cam_from_world[:3, :3].T
    q = _quat_from_matrix(R)
    return q, camera.center


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method)."""
    t = np.trace(R)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q) * (1 if q[0] >= 0 else -1)


def render_image(scene: Scene, camera: PinholeCamera, mode: str) -> np.ndarray:
    """uint8 [H, W, 3] of ``camera`` in one of ``MODES``."""
    if mode == "normals (prior)":
        return _unit_to_u8(scene.prior_normals(camera))
    r = render_maps(scene.model, camera, scene.facade_mask(camera))
    if mode == "final":
        x = r.rgb
    elif mode == "diffuse":
        x = r.diffuse
    elif mode == "specular":
        x = r.specular
    elif mode == "reflectivity":
        x = r.refl[..., None].expand(*r.refl.shape, 3)
    elif mode == "normals (splats)":
        return _unit_to_u8(r.normal.cpu().numpy())
    elif mode == "depth":
        d = r.depth.cpu().numpy()
        ok = (r.alpha.cpu().numpy() > 0.5) & (d > 0)
        lo, hi = np.percentile(d[ok], (2, 98)) if ok.any() else (0.0, 1.0)
        u = np.clip((d - lo) / max(hi - lo, 1e-6), 0, 1)
        img = cv2.applyColorMap((u * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
        img[~ok] = 0
        return np.ascontiguousarray(img)
    else:
        raise ValueError(f"mode {mode!r} not one of {MODES}")
    return (x.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def _unit_to_u8(n: np.ndarray) -> np.ndarray:
    return (np.clip(0.5 * np.asarray(n, np.float32) + 0.5, 0, 1) * 255 + 0.5).astype(np.uint8)


class Viewer:
    """The viser server of one scene: per browser a thread renders the camera when it changes."""

    def __init__(self, scene: Scene, port: int = 8080, host: str = "127.0.0.1", width_px: int = 512):
        import viser

        self.scene = scene
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        gui = self.server.gui
        self.mode = gui.add_dropdown("show", MODES, initial_value="final")
        self.width = gui.add_slider("width (px)", min=64, max=1920, step=32, initial_value=width_px)
        self.moving_factor = gui.add_slider("while moving", min=0.125, max=1.0, step=0.125, initial_value=0.5)
        self.fov = gui.add_slider("field of view (deg)", min=FOV_RANGE_DEG[0], max=FOV_RANGE_DEG[1], step=1.0,
                                  initial_value=self._slider_deg(fov_of(self._home().camera))
                                  if scene.cameras else 60.0)  # fmt: skip
        # a text, not a number box: viser shows a number with the digits of its first value, and a first
        # value of 0 rounded every rate below 0.5 frames per second (a CPU frame at full size) to 0
        self.fps = gui.add_text("frames per second", initial_value="no frame yet", disabled=True)
        self.show_cameras = gui.add_checkbox("cameras", initial_value=True)
        self.show_mesh = gui.add_checkbox("corrected mesh", initial_value=False)
        self.show_panels = gui.add_checkbox("3D panels", initial_value=True)
        self._photo: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # client -> (photo, its camera centre)
        self._dirty: dict[int, float] = {}
        self.last_image: dict[int, np.ndarray] = {}
        """per client, the last image sent (what its browser shows behind the overlays)"""
        self.frames_sent: dict[int, int] = {}
        """per client, how many images were sent"""
        self.mesh_overlay = None
        """the corrected mesh's overlay (None without a mesh)"""
        self.panels_overlay = None
        """the 3D panels' overlay (None without panels)"""
        self._fov_from_camera = False  # the slider follows a camera set by the viewer: leave the others
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._add_overlays()
        for handle in (self.mode, self.width, self.moving_factor):
            handle.on_update(lambda _: self._touch_all())
        self.fov.on_update(lambda _: self._fov_changed())
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    # --- scene overlays ---
    def _add_overlays(self) -> None:
        s, scene = self.server.scene, self.scene
        s.set_up_direction("+z")
        self._frustums = []
        for vc in scene.cameras:
            cam = vc.camera
            wxyz, pos = pose_of(cam)
            colour = (40, 160, 255) if vc.split == "train" else (255, 140, 0)
            f = s.add_camera_frustum(f"/cameras/{vc.split}/{vc.stem}", fov=fov_of(cam),
                                     aspect=cam.width / cam.height, scale=self._frustum_scale(),
                                     color=colour, wxyz=wxyz, position=pos)  # fmt: skip
            f.on_click(lambda event, vc=vc: self._look_through(event.client, vc))
            self._frustums.append(f)
        self.show_cameras.on_update(lambda _: [setattr(f, "visible", self.show_cameras.value)
                                               for f in self._frustums])  # fmt: skip
        if scene.mesh is not None:
            v, t, labels = scene.mesh
            self.mesh_overlay = s.add_mesh_simple(
                "/corrected_mesh", v.astype(np.float32), t.astype(np.uint32), color=(180, 180, 190),
                opacity=0.4, visible=self.show_mesh.value,
            )  # fmt: skip
            self.show_mesh.on_update(lambda _: setattr(self.mesh_overlay, "visible", self.show_mesh.value))
        if scene.panels is not None and len(scene.panels):
            p = scene.panels
            segs = np.stack([p, np.roll(p, -1, axis=1)], axis=2).reshape(-1, 2, 3).astype(np.float32)
            self.panels_overlay = s.add_line_segments("/panels", segs, colors=(60, 220, 90), thickness=2.0,
                                                      thickness_units="screen",
                                                      visible=self.show_panels.value)  # fmt: skip
            self.show_panels.on_update(
                lambda _: setattr(self.panels_overlay, "visible", self.show_panels.value)
            )

    def _frustum_scale(self) -> float:
        centres = np.array([vc.camera.center for vc in self.scene.cameras]) if self.scene.cameras else None
        if centres is None or len(centres) < 2:
            return 0.3
        return float(0.05 * np.linalg.norm(np.ptp(centres, axis=0)))

    # --- clients ---
    def _home(self) -> ViewCamera:
        """The camera a browser starts at: the middle training camera."""
        train = [vc for vc in self.scene.cameras if vc.split == "train"] or self.scene.cameras
        return train[len(train) // 2]

    def _connect(self, client) -> None:
        if self.scene.cameras:
            self._set_pose(client, self._home().camera)
        client.camera.on_update(lambda _: self._touch(client.client_id))
        self._touch(client.client_id)
        thread = threading.Thread(target=self._render_loop, args=(client,), daemon=True)
        self._threads.append(thread)
        thread.start()

    def _disconnect(self, client) -> None:
        with self._lock:
            self._dirty.pop(client.client_id, None)  # its render loop ends
            self._photo.pop(client.client_id, None)

    def _set_pose(self, client, camera: PinholeCamera) -> None:
        """Put the browser's camera at ``camera`` (its field of view included; the slider follows)."""
        wxyz, pos = pose_of(camera)
        with client.atomic():
            client.camera.fov = fov_of(camera)
            client.camera.wxyz = wxyz
            client.camera.position = pos
        self._fov_from_camera = True
        try:
            self.fov.value = self._slider_deg(fov_of(camera))
        finally:
            self._fov_from_camera = False

    @staticmethod
    def _slider_deg(fov: float) -> float:
        return float(np.clip(round(np.degrees(fov)), *FOV_RANGE_DEG))

    def _fov_changed(self) -> None:
        """The slider moved: every browser's camera takes its field of view (and is rendered anew)."""
        if self._fov_from_camera:
            return
        fov = float(np.radians(self.fov.value))
        for client in list(self.server.get_clients().values()):
            client.camera.fov = fov
            self._touch(client.client_id)

    def _look_through(self, client, vc: ViewCamera) -> None:
        """A frustum was clicked: the browser looks through ``vc``, its photo beside the render."""
        self._set_pose(client, vc.camera)  # first: a frame of the old pose must not see the new selection
        self.select(client.client_id, vc)
        self._touch(client.client_id)

    def select(self, client_id: int, vc: ViewCamera) -> None:
        """Show ``vc``'s photo beside the frames of ``client_id`` while it looks from ``vc``'s centre."""
        with self._lock:
            if vc.photo is not None:
                self._photo[client_id] = (vc.photo, vc.camera.center, time.monotonic())

    def frame(self, client_id: int, position, wxyz, fov: float, aspect: float, width_px: int) -> np.ndarray:
        """The image sent to ``client_id`` for its camera (viser's pose, ``fov`` vertical in rad): the render
        in the chosen mode, with the selected camera's photo on its left while the camera stays there."""
        img = render_image(self.scene, viser_camera(position, wxyz, fov, aspect, width_px), self.mode.value)
        with self._lock:
            photo = self._photo.get(client_id)
            if photo is not None and not np.allclose(position, photo[1], atol=1e-4):
                # the browser may report a pose from before the click for a moment: the photo goes once
                # the camera is away from the selected one after that
                if time.monotonic() - photo[2] > SELECT_GRACE_SECONDS:
                    self._photo.pop(client_id, None)
                photo = None
        return img if photo is None else _beside(photo[0], img)

    def _touch(self, client_id: int) -> None:
        with self._lock:
            self._dirty[client_id] = time.monotonic()

    def _touch_all(self) -> None:
        with self._lock:
            for k in self._dirty:
                self._dirty[k] = time.monotonic()

    def _render_loop(self, client) -> None:
        """Render while the camera moves (low resolution), then once at full resolution when it stops."""
        cid, full_done_for = client.client_id, None
        while not self._stop.is_set():
            with self._lock:
                stamp = self._dirty.get(cid)
            if stamp is None:
                return  # disconnected
            since = time.monotonic() - stamp
            moving = since < MOVING_SECONDS
            if not moving and full_done_for == stamp:
                time.sleep(0.02)
                continue
            try:
                t0 = time.perf_counter()
                cam = client.camera
                width = render_width(self.width.value, self.moving_factor.value, since)
                img = self.frame(cid, cam.position, cam.wxyz, cam.fov, cam.aspect, width)
                if client.client_id not in self.server.get_clients():
                    return  # left while this frame was rendered
                client.scene.set_background_image(img, format="jpeg", jpeg_quality=90)
                self.last_image[cid] = img
                self.frames_sent[cid] = self.frames_sent.get(cid, 0) + 1
                self.fps.value = rate_text(time.perf_counter() - t0, width, img.shape[0])
            except Exception as e:  # a client that disconnects mid-render
                if "disconnect" in str(e).lower():
                    return
                raise
            if not moving:
                full_done_for = stamp

    def stop(self) -> None:
        """Stop rendering (a render under way finishes: native thread pools must not be torn down under
        it at exit), then the server."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=60)
        self.server.stop()


def _beside(photo: np.ndarray, render: np.ndarray) -> np.ndarray:
    """The photo (left) and the render (right) at the render's height."""
    h = render.shape[0]
    w = max(1, round(photo.shape[1] * h / photo.shape[0]))
    left = cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA)
    return np.concatenate([left, np.zeros((h, 4, 3), np.uint8), render], axis=1)


@contextlib.contextmanager
def headless_page(
    browser: str, url: str, workdir: Path, timeout: float = 90.0, size: tuple[int, int] = (800, 600)
) -> Iterator[Callable[..., dict]]:
    """Open ``url`` in headless Chromium (``browser``: its executable; its profile goes in ``workdir``) and
    yield ``call(method, **params)``, which sends one DevTools protocol command to the page and returns its
    result; the page is left and Chromium stopped on exit."""
    from websockets.sync.client import connect

    port = _free_port()
    proc = subprocess.Popen(
        [browser, "--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
         "--enable-unsafe-swiftshader", f"--window-size={size[0]},{size[1]}",
         f"--remote-debugging-port={port}",
         f"--user-data-dir={Path(workdir) / 'chromium'}", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.time() + timeout
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=5) as r:
                    pages = [t for t in json.loads(r.read()) if t["type"] == "page"]
                if pages:
                    break
            except OSError:
                pass
            assert time.time() < deadline, "Chromium did not start"
            time.sleep(0.2)
        with connect(pages[0]["webSocketDebuggerUrl"], max_size=None) as ws:
            ids = iter(range(1, 1 << 30))

            def call(method, **params):
                i = next(ids)
                ws.send(json.dumps({"id": i, "method": method, "params": params}))
                while True:
                    msg = json.loads(ws.recv(timeout=max(1.0, deadline - time.time())))
                    if msg.get("id") == i:
                        return msg.get("result", {})

            call("Page.navigate", url=url)
            try:
                yield call
            finally:
                call("Page.navigate", url="about:blank")  # leave the viewer cleanly before Chromium goes
                time.sleep(0.5)
    finally:
        proc.kill()
        proc.wait()


#: a screenshot shows the server's last render once their brightness correlates at least this well
SHOWN_CORRELATION = 0.7

#: the median filter both images pass before they are compared: more than twice as wide as the lines drawn
#: over the render (the frustum of the camera looked through, its edges inside the compared region) and the
#: JPEG noise of the image's way to the page, so that a dark, low-contrast render is judged by its shapes,
#: not by a line or the codec
SHOWN_MEDIAN_PX = 11


def shown_correlation(png: bytes, image: np.ndarray) -> float:
    """How well a screenshot of the page (PNG bytes) shows ``image`` [H, W, 3] uint8, the server's last
    render: the correlation of their brightness, median-filtered (``SHOWN_MEDIAN_PX``), over the lower left
    of the canvas, where no panel covers it (the sidebar is top right, viser's buttons along the left
    edge)."""
    shot = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    h, w = shot.shape[:2]
    sent = cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR)
    region = (slice(h // 2, h - 40), slice(110, w // 2))
    grey = (cv2.cvtColor(shot, cv2.COLOR_BGR2GRAY), cv2.cvtColor(sent, cv2.COLOR_RGB2GRAY))
    a, b = (cv2.medianBlur(g, SHOWN_MEDIAN_PX)[region].astype(np.float64).ravel() for g in grey)
    return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else 0.0


def browser_screenshot(
    browser: str,
    url: str,
    last_image: Callable[[], np.ndarray | None],
    workdir: Path,
    timeout: float = 90.0,
    size: tuple[int, int] = (800, 600),
) -> bytes:
    """PNG of ``url`` in headless Chromium (``browser``: its executable), taken through the DevTools
    protocol once it shows the server's last render (``last_image()``, None before the first;
    ``shown_correlation``): the image travels and is drawn in the page's own time (software WebGL), so
    the page is looked at until it is there. Chromium's profile goes in ``workdir``; ``TimeoutError``
    after ``timeout`` seconds."""
    deadline = time.time() + timeout
    with headless_page(browser, url, workdir, timeout, size) as call:
        seen = "no render sent"
        while True:
            image = last_image()
            if image is not None:
                png = base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
                correlation = shown_correlation(png, image)
                if correlation > SHOWN_CORRELATION:
                    return png
                seen = f"the last screenshot correlates {correlation:.2f} with the render"
            if time.time() > deadline:
                raise TimeoutError(f"the page did not show the viewer's render in {timeout:.0f} s ({seen})")
            time.sleep(0.2)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def load_scene(building: str, data_root: str | None, variant: str | None, device: str = "cpu") -> Scene:
    """The trained model of ``building`` (07_train, or ``variants/<variant>``), its cameras and photos,
    the corrected mesh and the 3D panels."""
    from facade_pipeline.evaluation.render_views import load_trained
    from facade_pipeline.io.images import read_image
    from facade_pipeline.io.meshes import read_mesh
    from facade_pipeline.layout import BuildingLayout
    from facade_pipeline.meshing.correct import read_labels
    from facade_pipeline.panels3d.model import PanelSet
    from facade_pipeline.scene import ImportedScene
    from facade_pipeline.training.trained import TrainedModelFiles

    layout = BuildingLayout.for_building(building, data_root)
    if variant:
        tv = TrainedModelFiles.from_dir(layout.path("variant_dir", variant=variant))
    else:
        tv = TrainedModelFiles.pipeline(layout)
    model = load_trained(tv, device)
    split = tv.split_stems()
    scene = ImportedScene.load(layout)
    cams = []
    for v in scene.uav_views:
        which = "test" if v.stem in split["test"] else "train"
        cams.append(ViewCamera(v.stem, which, v.camera, read_image(layout.root / v.image)))
    mesh = read_mesh(layout.path("correct_mesh"))
    tri = np.asarray(mesh.triangles)
    labels = read_labels(layout.path("correct_mesh_labels"), len(tri))
    panels_path = layout.path("regularize_panels")
    panels = None
    if panels_path.is_file():
        ps = PanelSet.load(panels_path)
        panels = np.array([p.corners for p in ps.panels]) if ps.panels else None
    return Scene(model, cams, (np.asarray(mesh.vertices), tri, labels), panels)


def main(argv: list[str] | None = None, ready: Callable[[Viewer], None] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m facade_pipeline.view", description=__doc__.splitlines()[0])
    ap.add_argument("--building", default="demo")
    ap.add_argument("--variant", default=None, help="a model under variants/ (default: 07_train)")
    ap.add_argument("--data-root", default=None)
    ap.add_argument("--port", type=int, default=8080)
    ap.add_argument("--host", default="127.0.0.1", help="0.0.0.0 to let other machines connect")
    ap.add_argument("--width", type=int, default=512, help="render width while the camera is still (px)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--screenshot", default=None, metavar="PNG",
                    help="open the viewer in headless Chromium, save what it shows and stop")  # fmt: skip
    args = ap.parse_args(argv)
    try:
        scene = load_scene(args.building, args.data_root, args.variant, args.device)
    except PipelineError as e:
        print(f"view: {e}", file=sys.stderr)
        return 2
    viewer = Viewer(scene, _free_port() if args.screenshot else args.port, args.host, args.width)
    url = f"http://{args.host}:{viewer.port}"
    if args.screenshot:
        return _save_screenshot(viewer, url, Path(args.screenshot))
    print(f"view: {args.building} at {url} (Ctrl-C to stop)", flush=True)
    if ready is not None:
        ready(viewer)
    try:
        while not viewer._stop.is_set():
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    viewer.stop()
    return 0


def _save_screenshot(viewer: Viewer, url: str, out: Path) -> int:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        print("view: --screenshot needs Chromium (Debian: apt-get install chromium)", file=sys.stderr)
        viewer.stop()
        return 2
    def last_image() -> np.ndarray | None:
        images = list(viewer.last_image.values())  # one browser: one client
        return images[-1] if images else None

    try:
        with tempfile.TemporaryDirectory(prefix="facade-view-") as tmp:
            try:
                png = browser_screenshot(browser, url, last_image, Path(tmp))
            except TimeoutError as e:
                print(f"view: no screenshot of {url}: {e}", file=sys.stderr)
                return 1
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(png)
        print(f"view: {out}")
        return 0
    finally:
        viewer.stop()


if __name__ == "__main__":
    raise SystemExit(main())
