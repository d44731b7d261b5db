"""Camera planning: UAV-like views around the facade, close-range frontal views covering every panel, and
the pose noise of the raw COLMAP models. Cameras are OpenCV pinholes (``PinholeCamera``), square pixels,
principal point at the image centre."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from facade_pipeline.errors import ConfigError
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.synthetic.facade import PartGeometry, world_from_facade
from facade_pipeline.synthetic.mesh import Material
from facade_pipeline.synthetic.noise import rng_for
from facade_pipeline.synthetic.params import CameraParams, SynthesizeParams

TARGET_INSET = 0.1  # UAV targets avoid this fraction of the part's width and height at each side (-)


def view_stem(kind: str, index: int) -> str:
    """File stem of a view: ``uav_0003``, ``frontal_0000``."""
    return f"{kind}_{index:04d}"


@dataclass(frozen=True, eq=False)
class View:
    """A view to render: ``kind`` "uav" or "frontal", file ``name`` (e.g. ``uav_0003.png``), its ``stem``,
    the true camera, and for frontal views the (part, rows, cols) block it covers. With a ``lens``, the
    raw image is taken through it and ``camera`` is the pinhole its undistorted image has (the truth)."""

    kind: str
    index: int
    camera: PinholeCamera
    block: tuple[int, tuple[int, ...], tuple[int, ...]] | None = None
    lens: Lens | None = None

    @property
    def stem(self) -> str:
        return view_stem(self.kind, self.index)

    @property
    def name(self) -> str:
        return self.stem + ".png"


@dataclass(frozen=True, eq=False)
class Lens:
    """A camera with radial distortion: ``camera`` holds K, size and pose of the distorted image, and
    (k1, k2) of OpenCV's model (COLMAP's OPENCV camera with no tangential terms)."""

    camera: PinholeCamera
    k1_k2: tuple[float, float]

    def colmap_camera(self):
        import pycolmap

        K = self.camera.K
        return pycolmap.Camera(model="OPENCV", width=self.camera.width, height=self.camera.height,
                               params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2], *self.k1_k2, 0.0, 0.0])

    def pixel_rays(self, supersample: int) -> tuple[np.ndarray, np.ndarray]:
        """Rays [N, 3] + [N, 3] through the distorted image's pixels, in ``PinholeCamera.all_pixel_rays``'
        order: each sub-pixel position undistorted by COLMAP's own inverse of the model."""
        cam = self.camera
        s = int(supersample)
        offs = (np.arange(s) + 0.5) / s
        ys = np.arange(cam.height)[:, None, None, None] + offs[None, None, :, None]
        xs = np.arange(cam.width)[None, :, None, None] + offs[None, None, None, :]
        ys, xs = np.broadcast_arrays(ys, xs)
        xy = self.colmap_camera().cam_from_img(np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64))
        d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        W = cam.world_from_cam
        d = d_cam @ W[:3, :3].T
        return np.broadcast_to(W[:3, 3], d.shape).copy(), d / np.linalg.norm(d, axis=1, keepdims=True)


def with_lens(view: View, k1_k2: tuple[float, float]) -> View:
    """``view`` taken through a radial lens: its camera becomes the pinhole that the importer undistorts
    its image to (COLMAP's ``undistort_camera`` with the importer's options), the truth's camera."""
    from facade_pipeline.io.colmap import undistort_camera, undistort_options

    lens = Lens(view.camera, (float(k1_k2[0]), float(k1_k2[1])))
    u = undistort_camera(undistort_options(), lens.colmap_camera())
    pin = PinholeCamera(u.calibration_matrix(), view.camera.cam_from_world, u.width, u.height)
    return View(view.kind, view.index, pin, view.block, lens)


def camera_matrix(width: int, height: int, fov_deg: float) -> np.ndarray:
    """K [3, 3] for a horizontal field of view ``fov_deg`` and the principal point at the image centre."""
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return intrinsics(f, f, width / 2, height / 2)


def frontal_views(parts: tuple[PartGeometry, ...], cams: CameraParams) -> list[View]:
    """Frontal views at ``frontal_distance_m`` along the local normal of the centre of blocks of panels,
    the blocks as large as fit in the image with ``frontal_margin_px`` to spare. Analytic: no ray is cast.
    Raises ConfigError if a panel of its block does not fit in a view."""
    width, height = cams.frontal_size_px
    K = camera_matrix(width, height, cams.frontal_fov_deg)
    D, f = cams.frontal_distance_m, K[0, 0]
    views: list[View] = []
    for g in parts:
        p = g.part
        pitch_s, pitch_z = (p.width_m - g.frame_width_m) / p.cols, (p.height_m - g.frame_width_m) / p.rows
        usable_w = (width - 2 * cams.frontal_margin_px) * D / f - g.frame_width_m
        usable_h = (height - 2 * cams.frontal_margin_px) * D / f - g.frame_width_m
        kc, kr = max(1, int(usable_w // pitch_s)), max(1, int(usable_h // pitch_z))
        for rows in np.array_split(np.arange(p.rows), math.ceil(p.rows / kr)):
            for cols in np.array_split(np.arange(p.cols), math.ceil(p.cols / kc)):
                s = 0.5 * (g.panel_bounds(0, cols[0])[0] + g.panel_bounds(0, cols[-1])[1])
                z = 0.5 * (g.panel_bounds(rows[0], 0)[2] + g.panel_bounds(rows[-1], 0)[3])
                target = g.surface(np.array(s), np.array(z), np.array(0.0))
                direction = oblique_direction(g.normal(np.array(s)), len(views), cams.frontal_oblique_deg,
                                              target, D, cams.uav_min_height_m)
                cam = PinholeCamera(K, look_at(target + D * direction, target), width, height)
                if cams.frontal_oblique_deg == (0.0, 0.0):  # oblique views may cut their block's panels
                    _check_block(g, cam, rows, cols, cams.frontal_margin_px, len(views))
                views.append(
                    View("frontal", len(views), cam, (g.index, tuple(map(int, rows)), tuple(map(int, cols))))
                )
    return views


def planned_frontal_views(params: SynthesizeParams) -> list[View]:
    """The frontal views of ``params`` without building the scene (cheap: for a stage's targets)."""
    parts = tuple(
        PartGeometry(i, p, world_from_facade(p), params.facade.frame_width_m)
        for i, p in enumerate(params.parts)
    )
    return frontal_views(parts, params.cameras)


def oblique_direction(normal: np.ndarray, k: int, max_deg: tuple[float, float], target: np.ndarray,
                      distance: float, min_height_m: float) -> np.ndarray:
    """Unit direction [3] from the target to frontal view ``k``'s eye: the facade's ``normal`` turned by
    yaw and pitch, fractions in [-1, 1] of ``max_deg`` from the additive recurrences of the plastic number
    (well spread for any number of views); a pitch that would put the eye below ``min_height_m`` is
    mirrored."""
    fy, fp = (2.0 * ((k + 1) * a % 1.0) - 1.0 for a in (0.7548776662, 0.5698402910))
    yaw, pitch = np.radians(max_deg[0] * fy), np.radians(max_deg[1] * fp)
    up = np.array([0.0, 0.0, 1.0])
    n = np.asarray(normal, float)
    side = np.cross(up, n)
    side /= np.linalg.norm(side)
    d = np.cos(yaw) * n + np.sin(yaw) * side
    out = np.cos(pitch) * d + np.sin(pitch) * up
    if target[2] + distance * out[2] < min_height_m:
        out = np.cos(pitch) * d - np.sin(pitch) * up
    return out / np.linalg.norm(out)


def _check_block(g: PartGeometry, cam: PinholeCamera, rows, cols, margin: float, index: int) -> None:
    corners = np.array(
        [
            [g.panel_bounds(r, c)[i], g.panel_bounds(r, c)[j]]
            for r in rows
            for c in cols
            for i, j in ((0, 2), (1, 2), (1, 3), (0, 3))
        ]
    )
    uv, z = cam.project(g.surface(corners[:, 0], corners[:, 1], np.zeros(len(corners))))
    lo, hi = margin - 1e-6, np.array([cam.width, cam.height]) - margin + 1e-6
    if not (np.all(z > 0) and np.all(uv >= lo) and np.all(uv <= hi)):
        raise ConfigError(
            None,
            f"'synthesize.cameras.frontal_distance_m' large enough for frontal view {index} "
            f"to hold its panels (part {g.part.name}, rows {list(rows)}, cols {list(cols)})",
            f"corners outside the image at {cam.height}x{cam.width} px",
        )


def uav_views(
    parts: tuple[PartGeometry, ...],
    cams: CameraParams,
    seed: int,
    visible: Callable[[np.ndarray, np.ndarray], bool],
) -> list[View]:
    """``uav_count`` views spread over the parts (round robin). View k of a part has an azimuth from the
    local normal stratified over +-``uav_azimuth_deg`` (the extremes are near grazing), a random elevation
    and distance, and looks at a random point of the part. ``visible(eye, target) -> bool`` rejects views
    whose target is hidden (or whose eye is inside an object); each view gets ``uav_max_tries`` draws."""
    K = camera_matrix(cams.width_px, cams.height_px, cams.fov_deg)
    views = []
    per_part = [len(range(i, cams.uav_count, len(parts))) for i in range(len(parts))]
    for i in range(cams.uav_count):
        g, k = parts[i % len(parts)], i // len(parts)
        rng = rng_for(seed, "uav_camera", i)
        for _ in range(cams.uav_max_tries):
            eye, target = _draw_uav(g, cams, rng, (k + rng.uniform()) / per_part[g.index])
            if visible(eye, target):
                break
        else:
            raise ConfigError(
                None,
                f"'synthesize.cameras' to allow an unoccluded UAV view {i} within {cams.uav_max_tries} tries",
                "every draw occluded or inside an object",
            )
        views.append(View("uav", i, PinholeCamera(K, look_at(eye, target), cams.width_px, cams.height_px)))
    return views


def _draw_uav(g: PartGeometry, cams: CameraParams, rng: np.random.Generator, stratum: float):
    p = g.part
    s = rng.uniform(-0.5 + TARGET_INSET, 0.5 - TARGET_INSET) * p.width_m
    z = rng.uniform(TARGET_INSET, 1.0 - TARGET_INSET) * p.height_m
    target = g.surface(np.array(s), np.array(z), np.array(0.0))
    az = math.radians(cams.uav_azimuth_deg) * (2.0 * stratum - 1.0)
    el = math.radians(rng.uniform(*cams.uav_elevation_deg))
    dist = rng.uniform(*cams.uav_distance_m)
    direction = math.cos(el) * (math.cos(az) * g.normal(np.array(s)) + math.sin(az) * g.tangent(np.array(s)))
    eye = target + dist * (direction + np.array([0.0, 0.0, math.sin(el)]))
    eye[2] = max(eye[2], cams.uav_min_height_m)
    return eye, target


def facade_visible(tracer, arrays):
    """A ``visible(eye, target)`` test for ``uav_views``: the ray from the eye first hits the facade (glass
    or frame) within 1 % of the eye-target distance of the target."""

    def visible(eye: np.ndarray, target: np.ndarray) -> bool:
        d = target - eye
        dist = float(np.linalg.norm(d))
        t, prim = tracer.cast(eye[None], (d / dist)[None], "other")
        if prim[0] < 0:
            return False
        return arrays.material[prim[0]] in (Material.GLASS, Material.FRAME) and abs(t[0] - dist) < 0.01 * dist

    return visible


def check_frontal_views(views: list[View], panels, tracer, arrays) -> None:
    """Raise ConfigError if the centre of a panel of a frontal view's block is hidden from that view (a tree
    or the fountain between the camera and the facade)."""
    for view in (v for v in views if v.kind == "frontal"):
        part, rows, cols = view.block
        ids = [i for i, pn in enumerate(panels)
               if pn.part == part and pn.row in rows and pn.col in cols and pn.glazed]
        if not ids:  # a block of units without glass: nothing to hide
            continue
        centres = np.array([panels[i].corners.mean(axis=0) for i in ids])
        d = centres - view.camera.center
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        _, prim = tracer.cast(np.broadcast_to(view.camera.center, d.shape), d, "other")
        seen = np.where(prim >= 0, arrays.object_id[np.maximum(prim, 0)], -1)
        if not np.array_equal(seen, ids):
            raise ConfigError(
                None,
                f"frontal view {view.index} to see its panels: 'synthesize.environment' objects "
                "farther than 'synthesize.cameras.frontal_distance_m'",
                f"panels {[i for i, j in zip(ids, seen, strict=True) if i != j]} hidden",
            )


def perturb_pose(
    camera: PinholeCamera, rng: np.random.Generator, rotation_deg: float, translation_m: float
) -> PinholeCamera:
    """The camera with its orientation rotated by an angle ~ N(0, rotation_deg) about a random axis and its
    centre moved by N(0, translation_m) per world axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = math.radians(rng.normal(0.0, rotation_deg))
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    dR = np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx  # Rodrigues
    W = camera.world_from_cam.copy()
    W[:3, :3] = dR @ W[:3, :3]
    W[:3, 3] += rng.normal(0.0, translation_m, size=3)
    return PinholeCamera(camera.K, np.linalg.inv(W), camera.width, camera.height)
