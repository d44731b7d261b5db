"""Pinhole cameras in our convention: OpenCV axes (x right, y down, z forward), ``cam_from_world`` 4x4,
``K`` 3x3 in pixels, pixel centres at (i + 0.5, j + 0.5) (COLMAP uses the same pixel convention)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """An undistorted pinhole camera. Arrays are float64."""

    K: np.ndarray  # [3, 3]
    cam_from_world: np.ndarray  # [4, 4]
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        T = np.asarray(self.cam_from_world, dtype=np.float64)
        assert K.shape == (3, 3) and T.shape == (4, 4), (K.shape, T.shape)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "cam_from_world", T)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def world_from_cam(self) -> np.ndarray:  # [4, 4]
        R, t = self.cam_from_world[:3, :3], self.cam_from_world[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def center(self) -> np.ndarray:  # [3] camera centre in world coordinates
        return self.world_from_cam[:3, 3]

    @property
    def forward(self) -> np.ndarray:  # [3] unit optical axis (camera z) in world coordinates
        return self.cam_from_world[2, :3] / np.linalg.norm(self.cam_from_world[2, :3])

    def world_to_cam(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] world points -> [N, 3] camera-frame points."""
        R, t = self.cam_from_world[:3, :3], self.cam_from_world[:3, 3]
        return np.asarray(points, dtype=np.float64) @ R.T + t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project [N, 3] world points (Eq. 6): pixel positions [N, 2] and depths z [N].

        Points with z <= 0 get NaN pixel positions (they are behind the camera)."""
        pc = self.world_to_cam(points)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (pc @ self.K.T)[:, :2] / z[:, None]
        uv[z <= 0] = np.nan
        return uv, z

    def pixel_rays(self, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-space rays through continuous pixel positions (x, y) (pixel centres at +0.5).

        Returns origins [N, 3] and unit directions [N, 3]."""
        pix = np.stack([np.ravel(xs), np.ravel(ys), np.ones(np.size(xs))], axis=1)
        d_cam = pix @ np.linalg.inv(self.K).T
        W = self.world_from_cam
        d = d_cam @ W[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(W[:3, 3], d.shape).copy()
        return o, d

    def all_pixel_rays(self, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Rays through every pixel on an ``supersample`` x ``supersample`` grid of sub-pixel positions,
        ordered row-major over (y, x, sub_y, sub_x): reshape to [H, W, s*s] to average."""
        s = int(supersample)
        offs = (np.arange(s) + 0.5) / s
        ys = np.arange(self.height)[:, None, None, None] + offs[None, None, :, None]
        xs = np.arange(self.width)[None, :, None, None] + offs[None, None, None, :]
        ys, xs = np.broadcast_arrays(ys, xs)
        return self.pixel_rays(xs, ys)

    def to_dict(self) -> dict:
        return {
            "K": self.K.tolist(),
            "cam_from_world": self.cam_from_world.tolist(),
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PinholeCamera:
        return cls(np.array(d["K"]), np.array(d["cam_from_world"]), d["width"], d["height"])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``cam_from_world`` [4, 4] of a camera at ``eye`` looking at ``target`` with image-up along ``up``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: any horizontal x will do
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:  # [3, 3]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
