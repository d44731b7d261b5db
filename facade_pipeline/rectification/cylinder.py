"""Robust fit of a cylindrical (or planar) facade surface to a cropped coarse point cloud (paper, 3.1.1).

The surface is kept in a form that stays finite as the radius goes to infinity: a tangent point ``p0``, an
orthonormal frame ``(a, b, n)`` (``a`` the cylinder axis, ``n`` the outward normal at ``p0``, ``b = n x a``)
and a signed curvature ``kappa = 1 / R`` (1/m; > 0: convex toward ``n``, the axis lies at ``p0 - n / kappa``;
0: a plane). For a point ``x`` with ``t = (x - p0) . b`` and ``w = (x - p0) . n`` the signed distance to the
surface (positive on the ``n`` side) is

    d(x) = (kappa (w^2 + t^2) + 2 w) / (sqrt((kappa w + 1)^2 + (kappa t)^2) + 1),

which equals ``sqrt((w + 1/kappa)^2 + t^2) - 1/kappa`` for kappa != 0 and ``w`` for kappa = 0 (no division by
kappa anywhere). All coordinates are world metres.

Fit (``fit_surface``): (0) given a frontal view's viewing direction, keep the points whose local surface
faces it (the level ground before the facade drops out); (1) reject points on a line or too few points;
(2) RANSAC plane with a generous threshold to drop far outliers (ghost points mirrored behind glass,
ground, clutter); (3) a quadric height field ``w = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2`` over the
plane, by iteratively reweighted least squares, whose Hessian gives the axis (the flat eigenvector) and
kappa (minus the other eigenvalue); (4) least squares on ``d(x)`` over (frame rotation, offset along n,
kappa) with a soft-L1 loss; (5) when the fit's inliers lie on two or more separate parts of the points
(``point_parts``), the view frames two surfaces side by side (a curved part's end beside a planar part):
one surface bent through both fits neither, and the fit is redone on the part holding most inliers, unless
the fit over all fits that part about as well as its own (one surface with a gap); (6) a plane and a
cylinder meeting with no gap between them (a flat wall continued by a curved corner, tangentially or at a
kink), or two planes meeting at a kink (a building's corner, a folded bay), are one part: the points are
split where two surfaces fit them best (``turn_split``), and the fit is redone on the side the view's
optical axis meets (the side holding most where no axis is given) where the fit over all strays from the
other side (``_turn_fit``); a fit of planes only, too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from facade_pipeline.errors import PipelineError
from facade_pipeline.rectification.params import SurfaceFitParams


class SurfaceFitError(PipelineError):
    """The points cannot define a surface (too few, or all on one line)."""

#: RANSAC plane hypotheses of the robust fit, drawn by a generator seeded with RANSAC_SEED so that a view's
#: fit is the same on every run. With a third of the points on the facade (the rest ground, ghosts and
#: clutter), 300 draws of 3 all miss an all-inlier sample with a probability of (1 - 1/27)^300, about 1e-5.
RANSAC_ITERATIONS = 300
RANSAC_SEED = 0
#: a cylinder bulging (its sagitta, |kappa| width^2 / 8) less than this many times the fit's RMS residual
#: over the view's points is not told from a plane by them: a plane is fitted instead (-).
MIN_SAGITTA_RMS = 3.0
#: a fit over separate parts of the points stands (one surface with a gap: a pilaster, a strip the mesh
#: hides) where its RMS residual over the main part's inliers is within this factor of the main part's own
#: fit's; a surface bent through two (a curved part's end beside a planar part) fits the main part worse:
#: 1.00 on a drawn plane or cylinder with a gap, 1.4-8 on drawn surfaces side by side, 1.9 on oblique's
#: frontal_0000. The same factor tells a plane and a cylinder meeting with no gap (``_turn_fit``: the fit
#: over both against the other side's inliers, over the worse side's own fit): 1.6-5 on drawn ones, and
#: two planes at a kink of 10-40 degrees: 1.4-8 bent through both as a cylinder, 4.6-9 as a plane (-)
MAX_PART_RMS_RATIO = 1.2


def implausible(fit: SurfaceFit, footprint_m: float, params: SurfaceFitParams,
                up: np.ndarray = (0.0, 0.0, 1.0)) -> str | None:
    """Why ``fit`` cannot be the facade a view frames, or None when it can: tilted from upright, tighter
    than the view's footprint allows (``footprint_m``: the width the view frames at the surface's depth),
    or too loose a fit for it."""
    s, up = fit.surface, np.asarray(up, float)
    if np.isfinite(s.radius_m):
        tilt = np.degrees(np.arccos(min(1.0, abs(float(s.axis @ up)))))
        what = "cylinder axis"
    else:
        tilt = np.degrees(np.arcsin(min(1.0, abs(float(s.normal @ up)))))
        what = "plane normal"
    if tilt > params.max_tilt_deg:
        off = "from up" if what == "cylinder axis" else "from horizontal"
        return f"{what} {tilt:.0f} deg {off} (max_tilt_deg {params.max_tilt_deg:g}): not an upright facade"
    if np.isfinite(s.radius_m) and s.radius_m < params.min_radius_footprint * footprint_m:
        return (f"radius {s.radius_m:.3g} m under {params.min_radius_footprint:g} x the view's footprint of "
                f"{footprint_m:.3g} m (min_radius_footprint): an object, not a facade")
    if fit.rms_m > params.max_rms_footprint * footprint_m:
        return (f"RMS residual {fit.rms_m:.3g} m over {params.max_rms_footprint:g} x the view's footprint of "
                f"{footprint_m:.3g} m (max_rms_footprint): clutter, not a surface")
    return None


def implausible_displacement(displacement_px: float, width_px: int, height_px: int,
                             params: SurfaceFitParams) -> str | None:
    """Why a fit whose rectification moves a pixel of a ``width_px`` x ``height_px`` view by up to
    ``displacement_px`` (at the view's own scale: ``surface_map.warp_displacement_px``) cannot be the
    surface the view frames, or None when it can."""
    limit = params.max_displacement_size * max(width_px, height_px)
    if not displacement_px <= limit:  # NaN too: no pixel of the view meets the surface
        return (f"its map moves pixels up to {displacement_px:.0f} px, more than max_displacement_size = "
                f"{params.max_displacement_size:g} x the view's {width_px} x {height_px} px: not the surface "
                "the view frames")
    return None


@dataclass(frozen=True, eq=False)
class Surface:
    """A cylinder or plane (kappa = 0) in the stable tangent-point form of the module docstring."""

    origin: np.ndarray  # [3] tangent point p0 (m, world)
    axis: np.ndarray  # [3] unit axis a (any in-plane direction for a plane)
    normal: np.ndarray  # [3] unit outward normal n at p0
    curvature_per_m: float  # signed kappa (1/m)

    @property
    def binormal(self) -> np.ndarray:  # [3] b = n x a
        return np.cross(self.normal, self.axis)

    @property
    def radius_m(self) -> float:
        return float("inf") if self.curvature_per_m == 0.0 else 1.0 / abs(self.curvature_per_m)

    def local(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(t, w) [N] of world points [N, 3] in the frame (b, n) about p0."""
        q = np.asarray(points, dtype=np.float64) - self.origin
        return q @ self.binormal, q @ self.normal

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [N] (m) of world points [N, 3] to the surface, positive on the normal side."""
        t, w = self.local(points)
        return _stable_distance(t, w, self.curvature_per_m)

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Ray parameter [N] of the first hit (lambda > 0) of rays o + lambda d ([N, 3] each); NaN: a miss."""
        k = self.curvature_per_m
        t0, w0 = self.local(origins)
        dt, dw = np.asarray(directions) @ self.binormal, np.asarray(directions) @ self.normal
        A = k * (dt**2 + dw**2)
        B = 2.0 * k * (w0 * dw + t0 * dt) + 2.0 * dw
        C = k * (w0**2 + t0**2) + 2.0 * w0
        disc = B**2 - 4.0 * A * C
        ok = disc >= 0
        q = -0.5 * (B + np.copysign(np.sqrt(np.where(ok, disc, 0.0)), B))
        with np.errstate(divide="ignore", invalid="ignore"):
            r1 = np.where(A != 0, q / A, np.nan)
            r2 = np.where(q != 0, C / q, np.nan)
        roots = np.stack([r1, r2], axis=1)
        roots[~(roots > 1e-9)] = np.inf
        lam = roots.min(axis=1)
        return np.where(ok & np.isfinite(lam), lam, np.nan)

    def to_dict(self) -> dict:
        k = self.curvature_per_m
        return {
            "kind": "plane" if k == 0.0 else "cylinder",
            "origin_m": self.origin.tolist(), "axis": self.axis.tolist(), "normal": self.normal.tolist(),
            "curvature_per_m": k, "radius_m": None if k == 0.0 else 1.0 / abs(k),
            "axis_point_m": None if k == 0.0 else (self.origin - self.normal / k).tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Surface:
        return cls(np.array(d["origin_m"]), np.array(d["axis"]), np.array(d["normal"]),
                   float(d["curvature_per_m"]))


@dataclass(frozen=True, eq=False)
class SurfaceFit:
    """A fitted surface with its quality: RMS distance of the inliers (m) and counts. ``part``: where the
    points lay on separate parts and the fit took the one holding most of its inliers, those inliers [K, 3]
    (the extent of the surface the view frames); None where it took every part."""

    surface: Surface
    rms_m: float
    n_points: int
    n_inliers: int
    part: np.ndarray | None = None

    def to_dict(self) -> dict:
        d = {**self.surface.to_dict(), "rms_m": self.rms_m, "n_points": self.n_points,
             "n_inliers": self.n_inliers}
        return d if self.part is None else {**d, "fitted_part": True}


def _stable_distance(t: np.ndarray, w: np.ndarray, k: float) -> np.ndarray:
    """d(t, w; kappa) of the module docstring: finite for every kappa, exactly w at kappa = 0."""
    return (k * (w * w + t * t) + 2.0 * w) / (np.sqrt((k * w + 1.0) ** 2 + (k * t) ** 2) + 1.0)


def check_points(points: np.ndarray, params: SurfaceFitParams, unit_m: float,
                 source: str | Path | None = None) -> None:
    """Raise ``SurfaceFitError`` for too few points or points on one line (second spread below
    ``min_spread`` of ``unit_m``, the frontal views' footprint)."""
    n = len(points)
    if n < params.min_points:
        raise SurfaceFitError(source, f"at least {params.min_points} coarse points in the view", f"{n}")
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(points.T)), 0.0))  # ascending
    if spread[1] < params.min_spread * unit_m:
        raise SurfaceFitError(source, "points spread over a surface (2nd spread >= "
                              f"{params.min_spread * unit_m:.3g} m, min_spread of the views' footprint)",
                              f"points along one line (spreads {spread[2]:.3g} m and {spread[1]:.3g} m)")


def ransac_plane(points: np.ndarray, viewpoint: np.ndarray, params: SurfaceFitParams, unit_m: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Inlier mask [N] of the facade plane among 3-point RANSAC hypotheses.

    Priors of a frontal view: the facade faces the camera (normal within ``max_normal_angle_deg`` of the
    direction to ``viewpoint``) and it is the first surface seen (points well in front of a plane count
    against it; ghost points mirrored behind the glass lie behind the facade). Score = inliers - in front."""
    n, thr = len(points), params.ransac_threshold * unit_m
    idx = rng.integers(0, n, size=(RANSAC_ITERATIONS, 3))
    p = points[idx]  # [I, 3, 3]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    good = norm > 1e-12
    normals, p0 = normals[good] / norm[good, None], p[good, 0]
    to_eye = viewpoint - p0
    normals *= np.sign(np.einsum("id,id->i", normals, to_eye))[:, None]  # face the camera
    facing = np.einsum("id,id->i", normals, to_eye / np.linalg.norm(to_eye, axis=1, keepdims=True))
    keep = facing >= np.cos(np.radians(params.max_normal_angle_deg))
    normals, p0 = normals[keep], p0[keep]
    best, best_score = np.zeros(n, bool), -np.inf
    for k in range(0, len(normals), 64):  # batches bound memory at [64, N]
        d = np.einsum("ind,id->in", points[None] - p0[k:k + 64, None], normals[k:k + 64])
        score = (np.abs(d) < thr).sum(axis=1) - (d > thr).sum(axis=1)
        j = int(np.argmax(score))
        if score[j] > best_score:
            best, best_score = np.abs(d[j]) < thr, float(score[j])
    return best


def facing_points(points: np.ndarray, toward_camera: np.ndarray, knn: int,
                  max_angle_deg: float) -> np.ndarray:
    """Mask [N] of the points whose local surface faces the camera: the normal of the plane through each
    point's ``knn`` nearest points (open3d's PCA estimate, either sign) within ``max_angle_deg`` of the
    unit ``toward_camera`` (minus the optical axis). The ground before a facade is level, the facade faces
    a frontal view: seen from a low camera the ground's points outnumber the facade's, and a plane fit
    takes the ground (tests/rectification/test_rectify_hidden.py builds that case)."""
    n = len(points)
    if knn <= 0 or n < 3:
        return np.ones(n, bool)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(min(knn, n)))
    normals = np.asarray(cloud.normals)
    return np.abs(normals @ np.asarray(toward_camera, float)) >= np.cos(np.radians(max_angle_deg))


def _pca_frame(points: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted centroid [3] and eigenvectors [3, 3] (columns, ascending eigenvalues)."""
    c = (weights[:, None] * points).sum(0) / weights.sum()
    q = points - c
    _, vecs = np.linalg.eigh((weights[:, None] * q).T @ q)
    return c, vecs


def quadric_init(points: np.ndarray, viewpoint: np.ndarray, scale_m: float,
                 iterations: int = 8) -> Surface:
    """Initial surface from a robust (Huber IRLS) quadric height field over the points' plane."""
    w8 = np.ones(len(points))
    for _ in range(iterations):
        c, vecs = _pca_frame(points, w8)
        n, e1, e2 = vecs[:, 0], vecs[:, 2], vecs[:, 1]
        if (viewpoint - c) @ n < 0:
            n = -n
        q = points - c
        u, v, h = q @ e1, q @ e2, q @ n
        A = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)
        coef = np.linalg.lstsq(A * w8[:, None], h * w8, rcond=None)[0]
        r = np.abs(A @ coef - h)
        w8 = np.minimum(1.0, scale_m / np.maximum(r, 1e-12))
    H = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
    evals, evecs = np.linalg.eigh(H)
    flat = int(np.argmin(np.abs(evals)))
    axis = evecs[0, flat] * e1 + evecs[1, flat] * e2
    kappa = -float(evals[1 - flat])
    p0 = c + coef[0] * n  # the height field at the centroid (slope is absorbed by the refinement)
    return Surface(p0, axis / np.linalg.norm(axis), n, kappa)


def refine_surface(surface: Surface, points: np.ndarray, scale_m: float) -> Surface:
    """Least squares on the stable distance over (frame rotation [3], offset along n, kappa), soft-L1 loss."""
    R0 = np.stack([surface.axis, surface.binormal, surface.normal], axis=1)  # columns a, b, n

    def unpack(x: np.ndarray) -> Surface:
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        return Surface(surface.origin + x[3] * R[:, 2], R[:, 0], R[:, 2], float(x[4]))

    def residual(x: np.ndarray) -> np.ndarray:
        return unpack(x).signed_distance(points)

    x0 = np.array([0.0, 0.0, 0.0, 0.0, surface.curvature_per_m])
    sol = least_squares(residual, x0, loss="soft_l1", f_scale=scale_m, x_scale=[0.1, 0.1, 0.1, scale_m, 0.01])
    return unpack(sol.x)


def fit_plane(points: np.ndarray, viewpoint: np.ndarray, scale_m: float, iterations: int = 8) -> Surface:
    """A plane through world points [N, 3] by robust (Huber IRLS) PCA, its normal toward ``viewpoint``."""
    w8 = np.ones(len(points))
    for _ in range(iterations):
        c, vecs = _pca_frame(points, w8)
        r = np.abs((points - c) @ vecs[:, 0])
        w8 = np.minimum(1.0, scale_m / np.maximum(r, 1e-12))
    n = vecs[:, 0] if (viewpoint - c) @ vecs[:, 0] >= 0 else -vecs[:, 0]
    return Surface(c, vecs[:, 2], n, 0.0)


def sagitta_m(surface: Surface, points: np.ndarray) -> float:
    """Bulge (m) of ``surface`` over the extent of ``points`` [N, 3] across its axis: |kappa| w^2 / 8."""
    t, _ = surface.local(points)
    return abs(surface.curvature_per_m) * float(np.ptp(t)) ** 2 / 8.0 if len(t) else 0.0


def point_parts(points: np.ndarray, knn: int) -> np.ndarray:
    """Label [N] of each point's part: the connected components of the graph that joins two points when
    each is among the other's ``knn`` nearest. A surface's points join densely; a lone point between two
    surfaces (a ghost, a stray) is among neither's nearest and joins neither, so that a gap between two
    surfaces splits them even where single points lie across it. ``knn`` 0: one part."""
    n = len(points)
    k = min(knn, n - 1)
    if k <= 0:
        return np.zeros(n, int)
    _, idx = cKDTree(points).query(points, k + 1)
    pairs = (np.repeat(np.arange(n), k), idx[:, 1:].ravel())
    near = coo_matrix((np.ones(n * k), pairs), shape=(n, n)).tocsr()
    return connected_components(near.multiply(near.T), directed=False)[1]


#: Pratt's constraint B^2 + C^2 - 4 A D on a line or circle A (s^2 + w^2) + B s + C w + D = 0, as a matrix
_PRATT = np.array([[0.0, 0, 0, -2], [0, 1, 0, 0], [0, 0, 1, 0], [-2, 0, 0, 0]])


def _circle_costs(moments: np.ndarray, z: np.ndarray, left: np.ndarray, band: float) -> np.ndarray:
    """Truncated squared distances [C], summed, of cross-section points ``z`` [K, 4] (rows (s^2 + w^2, s, w,
    1)) in ``left`` [C, K] (each row one set) to the line or circle ``A (s^2 + w^2) + B s + C w + D = 0``
    that Pratt's fit takes from the set's moments ``moments`` [C, 4, 4] (``z^T z`` over it): the algebraic
    least squares under ``B^2 + C^2 - 4 A D = 1``, which holds lines (A = 0) and circles alike. Each point's
    distance, ``2 f / (1 + sqrt(1 + 4 A f))`` with f the algebraic value (exact for both), counts at most
    ``band`` squared: a point beyond is no evidence of the surface's shape."""
    _, vecs = np.linalg.eig(np.linalg.solve(_PRATT, moments))  # M v = eta P v
    vecs = np.real(vecs)  # [C, 4, 4], columns
    norm = np.einsum("cij,ik,ckj->cj", vecs, _PRATT, vecs)
    vecs = vecs / np.sqrt(np.where(norm > 1e-12, norm, 1.0))[:, None, :]
    err = np.where(norm > 1e-12, np.einsum("cij,cik,ckj->cj", vecs, moments, vecs), np.inf)
    v = np.take_along_axis(vecs, np.argmin(err, axis=1)[:, None, None], axis=2)[:, :, 0]  # [C, 4]
    f = v @ z.T  # [C, K]
    d = 2.0 * f / (1.0 + np.sqrt(np.maximum(1.0 + 4.0 * v[:, :1] * f, 0.0)))
    cost = np.where(left, np.minimum(d * d, band * band), 0.0).sum(axis=1)
    return np.where(np.isfinite(err).any(axis=1), cost, np.inf)


def _bend_directions(points: np.ndarray, plane: Surface, scale_m: float) -> list[np.ndarray]:
    """The two in-plane directions [3] of ``plane`` across which world points [N, 3] near it bend most and
    least (the principal directions of their robust quadric height field, ``quadric_init``): two walls
    meeting at a kink bend across the line where they meet, whatever way the plane's own in-plane axes
    (the points' spreads) lie."""
    bent = quadric_init(points, plane.origin + plane.normal, scale_m)
    across = bent.binormal - (bent.binormal @ plane.normal) * plane.normal
    across /= np.linalg.norm(across)
    return [across, np.cross(plane.normal, across)]


def turn_split(points: np.ndarray, surface: Surface, params: SurfaceFitParams, unit_m: float,
               curved: bool = True, candidates: int = 64, looked_at: np.ndarray | None = None) -> np.ndarray:
    """Mask [N] of one side of the best split of ``points`` [N, 3] into two surfaces meeting along a line
    across ``surface`` (a flat wall continued by a curved corner, tangentially or at a kink, or by a second
    flat wall at a kink, with no gap between them: one part for ``point_parts``): the side holding
    ``looked_at`` [3] (the point of ``surface`` a view's optical axis meets: the view frames the surface it
    looks at, whichever side holds more points), else, with no ``looked_at``, the side holding most.

    Only the points within ``ransac_threshold`` of ``surface`` take part (far outliers drop out as in the
    fit). They are taken in cross-section across ``surface``'s axis (a plane's two in-plane directions both
    tried: its own axes where a cylinder was allowed, ``curved``, which found the points' bend within their
    scatter; else, a plane fitted over any bend, across and along the way they bend most,
    ``_bend_directions``), split at ``candidates`` places that leave ``min_points`` on each side, and each
    side fitted by a line or circle (``_circle_costs``, its residuals truncated at the inlier band, 3
    ``inlier_scale``); the split of least total cost wins. The mask holds every point on the winning side, so
    that the surface's robust fit there (``_fit_points``) sees that side's outliers as the whole fit does."""
    band = params.ransac_threshold * unit_m
    near = np.abs(surface.signed_distance(points)) < band
    n = int(near.sum())
    if n < 2 * params.min_points:
        return np.ones(len(points), bool)
    if surface.curvature_per_m != 0.0:
        directions = [surface.binormal]
    elif curved:
        directions = [surface.binormal, surface.axis]
    else:
        directions = _bend_directions(points[near], surface, params.inlier_scale * unit_m)
    centre = points[near].mean(0)
    q = points - centre
    w = q @ surface.normal
    ks = np.unique(np.linspace(params.min_points, n - params.min_points, candidates).astype(int))
    best, best_cost = np.ones(len(points), bool), np.inf
    for u in directions:
        s = q @ u
        order = np.argsort(s[near])
        ss, ww = s[near][order] / unit_m, w[near][order] / unit_m  # unit scale keeps the moments conditioned
        z = np.stack([ss * ss + ww * ww, ss, ww, np.ones(n)], 1)
        cum = np.cumsum(z[:, :, None] * z[:, None, :], axis=0)
        left = np.arange(n)[None, :] < ks[:, None]  # [C, n]: the points before each split
        cost = (_circle_costs(cum[ks - 1], z, left, 3.0 * params.inlier_scale)
                + _circle_costs(cum[-1] - cum[ks - 1], z, ~left, 3.0 * params.inlier_scale))
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            k = int(ks[j])
            cut = 0.5 * (ss[k - 1] + ss[k]) * unit_m
            before = 2 * k >= n if looked_at is None else float((looked_at - centre) @ u) < cut
            best_cost, best = float(cost[j]), (s < cut) if before else (s >= cut)
    return best


def _rms(surface: Surface, points: np.ndarray) -> float:
    return float(np.sqrt(np.mean(surface.signed_distance(points) ** 2)))


def _fit_points(points: np.ndarray, viewpoint: np.ndarray, params: SurfaceFitParams, unit_m: float,
                source: str | Path | None, curved: bool) -> tuple[Surface, np.ndarray]:
    """Steps (2)-(4) of the module docstring on world points [N, 3]: the surface and its inlier mask [N]."""
    rng = np.random.default_rng(RANSAC_SEED)
    keep = ransac_plane(points, viewpoint, params, unit_m, rng)
    check_points(points[keep], params, unit_m, source)
    scale = params.inlier_scale * unit_m
    surface = quadric_init(points[keep], viewpoint, scale)
    for _ in range(2):  # refit on the inliers of the refined surface (outliers near the plane drop out)
        surface = refine_surface(surface, points[keep], scale)
        keep = np.abs(surface.signed_distance(points)) < 3.0 * scale
        check_points(points[keep], params, unit_m, source)
    rms = float(np.sqrt(np.mean(surface.signed_distance(points[keep]) ** 2)))
    if not curved or sagitta_m(surface, points[keep]) < MIN_SAGITTA_RMS * rms:
        surface = fit_plane(points[keep], viewpoint, scale)
        keep = np.abs(surface.signed_distance(points)) < 3.0 * scale
        check_points(points[keep], params, unit_m, source)
    return surface, keep


def fit_surface(points: np.ndarray, viewpoint: np.ndarray, params: SurfaceFitParams, unit_m: float,
                source: str | Path | None = None, toward_camera: np.ndarray | None = None,
                curved: bool = True) -> SurfaceFit:
    """Fit a cylinder (or plane) to world points [N, 3] seen from ``viewpoint`` [3] (the normal faces it).
    With ``toward_camera`` (unit [3], minus a frontal view's optical axis) only the points whose local
    surface faces it are fitted (``facing_points``); ``n_points`` counts the points given.

    ``curved = False`` fits a plane only; a cylinder whose sagitta over its inliers is under
    ``MIN_SAGITTA_RMS`` times its RMS residual is replaced by the plane as well. A fit whose inliers hold
    ``min_points`` or more on each of two separate parts of the points (``point_parts`` over
    ``normal_knn`` neighbours) is redone on the part holding most of them (``SurfaceFit.part``), unless the
    fit over all fits that part within ``MAX_PART_RMS_RATIO`` of its own fit (one surface with a gap); the
    other is left to the views that frame it. A plane and a cylinder on one part (no gap between them) are
    split where the fit over both strays from either side (``_turn_fit``), and so are two planes meeting at
    a kink, ``curved = False`` too: the fit is redone on the side the optical axis (minus
    ``toward_camera`` from ``viewpoint``) meets, the surface the view looks at, else on the side holding
    most.

    The params' lengths are fractions of ``unit_m``, the frontal views' footprint
    (``surface_map.frontal_footprint_m``). Raises ``SurfaceFitError`` naming ``source`` for too few points
    or points on one line."""
    points = np.asarray(points, dtype=np.float64)
    n_given = len(points)
    if toward_camera is not None:
        points = points[facing_points(points, toward_camera, params.normal_knn, params.max_normal_angle_deg)]
        if n_given >= params.min_points > len(points):
            angle = params.max_normal_angle_deg
            raise SurfaceFitError(source, f"at least {params.min_points} coarse points whose surface faces "
                                  f"the camera (normal within {angle:g} deg of the optical axis)",
                                  f"{len(points)} of {n_given}")
    check_points(points, params, unit_m, source)
    viewpoint = np.asarray(viewpoint, float)
    surface, keep = _fit_points(points, viewpoint, params, unit_m, source, curved)
    fitted = np.ones(len(points), bool)  # the points the surface is fitted to
    parts = point_parts(points, params.normal_knn)
    held = np.bincount(parts[keep])
    if np.count_nonzero(held >= params.min_points) > 1:  # fitted across two parts: fit the main one
        main = parts == int(np.argmax(held))
        part_surface, keep_main = _fit_points(points[main], viewpoint, params, unit_m, source, curved)
        on_main = points[main][keep_main]
        if _rms(surface, on_main) > MAX_PART_RMS_RATIO * _rms(part_surface, on_main):  # bent through both
            surface, fitted = part_surface, main
            keep = np.zeros(len(points), bool)
            keep[np.flatnonzero(main)[keep_main]] = True
    # two surfaces meeting on one part (no gap between them): fit the side the view looks at
    surface, keep, fitted = _turn_fit(surface, keep, fitted, points, viewpoint, params, unit_m, source,
                                      curved, toward_camera)
    d = surface.signed_distance(points[keep])
    return SurfaceFit(surface, float(np.sqrt(np.mean(d * d))), n_given, int(keep.sum()),
                      None if fitted.all() else points[keep])


def _turn_fit(surface: Surface, keep: np.ndarray, fitted: np.ndarray, points: np.ndarray,
              viewpoint: np.ndarray, params: SurfaceFitParams, unit_m: float,
              source: str | Path | None, curved: bool,
              toward_camera: np.ndarray | None = None) -> tuple[Surface, np.ndarray, np.ndarray]:
    """(surface, inlier mask [N], fitted mask [N]): ``surface`` (inliers ``keep`` among ``points`` [N, 3],
    fitted to those in ``fitted`` [N]) refitted on one side of the best split of its points into two surfaces
    (``turn_split``), else as given (the sides fitted as ``curved`` says, as the surface was). The side kept
    is the one the view looks at: where its optical axis (from ``viewpoint`` along minus ``toward_camera``)
    meets ``surface``; the side holding most where that is not known (no ``toward_camera``, or the axis
    misses the surface). It is refitted where a plane takes part (the surface or a side's own fit: not
    cylinders alone) and the surface fits the other side's inliers more than ``MAX_PART_RMS_RATIO`` times
    worse (RMS) than the worse of the two sides' own fits fits its own: bent through both, it keeps to the
    side holding most and strays from the other. Not the main side's ratio, as across separate parts: a
    cylinder bent through a curved corner and the flat wall it continues tangentially strays little over the
    corner, and a side of few points fitted alone (tilt and offset free) takes up some of the points' own
    error, so that its fit is no measure of their scatter alone."""
    looked_at = None
    if toward_camera is not None:
        forward = -np.asarray(toward_camera, float)
        lam = float(surface.intersect(viewpoint[None], forward[None])[0])
        looked_at = viewpoint + lam * forward if np.isfinite(lam) else None
    main = np.zeros(len(points), bool)
    main[fitted] = turn_split(points[fitted], surface, params, unit_m, curved, looked_at=looked_at)
    # the other side's points near the surface alone (as the split saw them): beyond it lie other things
    other = fitted & ~main & (np.abs(surface.signed_distance(points)) < params.ransac_threshold * unit_m)
    if other.sum() < params.min_points:
        return surface, keep, fitted
    try:
        other_surface, keep_other = _fit_points(points[other], viewpoint, params, unit_m, source, curved)
        on_other = points[other][keep_other]
        stray = _rms(surface, on_other)
        if not stray > MAX_PART_RMS_RATIO * _rms(other_surface, on_other):
            return surface, keep, fitted  # within the other side's own scatter: one surface
        main_surface, keep_main = _fit_points(points[main], viewpoint, params, unit_m, source, curved)
    except SurfaceFitError:  # a side's points cannot define a surface alone: no second surface
        return surface, keep, fitted
    if all(s.curvature_per_m != 0.0 for s in (surface, main_surface, other_surface)):
        return surface, keep, fitted  # cylinders alone: no plane meets a cylinder or a plane here
    if not stray > MAX_PART_RMS_RATIO * _rms(main_surface, points[main][keep_main]):
        return surface, keep, fitted  # it fits the other side within the points' own scatter: one surface
    keep = np.zeros(len(points), bool)
    keep[np.flatnonzero(main)[keep_main]] = True
    return main_surface, keep, main
