"""Fly-through videos of a trained facade: reflections only show when the camera moves.

The default path is an orbit in front of the facade: it looks at the point the training cameras look at
(the point nearest to all their optical axes) and sweeps their range of azimuths there and back, while its
height and distance move through the training cameras' ranges, so every frame is seen from where the model
was trained to be seen. The other path flies through named views in order: a Catmull-Rom spline through
their centres and a rotation spline through their orientations, each view reached exactly at one frame.
The specular term is limited to the facade, as in training: each frame's facade
mask is cast from the corrected mesh. Frames are written as MP4 (H.264 through imageio-ffmpeg's bundled
ffmpeg) and as a short looping animated WebP (Pillow) that the report shows inline.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from facade_pipeline.config import Count, PosInt, Positive
from facade_pipeline.errors import ConfigError
from facade_pipeline.geometry.camera import PinholeCamera, look_at
from facade_pipeline.io.atomic import atomic_path

PATH_KEY = "evaluate.video.path"
#: the report's looping clip: this many frames taken evenly from the video, at most this wide (px), so that
#: the clip the report embeds stays small whatever the video's length and size (the MP4 has every frame)
CLIP_FRAMES = 24
CLIP_WIDTH_PX = 480


@dataclass(frozen=True)
class VideoParams:
    """``[evaluate.video]``: the fly-through of each trained model."""

    frames: Count
    """frames of the video (0: no video); a path through views needs at least one frame per view"""
    fps: PosInt
    """frames per second of the MP4"""
    scale: Positive
    """frame size as a multiple of the training views' size (-)"""
    path: Literal["orbit"] | tuple[str, ...] = "orbit"
    """"orbit", or the stems of two or more views that the camera flies through in order"""

    def __post_init__(self) -> None:
        if self.path == "orbit":
            return
        if len(self.path) < 2:
            raise ConfigError(None, f"'{PATH_KEY}' \"orbit\" or the stems of at least two views",
                              f"{list(self.path)}")  # fmt: skip
        if 0 < self.frames < len(self.path):
            raise ConfigError(None, f"'evaluate.video.frames' 0 or at least one frame per view of "
                              f"'{PATH_KEY}' ({len(self.path)})", str(self.frames))  # fmt: skip


def look_target(cameras: Sequence[PinholeCamera]) -> np.ndarray:
    """The point nearest (least squares) to the optical axes of ``cameras``; where the axes are nearly
    parallel, the point at their median distance along the mean axis."""
    centres = np.array([c.center for c in cameras])
    axes = np.array([c.forward for c in cameras])
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, f in zip(centres, axes, strict=True):
        P = np.eye(3) - np.outer(f, f)
        A += P
        b += P @ c
    if np.linalg.cond(A) < 1e6:
        return np.linalg.solve(A, b)
    mean_axis = axes.mean(axis=0) / np.linalg.norm(axes.mean(axis=0))
    reach = np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1)) + 1.0
    return centres.mean(axis=0) + reach * mean_axis


def orbit_path(cameras: Sequence[PinholeCamera], n: int, scale: float = 1.0) -> list[PinholeCamera]:
    """``n`` cameras on a closed orbit in front of the facade through the range of ``cameras`` (z up):
    azimuth there and back over their azimuth range, height and distance through theirs; the intrinsics
    of the first camera, scaled by ``scale`` (even sizes, as video codecs need)."""
    target = look_target(cameras)
    rel = np.array([c.center for c in cameras]) - target
    az = np.arctan2(rel[:, 1], rel[:, 0])
    az0 = np.arctan2(np.sin(az).mean(), np.cos(az).mean())
    daz = np.angle(np.exp(1j * (az - az0)))  # wrapped about the mean direction
    dist = np.hypot(rel[:, 0], rel[:, 1])
    K, w, h = _video_intrinsics(cameras[0], scale)
    out = []
    for i in range(n):
        t = 2 * np.pi * i / max(n, 1)
        s = 0.5 - 0.5 * np.cos(t)  # 0 -> 1 -> 0: there and back, smooth at the turns
        q = 0.5 - 0.5 * np.cos(t + np.pi / 2)
        a = az0 + daz.min() + (daz.max() - daz.min()) * s
        r = dist.min() + (dist.max() - dist.min()) * q
        z = rel[:, 2].min() + np.ptp(rel[:, 2]) * (1 - q)
        eye = target + np.array([r * np.cos(a), r * np.sin(a), z])
        out.append(PinholeCamera(K, look_at(eye, target), w, h))
    return out


def _video_intrinsics(first: PinholeCamera, scale: float) -> tuple[np.ndarray, int, int]:
    """(K, width, height) of ``first`` scaled by ``scale``, at even sizes as video codecs need."""
    w, h = (max(2, 2 * round(first.width * scale / 2)), max(2, 2 * round(first.height * scale / 2)))
    K = first.K.copy()
    K[0] *= w / first.width
    K[1] *= h / first.height
    return K, w, h


def video_path(params: VideoParams, views: Sequence[tuple[str, PinholeCamera]]) -> list[PinholeCamera]:
    """The cameras of the video's frames: ``params.frames`` of the orbit, or of the path through the views
    ``params.path`` names (``views``: (stem, camera) of the building's views). A name that is not a view
    is a ``ConfigError`` naming the key and the views there are."""
    if params.frames == 0:
        return []
    if params.path == "orbit":
        return orbit_path([c for _, c in views], params.frames, params.scale)
    by_stem = dict(views)
    unknown = [s for s in params.path if s not in by_stem]
    if unknown:
        stems = sorted(by_stem)
        known = ", ".join(stems) if len(stems) <= 24 else f"{', '.join(stems[:12])}, ... {len(stems)} in all"
        raise ConfigError(None, f"'{PATH_KEY}' \"orbit\" or stems of this building's views ({known})",
                          f"unknown view {unknown[0]!r}")  # fmt: skip
    return views_path([by_stem[s] for s in params.path], params.frames, params.scale)


def views_path(keys: Sequence[PinholeCamera], n: int, scale: float = 1.0) -> list[PinholeCamera]:
    """``n`` cameras flying through the poses of ``keys`` in order (two or more, ``n`` at least as many):
    centres on a Catmull-Rom spline, orientations on a rotation spline (scipy's ``RotationSpline``), both
    over one time whose steps follow the distance between the views, so the speed is about even and
    smooth through them; key ``k`` is met exactly at frame ``key_frames(...)[k]``. The intrinsics are the
    first key's, scaled by ``scale``."""
    from scipy.spatial.transform import Rotation, RotationSpline

    assert len(keys) >= 2 and n >= len(keys), (len(keys), n)
    K, w, h = _video_intrinsics(keys[0], scale)
    centres = np.array([c.center for c in keys])  # [V, 3]
    rotations = Rotation.from_matrix(np.array([c.cam_from_world[:3, :3].T for c in keys]))  # world_from_cam
    knots = np.concatenate([[0.0], np.cumsum(_segment_lengths(centres, rotations))])
    at = key_frames(knots, n)
    t = np.interp(np.arange(n), at, knots)
    centre_at = catmull_rom(centres, knots, t)
    world_from_cam = RotationSpline(knots, rotations)(t).as_matrix()
    out = []
    for R, c in zip(world_from_cam, centre_at, strict=True):
        T = np.eye(4)
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ c
        out.append(PinholeCamera(K, T, w, h))
    return out


def _segment_lengths(centres: np.ndarray, rotations) -> np.ndarray:
    """[V - 1] length of each step between views (m): the distance between their centres plus their turn,
    a full turn weighing as much as crossing the views' spread, so that a turn on the spot takes time too;
    never 0 (the same view twice in a row: the camera holds still for a frame)."""
    dist = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    turn = (rotations[:-1].inv() * rotations[1:]).magnitude()  # rad
    spread = max(float(np.linalg.norm(np.ptp(centres, axis=0))), 1e-6)
    return np.maximum(dist + spread * turn / (2 * np.pi), 1e-9 * spread)


def key_frames(knots: np.ndarray, n: int) -> np.ndarray:
    """[V] int: the frame of each view, in proportion to ``knots`` (the path's time at each view,
    increasing), the first at 0 and the last at ``n - 1``, at least one frame apart."""
    at = np.floor((knots - knots[0]) / (knots[-1] - knots[0]) * (n - 1) + 0.5).astype(int)
    for k in range(1, len(at)):
        at[k] = max(at[k], at[k - 1] + 1)
    at[-1] = n - 1
    for k in range(len(at) - 2, -1, -1):
        at[k] = min(at[k], at[k + 1] - 1)
    return at


def catmull_rom(points: np.ndarray, knots: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[T, D]: the Catmull-Rom spline through ``points`` [V, D] at times ``knots`` [V] (increasing),
    evaluated at ``t`` [T] (Barry and Goldman's recursive form, which takes any knots); the ends are
    continued by reflecting the second point about the first (and the last but one about the last)."""
    P = np.concatenate([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
    u = np.concatenate([[2 * knots[0] - knots[1]], knots, [2 * knots[-1] - knots[-2]]])
    out = np.empty((len(t), points.shape[1]))
    for i, ti in enumerate(np.asarray(t, float)):
        k = int(np.clip(np.searchsorted(knots, ti, side="right") - 1, 0, len(knots) - 2)) + 1
        p0, p1, p2, p3 = P[k - 1 : k + 3]
        t0, t1, t2, t3 = u[k - 1 : k + 3]
        a1 = ((t1 - ti) * p0 + (ti - t0) * p1) / (t1 - t0)
        a2 = ((t2 - ti) * p1 + (ti - t1) * p2) / (t2 - t1)
        a3 = ((t3 - ti) * p2 + (ti - t2) * p3) / (t3 - t2)
        b1 = ((t2 - ti) * a1 + (ti - t0) * a2) / (t2 - t0)
        b2 = ((t3 - ti) * a2 + (ti - t1) * a3) / (t3 - t1)
        out[i] = ((t2 - ti) * b1 + (ti - t1) * b2) / (t2 - t1)
    return out


def render_path(
    path: Sequence[PinholeCamera],
    render: Callable[[PinholeCamera, np.ndarray], np.ndarray],
    facade_mask: Callable[[PinholeCamera], np.ndarray],
    progress: Callable[[int], None] | None = None,
) -> list[np.ndarray]:
    """uint8 frames [H, W, 3]: ``render(camera, facade_mask)`` -> RGB in [0, 1] for each camera."""
    frames = []
    for cam in path:
        frames.append(to_frame(render(cam, facade_mask(cam))))
        if progress is not None:
            progress(1)
    return frames


def to_frame(rgb: np.ndarray) -> np.ndarray:
    """A video frame, uint8 [H, W, 3], of a render's colour [H, W, 3] in [0, 1]."""
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def merge_films(per_variant: Sequence[Sequence[np.ndarray]], gap_px: int = 4) -> list[np.ndarray]:
    """One frame per time step with the variants' frames left to right (even width kept)."""
    out = []
    for frames in zip(*per_variant, strict=True):
        h = frames[0].shape[0]
        gap = np.zeros((h, gap_px, 3), np.uint8)
        row = np.concatenate([x for f in frames for x in (f, gap)][:-1], axis=1)
        if row.shape[1] % 2:
            row = np.concatenate([row, np.zeros((h, 1, 3), np.uint8)], axis=1)
        out.append(row)
    return out


def write_mp4(path: str | Path, frames: Sequence[np.ndarray], fps: int) -> None:
    """H.264 MP4 (yuv420p, playable in browsers), written atomically."""
    import imageio_ffmpeg

    h, w = frames[0].shape[:2]
    with atomic_path(path) as tmp:
        writer = imageio_ffmpeg.write_frames(
            str(tmp), (w, h), fps=fps, codec="libx264", pix_fmt_out="yuv420p", macro_block_size=1,
            output_params=["-crf", "20"], ffmpeg_log_level="error",
        )  # fmt: skip
        writer.send(None)
        for f in frames:
            writer.send(np.ascontiguousarray(f))
        writer.close()


def read_mp4(path: str | Path) -> list[np.ndarray]:
    """The frames of an MP4 as uint8 [H, W, 3] (for checks)."""
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    w, h = meta["size"]
    return [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in reader]


def write_clip(path: str | Path, frames: Sequence[np.ndarray], n: int, width_px: int, fps: int) -> None:
    """A looping animated WebP of ``n`` frames taken evenly from ``frames``, at most ``width_px`` wide."""
    from PIL import Image

    pick = np.linspace(0, len(frames), num=min(n, len(frames)), endpoint=False).astype(int)
    h, w = frames[0].shape[:2]
    size = (w, h) if w <= width_px else (width_px, max(1, round(h * width_px / w)))
    images = [Image.fromarray(frames[i]).resize(size, Image.Resampling.LANCZOS) for i in pick]
    step_ms = round(1000 * len(frames) / (fps * len(pick)))
    with atomic_path(path) as tmp:
        images[0].save(tmp, format="WEBP", save_all=True, append_images=images[1:], duration=step_ms, loop=0,
                       quality=80)  # fmt: skip
