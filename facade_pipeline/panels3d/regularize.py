"""3D panel models from panel corners seen in frontal views (the paper, section 3.1.2, end).

1. Corner pixels are cast as rays onto the coarse mesh (``MeshRaycaster``). Rays that miss, graze the hit
   surface, or land far from the facade surface fitted through the other corners ("ghost" geometry: a
   reflection baked into the mesh, a tree) are rejected for the surface fit and counted.
2. Panels seen with four good corners are grouped into facade parts (neighbours closer than a few panel
   sizes, normals agreeing); each part gets a surface: a plane, or a vertical cylinder when a circle fits its
   corners clearly better (panel columns then follow the cylinder's rulings).
3. Corner rays hit the mesh where it stands proudest near the corner (the frame front), so the glass
   surface is found along the normal from the coarse evidence inside the panels: the densest offset of the
   coarse points (``coarse_points_mode``) or the median offset of the coarse mesh (``coarse_mesh_median``).
4. Every corner ray (missed ones included) is intersected with the part's surface; panels get global rows
   and columns by clustering their centres; per row of corners the height is averaged, per column the
   position along the surface (s, a ruling on cylinders), both robustly (outliers by the grid's regularity),
   after each view's offset along the surface (its pose's error, shared by all its corners) is fitted with
   the lines and taken off (``facade_pipeline.panels3d.grid.view_offsets``).

Frames: local (01_import), metres. Surface coordinates (s, z, h): see ``facade_pipeline.panels3d.model``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster, grazing
from facade_pipeline.panels3d.model import PartSurface
from facade_pipeline.panels3d.params import RegularizeConfig

OK, MISS, GRAZING, GHOST = 0, 1, 2, 3
STATUS_NAMES = {MISS: "missed", GRAZING: "grazing", GHOST: "ghost"}


@dataclass(frozen=True, eq=False)
class CornerRays:
    """The corner rays of Q panel observations: ``origins`` and unit ``dirs`` [Q, 4, 3] (local frame),
    the observing ``view`` [Q] and the camera centres [V, 3]."""

    origins: np.ndarray
    dirs: np.ndarray
    view: np.ndarray
    centers: np.ndarray


def corner_rays(quads_px: list[np.ndarray], view: list[int], cameras: list[PinholeCamera]) -> CornerRays:
    """Rays through the corners ``quads_px`` (Q arrays [4, 2], px) of views ``view`` [Q] of ``cameras``."""
    q = len(quads_px)
    o, d = np.zeros((q, 4, 3)), np.zeros((q, 4, 3))
    for i, (c, v) in enumerate(zip(quads_px, view, strict=True)):
        o[i], d[i] = cameras[v].pixel_rays(c[:, 0], c[:, 1])
    return CornerRays(
        o, d, np.asarray(view, dtype=np.int64), np.array([c.center for c in cameras]).reshape(-1, 3)
    )


def cast_corners(
    rc: MeshRaycaster, rays: CornerRays, grazing_max_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Hit points [Q, 4, 3] (NaN where none) and status [Q, 4] (OK, MISS, GRAZING) of the corner rays."""
    hits = rc.cast(rays.origins.reshape(-1, 3), rays.dirs.reshape(-1, 3))
    status = np.where(hits.hit, OK, MISS)
    status[hits.hit & grazing(rays.dirs.reshape(-1, 3), hits.normal, grazing_max_deg)] = GRAZING
    t = np.where(status == OK, hits.t.astype(np.float64), np.nan)
    pts = rays.origins.reshape(-1, 3) + t[:, None] * rays.dirs.reshape(-1, 3)
    return pts.reshape(-1, 4, 3), status.reshape(-1, 4)


def quad_frames(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres [Q, 3], sizes [Q] (mean edge length, m) and outward unit normals [Q, 3] of 3D quads
    [Q, 4, 3] ordered BL, BR, TR, TL seen from outside (right x up = outward)."""
    c = points.mean(axis=1)
    edges = np.linalg.norm(points - np.roll(points, -1, axis=1), axis=2)
    n = np.cross(points[:, 2] - points[:, 0], points[:, 3] - points[:, 1])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return c, edges.mean(axis=1), n


def quad_flatness(points: np.ndarray) -> np.ndarray:
    """[Q] largest distance (m) of a 3D quad's corners [Q, 4, 3] from the plane through its centre spanned by
    its diagonals: large when a corner landed on ghost geometry in front of or behind the facade."""
    c, _, n = quad_frames(points)
    return np.abs(np.einsum("qkj,qj->qk", points - c[:, None], n)).max(axis=1)


def group_parts(
    points: np.ndarray, anchor: np.ndarray, link_factor: float, max_angle_deg: float
) -> np.ndarray:
    """Part index [Q] of each anchor quad (-1 for the others): connected components of the graph linking
    anchors whose centres are closer than ``link_factor`` times the larger size and whose normals agree
    within ``max_angle_deg``. Parts are numbered by decreasing size."""
    idx = np.flatnonzero(anchor)
    parent = np.arange(len(idx))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if len(idx):
        c, size, n = quad_frames(points[idx])
        dist = np.linalg.norm(c[:, None] - c[None], axis=2)
        near = dist < link_factor * np.maximum(size[:, None], size[None])
        near &= (n @ n.T) > np.cos(np.radians(max_angle_deg))
        for i, j in zip(*np.nonzero(np.triu(near, 1)), strict=True):
            parent[find(i)] = find(j)
    roots = np.array([find(i) for i in range(len(idx))], dtype=np.int64)
    part = np.full(len(points), -1, dtype=np.int64)
    labels, counts = np.unique(roots, return_counts=True)
    for rank, lab in enumerate(labels[np.argsort(-counts, kind="stable")]):
        part[idx[roots == lab]] = rank
    return part


def _fit_line(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid [2] and unit normal [2] of the least-squares line through ``xy`` [M, 2]."""
    c = xy.mean(axis=0)
    _, _, vt = np.linalg.svd(xy - c)
    return c, vt[1]


def _fit_circle(xy: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Centre [2] and radius of the algebraic (Kasa) least-squares circle through ``xy`` [M, 2]."""
    m = xy.mean(axis=0)
    p = xy - m  # centred for conditioning
    A = np.concatenate([p, np.ones((len(p), 1))], axis=1)
    sol, *_ = np.linalg.lstsq(A, (p**2).sum(1), rcond=None)
    r2 = sol[2] + (sol[:2] ** 2).sum() / 4
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return m + sol[:2] / 2, float(np.sqrt(r2))


def fit_part_surface(points: np.ndarray, cam_centers: np.ndarray, planar_max_sagitta_m: float) -> PartSurface:
    """The surface through corner points [M, 3] of one part: a vertical plane, or a vertical cylinder when
    the circle fitted to their horizontal positions bulges more than ``planar_max_sagitta_m`` over the
    part's width and fits better than the line. Outward faces the cameras (centres [C, 3])."""
    xy = points[:, :2]
    c, n = _fit_line(xy)
    toward = (cam_centers[:, :2] - c).mean(axis=0)
    n = n if n @ toward >= 0 else -n
    normal = np.array([n[0], n[1], 0.0])
    plane = PartSurface("planar", np.array([c[0], c[1], 0.0]), normal)
    width = float(np.ptp(plane.coords(points)[:, 0]))
    circle = _fit_circle(xy) if len(xy) >= 3 else None
    if circle is None:
        return plane
    centre, radius = circle
    res_line = np.abs((xy - c) @ n)
    res_circle = np.abs(np.linalg.norm(xy - centre, axis=1) - radius)
    sagitta = width**2 / (8 * radius)
    if sagitta <= planar_max_sagitta_m or np.sqrt((res_circle**2).mean()) >= 0.5 * np.sqrt(
        (res_line**2).mean()
    ):
        return plane
    cams = np.linalg.norm(cam_centers[:, :2] - centre, axis=1)
    convex = bool(np.median(cams) > radius)
    d = xy - centre
    ref = float(np.arctan2(d[:, 1].mean(), d[:, 0].mean()))
    origin = np.array([centre[0], centre[1], 0.0])
    ref_n = np.array([np.cos(ref), np.sin(ref), 0.0]) * (1 if convex else -1)
    return PartSurface("cylindrical", origin, ref_n, radius, convex, ref)


#: a corner (or a hit) more than this many robust sigmas (1.4826 x the median absolute deviation) off its
#: row or column line (or its part's surface) is an outlier: about 1 in 15,000 of Gaussian scatter is
OUTLIER_MAD_FACTOR = 4.0


def robust_inliers(values: np.ndarray, mad_factor: float, floor: float) -> np.ndarray:
    """[M] bool: values within max(``floor``, ``mad_factor`` robust sigmas) of their median."""
    if len(values) == 0:
        return np.zeros(0, bool)
    dev = np.abs(values - np.median(values))
    sigma = 1.4826 * np.median(dev)
    return dev <= max(floor, mad_factor * sigma)


def fit_surface_robust(
    points: np.ndarray, cam_centers: np.ndarray, cfg: RegularizeConfig
) -> tuple[PartSurface, np.ndarray]:
    """``fit_part_surface`` with ghost rejection: points [M, 3] farther than ``ghost_max_m`` (or than the
    robust spread) from the surface are dropped and the surface refitted. Returns it and the inliers [M]."""
    keep = np.ones(len(points), bool)
    for _ in range(3):
        surf = fit_part_surface(points[keep], cam_centers, cfg.planar_max_sagitta_m)
        h = surf.coords(points)[:, 2]
        new = (np.abs(h) <= cfg.ghost_max_m) & robust_inliers(h, OUTLIER_MAD_FACTOR, cfg.outlier_floor_m)
        if new.sum() < 3 or (new == keep).all():
            break
        keep = new
    return surf, keep


def glass_offset(
    surface: PartSurface,
    footprints: np.ndarray,
    coarse_points: np.ndarray,
    rc: MeshRaycaster,
    cfg: RegularizeConfig,
) -> tuple[float, str, int]:
    """Offset (m, along the outward normal) of the glass from ``surface``, from the coarse evidence inside
    the panel ``footprints`` [P, 4] (s0, s1, z0, z1, shrunk away from frames): the density mode of the
    coarse points' offsets, else the median offset of the coarse mesh. Returns (offset, source, count)."""
    if len(footprints) == 0:
        return 0.0, "none", 0
    if len(coarse_points):
        szh = surface.coords(coarse_points)
        inside = _in_footprints(szh, footprints) & (np.abs(szh[:, 2]) <= cfg.depth_window_m)
        h = szh[inside, 2]
        if len(h) >= cfg.depth_min_points:
            grid = np.arange(-cfg.depth_window_m, cfg.depth_window_m, cfg.depth_bandwidth_m / 4)
            density = np.zeros_like(grid)
            for a in range(0, len(h), 4096):
                density += np.exp(
                    -0.5 * ((grid[:, None] - h[None, a : a + 4096]) / cfg.depth_bandwidth_m) ** 2
                ).sum(1)
            mode = grid[int(np.argmax(density))]
            near = np.abs(h - mode) <= cfg.depth_bandwidth_m
            return float(np.mean(h[near])), "coarse_points_mode", int(len(h))
    # the coarse mesh along the normal through a grid of points in each footprint
    u = (np.arange(8) + 0.5) / 8
    fs = footprints[:, None, None, :]
    s = fs[..., 0] + u[None, :, None] * (fs[..., 1] - fs[..., 0])
    z = fs[..., 2] + u[None, None, :] * (fs[..., 3] - fs[..., 2])
    s, z = np.broadcast_arrays(s, z)
    szh = np.stack([s, z, np.full_like(s, cfg.depth_window_m)], axis=-1).reshape(-1, 3)
    start = surface.points(szh)
    hits = rc.cast(start, -surface.normals_at(start))
    ok = hits.hit & (hits.t <= 2 * cfg.depth_window_m)
    if not ok.any():
        return 0.0, "none", 0
    return float(np.median(cfg.depth_window_m - hits.t[ok])), "coarse_mesh_median", int(ok.sum())


def _in_footprints(szh: np.ndarray, footprints: np.ndarray) -> np.ndarray:
    """[N] bool: surface coordinates [N, 3] inside any footprint [P, 4] (s0, s1, z0, z1)."""
    out = np.zeros(len(szh), bool)
    for s0, s1, z0, z1 in footprints:
        out |= (szh[:, 0] >= s0) & (szh[:, 0] <= s1) & (szh[:, 1] >= z0) & (szh[:, 1] <= z1)
    return out


def footprints_of(szh: np.ndarray, shrink: float) -> np.ndarray:
    """Footprints [Q, 4] (s0, s1, z0, z1) of quads given by corner surface coordinates [Q, 4, 3], shrunk
    about their centres by ``shrink``."""
    lo, hi = szh[..., :2].min(axis=1), szh[..., :2].max(axis=1)
    c, half = (lo + hi) / 2, shrink * (hi - lo) / 2
    return np.stack(
        [c[:, 0] - half[:, 0], c[:, 0] + half[:, 0], c[:, 1] - half[:, 1], c[:, 1] + half[:, 1]], axis=1
    )


def cluster_1d(values: np.ndarray, gap: float) -> np.ndarray:
    """Cluster labels [M] (0, 1, ... in increasing order of value) splitting sorted ``values`` at gaps
    larger than ``gap``."""
    order = np.argsort(values, kind="stable")
    breaks = np.concatenate([[0], (np.diff(values[order]) > gap).astype(np.int64)]).cumsum()
    labels = np.empty(len(values), np.int64)
    labels[order] = breaks
    return labels
