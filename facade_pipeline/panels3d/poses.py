"""Each frontal view's pose registered to the 3D panels, and the hand-off that carries it
(``04_regularize/poses.json``, ``RegisteredPoses``).

An imported pose is never exact (photogrammetry, motion capture): corners back-projected with it scatter
around the panels that all the views agree on, by several pixels on a close-range photo, which blurs every
frame bar across the views that train together. ``regularize_corners`` has what a perspective-n-point
solve needs: each view's panel corners (``03_segment``) and the regularised 3D panels. Each true corner
(``grid.true_corners``) of a view's quad is matched to the corner of the panel whose image through the
imported pose is nearest, and the pose is fitted to the matches by a robust least-squares on the
reprojection error (``refine_pose``): Huber loss from the imported pose, matches far off the fit dropped,
a plain least-squares on the rest. A view keeps its imported pose, with the reason, where the corners
cannot tell it better: too few matched corners, corners on one line, a fit no better than the imported
pose, or a move too large for the error of a pose.

Every later stage reads the views' cameras through ``registered_scene``: the frontal views with their
registered poses, and a UAV view that is the same photo as a frontal view (the same imported camera) with
that view's. Frames: local (01_import), metres; pixels with centres at (i + 0.5, j + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.io.atomic import read_json, write_json
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.panels3d.model import PanelSet
from facade_pipeline.scene import ImportedScene

POSES_VERSION = 1

# Constants of the registration, in pixels or relative to what the view shows, so they hold at any scale;
# no building ever needed other values.
#: fewer matched corners than this leave a view's pose as imported: six unknowns, and a corner or two that
#: a bad match puts wrong must not decide them
MIN_CORNERS = 8
#: a quad's true corners match a panel when their mean distance from its projected corners is within this
#: fraction of the panel's projected size (-): the imported pose errs by a few pixels, a pitch is hundreds
MATCH_FRACTION = 0.25
#: the Huber loss turns linear beyond this reprojection error (px): a corner is found to about a pixel
HUBER_PX = 1.0
#: a corner whose reprojection error after the robust fit exceeds this many times the median, and at least
#: ``OUTLIER_FLOOR_PX``, is a bad match or a misplaced corner (-): about 1 in 500 of Gaussian scatter
OUTLIER_FACTOR = 3.0
OUTLIER_FLOOR_PX = 1.0
#: the prior toward the imported pose weighs a change like this fraction of the image motion it causes at
#: one corner (-): corners on a plane seen across a narrow field trade a turn against a move along the
#: plane almost freely, and of the poses that fit them equally the nearest to the imported one is taken
PRIOR_WEIGHT = 0.1
#: the matched corners must span two directions: the smaller singular value of their centred positions at
#: least this fraction of the larger (-); on one line the rotation about it is free
MIN_SPREAD = 0.05
#: a fit that moves the camera by more than this fraction of its distance to the corners, or turns it by
#: more than ``MAX_TURN_DEG``, has met a wrong minimum, not a pose's error (-): an imported pose is off by
#: a degree or a few, and a plane's corners trade some turn against a move along it
MAX_MOVE_FRACTION = 0.1
MAX_TURN_DEG = 10.0


def _stored(x: float) -> float:
    """A per-view figure as the poses file stores it (6 decimals)."""
    return round(float(x), 6)


@dataclass(frozen=True)
class ViewPose:
    """One frontal view's registered pose: ``cam_from_world`` [4, 4] (refined, or as imported with the
    ``reason``), the corners it rests on and the median reprojection error (px) over the matched corners
    with the imported and with the registered pose (NaN without matches)."""

    stem: str
    cam_from_world: np.ndarray
    refined: bool
    reason: str
    corners: int
    inliers: int
    reprojection_imported_px: float
    reprojection_px: float
    rotation_deg: float = 0.0
    translation_m: float = 0.0

    def to_dict(self) -> dict:
        def num(x: float) -> float | None:
            return _stored(x) if np.isfinite(x) else None

        return {
            "stem": self.stem,
            "cam_from_world": np.asarray(self.cam_from_world).tolist(),
            "refined": self.refined,
            "reason": self.reason,
            "corners": self.corners,
            "inliers": self.inliers,
            "reprojection_imported_px": num(self.reprojection_imported_px),
            "reprojection_px": num(self.reprojection_px),
            "rotation_deg": num(self.rotation_deg),
            "translation_m": num(self.translation_m),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ViewPose:
        def num(x) -> float:
            return float("nan") if x is None else float(x)

        return cls(
            str(d["stem"]),
            np.array(d["cam_from_world"], dtype=np.float64).reshape(4, 4),
            bool(d["refined"]),
            str(d["reason"]),
            int(d["corners"]),
            int(d["inliers"]),
            num(d["reprojection_imported_px"]),
            num(d["reprojection_px"]),
            num(d["rotation_deg"]),
            num(d["translation_m"]),
        )


@dataclass(frozen=True)
class RegisteredPoses:
    """The registered pose of every frontal view (``regularize_corners``'s ``04_regularize/poses.json``)."""

    views: tuple[ViewPose, ...]

    def save(self, path: str | Path) -> None:
        write_json(path, {"version": POSES_VERSION, "frame": "local (01_import), metres",
                          "views": [v.to_dict() for v in self.views]})  # fmt: skip

    @classmethod
    def load(cls, path: str | Path) -> RegisteredPoses:
        """Read the poses; a damaged file raises ``InputError`` naming it."""
        views = read_json(path, "registered poses (JSON with views) written by regularize_corners",
                          lambda d: tuple(ViewPose.from_dict(v) for v in d["views"]), POSES_VERSION)
        bad = [v.stem for v in views if not np.isfinite(v.cam_from_world).all()]
        if bad:
            raise InputError(path, "finite cam_from_world for every view", f"not for {bad[:3]}")
        return cls(views)

    def summary(self) -> dict:
        """The manifest's figures: views refined, the others' reasons, and over the views the median of each
        view's median reprojection error (px) with the imported and with the registered poses."""
        kept = {v.stem: v.reason for v in self.views if not v.refined}
        # of the values as the file stores them, so that the summary of poses read back is this one (a
        # median 0.5e-4 from a rounding boundary would otherwise round either way)
        before = [
            _stored(v.reprojection_imported_px) for v in self.views if np.isfinite(v.reprojection_imported_px)
        ]
        after = [_stored(v.reprojection_px) for v in self.views if np.isfinite(v.reprojection_px)]
        return {
            "views_refined": sum(v.refined for v in self.views),
            "views_as_imported": kept,
            "reprojection_median_px_imported": round(float(np.median(before)), 4) if before else None,
            "reprojection_median_px": round(float(np.median(after)), 4) if after else None,
        }


def match_corners(
    quads_px: list[np.ndarray], ok: np.ndarray, panels: PanelSet, camera: PinholeCamera
) -> tuple[np.ndarray, np.ndarray]:
    """The true corners (``ok`` [Q, 4]) of one view's quads (Q arrays [4, 2], px, BL BR TR TL) matched to
    the 3D panels' corners: each quad to the panel whose projection through ``camera`` lies nearest
    (``MATCH_FRACTION``). Returns pixels [M, 2] and world points [M, 3]."""
    if not panels.panels or not len(quads_px):
        return np.zeros((0, 2)), np.zeros((0, 3))
    world = np.stack([p.corners for p in panels.panels])  # [P, 4, 3]
    uv, z = camera.project(world.reshape(-1, 3))
    uv = np.where((z > 0)[:, None], uv, np.nan).reshape(-1, 4, 2)
    size = np.sqrt(np.abs(_area(uv)))  # [P] projected size (px)
    px, pts = [], []
    for q, k in zip(quads_px, ok, strict=True):
        if not k.any():
            continue
        d = np.linalg.norm(uv[:, k] - np.asarray(q, np.float64)[None, k], axis=2).mean(axis=1)  # [P]
        d = np.where(np.isfinite(d), d, np.inf)
        best = int(np.argmin(d))
        if d[best] <= MATCH_FRACTION * size[best]:
            px.append(np.asarray(q, np.float64)[k])
            pts.append(world[best][k])
    if not px:
        return np.zeros((0, 2)), np.zeros((0, 3))
    return np.concatenate(px), np.concatenate(pts)


def _area(uv: np.ndarray) -> np.ndarray:
    """[P] signed area of quadrilaterals [P, 4, 2] (shoelace)."""
    x, y = uv[..., 0], uv[..., 1]
    return 0.5 * (x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y).sum(axis=1)


def _moved(cam_from_world: np.ndarray, params: np.ndarray) -> np.ndarray:
    """``cam_from_world`` [4, 4] followed by a rotation (rotation vector ``params[:3]``, rad) and a
    translation (``params[3:]``, m) in the camera frame."""
    from scipy.spatial.transform import Rotation

    delta = np.eye(4)
    delta[:3, :3] = Rotation.from_rotvec(params[:3]).as_matrix()
    delta[:3, 3] = params[3:]
    return delta @ cam_from_world


def reprojection_px(camera: PinholeCamera, px: np.ndarray, world: np.ndarray) -> np.ndarray:
    """[M] distance (px) between observed pixels [M, 2] and world points [M, 3] projected by ``camera``
    (inf behind it)."""
    uv, z = camera.project(world)
    err = np.linalg.norm(uv - px, axis=1)
    return np.where((z > 0) & np.isfinite(err), err, np.inf)


def _fit(camera: PinholeCamera, px: np.ndarray, world: np.ndarray, loss: str, x0: np.ndarray) -> np.ndarray:
    """The pose correction (6 parameters of ``_moved``) minimising the reprojection error with ``loss``,
    plus a weak prior toward the imported pose (``PRIOR_WEIGHT``)."""
    from scipy.optimize import least_squares

    K, T = camera.K, camera.cam_from_world
    f = float(np.sqrt(K[0, 0] * K[1, 1]))
    reach = float(np.median(np.linalg.norm(world - camera.center, axis=1)))
    # each parameter's change as the image motion (px) it causes: a turn of w rad moves the image f w, a
    # move of t m across the line of sight f t / reach
    scale = PRIOR_WEIGHT * f * np.array([1.0, 1.0, 1.0, 1.0 / reach, 1.0 / reach, 1.0 / reach])

    def residuals(p: np.ndarray) -> np.ndarray:
        M = _moved(T, p)
        pc = world @ M[:3, :3].T + M[:3, 3]
        z = np.maximum(pc[:, 2], 1e-9)  # a point behind the camera costs its distance, not a division by 0
        uv = (pc @ K.T)[:, :2] / z[:, None]
        return np.concatenate([(uv - px).ravel(), scale * p])

    return least_squares(residuals, x0, loss=loss, f_scale=HUBER_PX, x_scale="jac", method="trf").x


def refine_pose(camera: PinholeCamera, px: np.ndarray, world: np.ndarray, stem: str = "") -> ViewPose:
    """``camera``'s pose fitted to its matched corners (pixels [M, 2], world points [M, 3]): a Huber fit
    from the imported pose, the corners beyond ``OUTLIER_FACTOR`` times the median error dropped, a plain
    least-squares fit on the rest. The imported pose is kept, with the reason, where the corners cannot
    tell a better one."""
    T0 = camera.cam_from_world
    before = reprojection_px(camera, px, world)
    med0 = float(np.median(before)) if len(before) else float("nan")

    def kept(reason: str, inliers: int = 0) -> ViewPose:
        return ViewPose(stem, T0, False, reason, len(px), inliers, med0, med0)

    if len(px) < MIN_CORNERS:
        return kept(f"{len(px)} matched panel corners, fewer than {MIN_CORNERS}")
    sv = np.linalg.svd(world - world.mean(axis=0), compute_uv=False)
    if sv[1] < MIN_SPREAD * sv[0]:
        return kept("the matched panel corners lie on one line")
    p = _fit(camera, px, world, "huber", np.zeros(6))
    err = reprojection_px(replace(camera, cam_from_world=_moved(T0, p)), px, world)
    inl = err <= max(OUTLIER_FLOOR_PX, OUTLIER_FACTOR * float(np.median(err)))
    if inl.sum() < MIN_CORNERS:
        n = int(inl.sum())
        return kept(f"{n} corners agree with the fitted pose, fewer than {MIN_CORNERS}", n)
    p = _fit(camera, px[inl], world[inl], "linear", p)
    T = _moved(T0, p)
    new = replace(camera, cam_from_world=T)
    after = reprojection_px(new, px, world)
    turn = float(np.degrees(np.linalg.norm(p[:3])))
    move = float(np.linalg.norm(new.center - camera.center))
    reach = float(np.median(np.linalg.norm(world - camera.center, axis=1)))
    if not float(np.median(after[inl])) < float(np.median(before[inl])):
        return kept("the fitted pose reprojects the corners no better than the imported one", int(inl.sum()))
    if move > MAX_MOVE_FRACTION * reach or turn > MAX_TURN_DEG:
        return kept(
            f"the fit moves the camera {move:.3g} m and turns it {turn:.2f} deg: more than a pose's error "
            f"({MAX_MOVE_FRACTION} of its distance {reach:.3g} m, {MAX_TURN_DEG} deg)",
            int(inl.sum()),
        )
    return ViewPose(stem, T, True, "", len(px), int(inl.sum()), med0, float(np.median(after)), turn, move)


def registered_scene(layout: BuildingLayout) -> ImportedScene:
    """The imported scene with every frontal view at its registered pose (``04_regularize/poses.json``),
    and every UAV view that is the same photo as a frontal view (the same imported camera: K, size and
    pose) at that view's: the one way later stages read the views' cameras."""
    scene = ImportedScene.load(layout)
    registered = {v.stem: v for v in RegisteredPoses.load(layout.path("regularize_poses")).views}
    by_camera = []  # (imported camera, registered pose) of the refined frontal views
    views = []
    for v in scene.views:
        r = registered.get(v.stem) if v.role == "frontal" else None
        if r is not None and r.refined:
            by_camera.append((v.camera, r.cam_from_world))
            v = replace(v, camera=replace(v.camera, cam_from_world=r.cam_from_world))
        views.append(v)
    for i, v in enumerate(views):
        if v.role != "uav":
            continue
        for cam, T in by_camera:
            if _same_camera(v.camera, cam):
                views[i] = replace(v, camera=replace(v.camera, cam_from_world=T))
                break
    return replace(scene, views=tuple(views))


def _same_camera(a: PinholeCamera, b: PinholeCamera) -> bool:
    """Whether two imported cameras are one: the same size, intrinsics and pose (to rounding)."""
    return (a.width, a.height) == (b.width, b.height) and bool(
        np.allclose(a.K, b.K, rtol=1e-9, atol=1e-9) and np.allclose(a.cam_from_world, b.cam_from_world,
                                                                    rtol=1e-9, atol=1e-9)
    )  # fmt: skip


def pose_error(cam_from_world: np.ndarray, true_cam_from_world: np.ndarray) -> tuple[float, float]:
    """The rotation (deg) and the camera centre's distance (m) between a pose [4, 4] and the true one."""
    R = cam_from_world[:3, :3] @ true_cam_from_world[:3, :3].T
    turn = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))

    def centre(T: np.ndarray) -> np.ndarray:
        return -T[:3, :3].T @ T[:3, 3]

    return turn, float(np.linalg.norm(centre(cam_from_world) - centre(true_cam_from_world)))
