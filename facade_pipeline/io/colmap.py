"""COLMAP models through pycolmap: the one adapter between pycolmap's types and ours.

pycolmap 4.x stores rigs and frames beside cameras, images and points; models written by older COLMAP
versions, Metashape or DJI Terra (binary or text) are read the same way.
"""

from __future__ import annotations

import shutil
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.io.atomic import TMP_PREFIX

MODEL_FILES = ("cameras", "images", "points3D")


@dataclass(frozen=True)
class ColmapView:
    """One registered image of a model: its file name (relative to the image folder) and camera; with
    ``radial`` (k1, k2) the image was taken through that lens, and the camera is written as COLMAP's
    OPENCV model with ``camera``'s K, size and pose."""

    name: str
    camera: PinholeCamera
    radial: tuple[float, float] | None = None


def read_reconstruction(model_dir: str | Path) -> pycolmap.Reconstruction:
    """Read a COLMAP model (``.bin`` or ``.txt``) or raise ``InputError`` naming the folder."""
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise InputError(
            model_dir, "a COLMAP model folder (cameras, images, points3D as .bin or .txt)", "no folder"
        )
    present = [
        f for f in MODEL_FILES if (model_dir / f"{f}.bin").is_file() or (model_dir / f"{f}.txt").is_file()
    ]
    missing = [f for f in MODEL_FILES if f not in present]
    if missing:
        raise InputError(
            model_dir,
            "COLMAP files cameras, images, points3D (.bin or .txt)",
            f"missing {', '.join(missing)}",
        )
    check_binary_files(model_dir, walk_all=False)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises ValueError, IndexError, RuntimeError, MemoryError
        check_binary_files(model_dir, walk_all=True)  # a truncated file: say which
        raise InputError(
            model_dir, "a readable COLMAP model", f"a damaged model ({type(e).__name__}: {e})"
        ) from None
    if rec.num_reg_images() == 0:
        raise InputError(model_dir, "a COLMAP model with registered images", "no registered image")
    return rec


# COLMAP's binary records (src/colmap/scene/reconstruction_io_binary.cc): after a uint64 count, cameras
# are (uint32 id, int32 model, uint64 width, uint64 height, double params[n(model)]), images (uint32 id,
# double qvec[4], double tvec[3], uint32 camera id, NUL-terminated name, uint64 n, n x (double x, double y,
# uint64 point id)), points (uint64 id, double xyz[3], uint8 rgb[3], double error, uint64 n,
# n x (uint32 image id, uint32 point index)).
_RECORD_NAMES = {"cameras": "camera", "images": "image", "points3D": "point"}


def check_binary_files(model_dir: Path, walk_all: bool) -> None:
    """Raise ``InputError`` naming a binary model file that is empty or ends inside a record (a copy cut
    short); pycolmap itself reads such files as zeros or fails with a bare ``std::bad_alloc``. cameras.bin
    is always walked (it is tiny, and a truncated one reads as a camera with zero parameters); images.bin
    and points3D.bin are walked when ``walk_all`` (after pycolmap failed on the model)."""
    for name in MODEL_FILES:
        path = model_dir / f"{name}.bin"
        if not path.is_file():
            continue
        size = path.stat().st_size
        if size < 8:
            raise InputError(
                path,
                f"a COLMAP {name}.bin (at least its 8-byte count of {_RECORD_NAMES[name]}s)",
                f"{'an empty file' if size == 0 else f'a file of {size} bytes'}: copy it again from the "
                "photogrammetry export",
            )
        if name == "cameras" or walk_all:
            where = _truncated_record(name, path.read_bytes())
            if where is not None:
                raise InputError(
                    path,
                    f"a complete COLMAP {name}.bin",
                    f"a file that ends after {size} bytes, inside {where} (cut short: copy it again "
                    "from the photogrammetry export)",
                )


def _truncated_record(name: str, data: bytes) -> str | None:
    """Where ``data`` (a whole ``<name>.bin``) ends before its declared records do, in words; None if not
    (or if a record cannot be judged: an unknown camera model, which pycolmap reports itself)."""
    (count,) = struct.unpack_from("<Q", data, 0)
    at, done = 8, 0
    try:
        while done < count:
            if name == "cameras":
                _, model, _, _ = struct.unpack_from("<iiQQ", data, at)
                n_params = _num_params(model)
                if n_params is None:
                    return None
                at += 24 + 8 * n_params
            elif name == "images":
                end = data.index(b"\0", at + 4 + 8 * 7 + 4)
                (n,) = struct.unpack_from("<Q", data, end + 1)
                at = end + 9 + 24 * n
            else:
                (n,) = struct.unpack_from("<Q", data, at + 8 + 24 + 3 + 8)
                at += 8 + 24 + 3 + 8 + 8 + 8 * n
            if at > len(data):
                break
            done += 1
    except (struct.error, ValueError):
        pass
    record = _RECORD_NAMES[name]
    if done == count:
        return None
    if count > len(data):  # not a count at all: the file is damaged from its start
        return f"its first record, after a count of {count} {record}s that no file this size holds"
    return f"{record} {done + 1} of the {count} it declares"


def _num_params(model_id: int) -> int | None:
    try:
        model = pycolmap.CameraModelId(model_id)
        return len(pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params)
    except (ValueError, TypeError):
        return None


def camera_model_name(camera: pycolmap.Camera) -> str:
    return camera.model.name if hasattr(camera.model, "name") else str(camera.model)


def pinhole_camera(camera: pycolmap.Camera, cam_from_world: pycolmap.Rigid3d) -> PinholeCamera:
    """Our camera from a pycolmap camera whose model is SIMPLE_PINHOLE or PINHOLE."""
    name = camera_model_name(camera)
    if name not in ("SIMPLE_PINHOLE", "PINHOLE"):
        raise ValueError(f"camera {camera.camera_id} is {name}; undistort it first")
    T = np.eye(4)
    T[:3, :4] = cam_from_world.matrix()
    return PinholeCamera(camera.calibration_matrix(), T, camera.width, camera.height)


def registered_images(rec: pycolmap.Reconstruction) -> list[pycolmap.Image]:
    """Registered images sorted by name (a stable order for every stage)."""
    return sorted((rec.images[i] for i in rec.reg_image_ids()), key=lambda im: im.name)


def write_pinhole_model(
    model_dir: str | Path,
    views: Sequence[ColmapView],
    points_xyz: np.ndarray | None = None,  # [P, 3]
    points_rgb: np.ndarray | None = None,  # [P, 3] uint8
    binary: bool = True,
) -> None:
    """Write a COLMAP model with one PINHOLE camera (OPENCV for a view with ``radial``) per distinct
    intrinsics, atomically (the folder is built under a temporary name and renamed into place)."""
    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple, int] = {}
    for image_id, view in enumerate(views, start=1):
        c = view.camera
        key = (c.width, c.height, *np.round(c.K[[0, 1, 0, 1], [0, 1, 2, 2]], 9), view.radial)
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            fx, fy, cx, cy = c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]
            rec.add_camera_with_trivial_rig(
                pycolmap.Camera(
                    model="PINHOLE" if view.radial is None else "OPENCV",
                    width=c.width,
                    height=c.height,
                    params=[fx, fy, cx, cy] + ([] if view.radial is None else [*view.radial, 0.0, 0.0]),
                    camera_id=cam_ids[key],
                )
            )
        image = pycolmap.Image(name=view.name, camera_id=cam_ids[key], image_id=image_id)
        T = c.cam_from_world
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3].copy())
        )
    if points_xyz is not None:
        rgb = (
            np.zeros_like(points_xyz, dtype=np.uint8)
            if points_rgb is None
            else np.asarray(points_rgb, np.uint8)
        )
        for xyz, col in zip(np.asarray(points_xyz, dtype=np.float64), rgb, strict=True):
            rec.add_point3D(xyz, pycolmap.Track(), col)
    write_reconstruction(rec, model_dir, binary=binary)


def write_reconstruction(rec: pycolmap.Reconstruction, model_dir: str | Path, binary: bool = True) -> None:
    """Write ``rec`` into ``model_dir`` atomically (replacing any previous model there)."""
    model_dir = Path(model_dir)
    model_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = model_dir.parent / f"{TMP_PREFIX}{model_dir.name}"
    old = model_dir.parent / f"{TMP_PREFIX}old-{model_dir.name}"
    for p in (tmp, old):
        shutil.rmtree(p, ignore_errors=True)
    tmp.mkdir()
    try:
        (rec.write_binary if binary else rec.write_text)(str(tmp))
        if model_dir.exists():
            model_dir.rename(old)
        tmp.rename(model_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)


def check_camera_supported(camera: pycolmap.Camera, model_dir: Path) -> None:
    """Raise ``InputError`` for a camera model that cannot be undistorted to a pinhole camera."""
    if camera.is_spherical() or not (camera.is_perspective() or camera.is_perspective_fisheye()):
        raise InputError(
            model_dir / "cameras",
            "a perspective or fisheye camera model that COLMAP can undistort",
            f"camera {camera.camera_id} with model {camera_model_name(camera)}",
        )
    if camera.has_bogus_params(0.1, 10.0, 2.0):
        raise InputError(
            model_dir / "cameras",
            "plausible camera parameters (focal length, distortion)",
            f"camera {camera.camera_id} ({camera_model_name(camera)}) with params {list(camera.params)}",
        )


def is_pinhole(camera: pycolmap.Camera) -> bool:
    return camera_model_name(camera) in ("SIMPLE_PINHOLE", "PINHOLE")


#: How a distorted photo becomes a pinhole image: COLMAP's own image_undistorter defaults, fixed here so
#: that a pycolmap release cannot change them. No blank border pixels (the image is cropped to pixels that
#: hold the photo, so no view carries black borders into training), and the undistorted image between 0.2
#: and 2 times the original's size (bounds against a degenerate distortion model).
UNDISTORT_BLANK_PIXELS = 0.0
UNDISTORT_MIN_SCALE = 0.2
UNDISTORT_MAX_SCALE = 2.0


def undistort_options() -> pycolmap.UndistortCameraOptions:
    o = pycolmap.UndistortCameraOptions()
    o.blank_pixels = UNDISTORT_BLANK_PIXELS
    o.min_scale, o.max_scale = UNDISTORT_MIN_SCALE, UNDISTORT_MAX_SCALE
    return o


def undistort_camera(options: pycolmap.UndistortCameraOptions, camera: pycolmap.Camera) -> pycolmap.Camera:
    """The pinhole camera that ``undistort_rgb`` maps ``camera``'s images to (identity for pinhole ones)."""
    return camera if is_pinhole(camera) else pycolmap.undistort_camera(options, camera)


def undistort_rgb(
    options: pycolmap.UndistortCameraOptions, rgb: np.ndarray, camera: pycolmap.Camera
) -> np.ndarray:
    """Resample an RGB uint8 image [H, W, 3] of ``camera`` into its undistorted pinhole camera."""
    if is_pinhole(camera):
        return rgb
    bitmap, _ = pycolmap.undistort_image(
        options, pycolmap.Bitmap.from_array(np.ascontiguousarray(rgb)), camera
    )
    return bitmap.to_array()
