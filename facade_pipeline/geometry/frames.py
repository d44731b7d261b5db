"""The local world frame: z up, near the origin.

Photogrammetry exports come in two kinds: georeferenced (UTM easting/northing/height, 10^5 to 10^6 m,
z up) and arbitrary (COLMAP without geo-registration: any rotation, any scale). float32, which rendering
and training use, has a step of 6 cm at 10^6 m, so every model is moved to a local frame at import and
the transform back (``georef_from_local``, float64) is recorded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

AXES: dict[str, tuple[float, float, float]] = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
}


@dataclass(frozen=True)
class UpEstimate:
    up: np.ndarray  # [3] unit vector in the model frame
    method: str  # how it was found, for the manifest


def estimate_up_from_cameras(cam_from_world_R: np.ndarray, snap_deg: float) -> UpEstimate:  # [C, 3, 3]
    """World up from camera orientations, for models that are not georeferenced.

    UAV cameras fly with nearly zero roll, so each camera's x axis is nearly horizontal: up is the direction
    most orthogonal to all x axes (smallest eigenvector of sum x x^T). When all cameras share one heading
    that direction is ambiguous within a plane; there the mean camera up (-y axis) picks it. The sign follows
    the mean camera up. Within ``snap_deg`` of a model axis the estimate is snapped to that axis.
    """
    R = np.asarray(cam_from_world_R, dtype=np.float64)
    x_axes = R[:, 0, :]
    mean_up = -R[:, 1, :].mean(axis=0)
    evals, evecs = np.linalg.eigh(x_axes.T @ x_axes / len(R))
    if evals[1] - evals[0] > 0.05:
        up, method = evecs[:, 0], "camera x axes"
    else:
        plane = evecs[:, :2]
        up, method = plane @ (plane.T @ mean_up), "camera x axes and mean camera up"
    norm = np.linalg.norm(up)
    if norm < 1e-9:
        up, method = mean_up, "mean camera up"
        norm = np.linalg.norm(up)
    up = up / norm
    if up @ mean_up < 0:
        up = -up
    for name, axis in AXES.items():
        if np.degrees(np.arccos(np.clip(up @ np.array(axis), -1.0, 1.0))) <= snap_deg:
            return UpEstimate(np.array(axis), f"{method}, snapped to {name}")
    return UpEstimate(up, method)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # [3, 3]
    """The smallest rotation taking unit vector ``a`` to unit vector ``b`` (Rodrigues)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1.0 + 1e-12:  # opposite: turn half way about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def local_from_model(up: np.ndarray, centre: np.ndarray, recenter: bool, rounding_m: float) -> np.ndarray:
    """The rigid transform [4, 4] into the local frame: rotate ``up`` to +z, then (if ``recenter``) move
    ``centre`` (model frame) to the origin, rounded to a multiple of ``rounding_m``."""
    R = rotation_between(up, [0.0, 0.0, 1.0])
    T = np.eye(4)
    T[:3, :3] = R
    if recenter:
        c = R @ np.asarray(centre, dtype=np.float64)
        if rounding_m > 0:
            c = np.round(c / rounding_m) * rounding_m
        T[:3, 3] = -c
    return T


def invert_rigid(T: np.ndarray) -> np.ndarray:  # [4, 4]
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a [4, 4] transform to [N, 3] points in float64."""
    p = np.asarray(points, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]
