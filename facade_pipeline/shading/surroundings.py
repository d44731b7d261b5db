"""The surroundings as a surface model from the coarse point cloud: what a reflected ray meets in front of
the facade.

A proxy that put everything above the ground on one cylinder wall, twice the facade's half-diagonal away,
smeared the surroundings that stand at other distances (on demo, trees 16-32 m from the facade and
buildings 50-75 m): rays from different points of the facade that meet the same tree read different texels
of that wall. Photogrammetry reconstructs the surroundings with the facade: its coarse point cloud holds
them. Here they become a surface model (a DSM, as photogrammetry software exports one) that the reflected
rays of the environment proxy (``shading.proxy``) are cast against:

- points off the facade (beyond its bounds by ``margin_m``, horizontally) and above the ground (by
  ``MIN_HEIGHT_CELLS`` cells) are binned into square cells of ``cell_m`` around the facade's centre, out to
  ``reach_m``; a cell's top is its highest point's height, and a grey-level closing over 3 x 3 cells fills
  the one-cell holes that sparse points leave in roofs and crowns; its bottom is its lowest point's, or the
  ground where that is within ``GROUND_SNAP_CELLS`` cells of it (walls and trunks);
- each cell with something in it is a block from its bottom to its top, with walls where a neighbour does
  not cover that span: a building is a box, a tree's crown a lump that rays can pass under.

Photogrammetry triangulates the features of the reflections too: a plane mirror's image of a point is a
consistent 3D point as far behind the glass as the point stands in front of it (a virtual point), so a
survey's point cloud (a user's COLMAP sparse model, gcw_dev's triangulated points, demo's ghost points)
holds the surroundings' mirror images behind a glass facade. ``unmirror`` moves them back across the glass
plane before the binning, where they are the real surroundings (reflected rays never go behind the facade,
so left there they would be lost). A point counts as virtual where every photo that has it in view sees it
through the glass (the ray crosses the glass plane inside the glass's extent): roofs and walls behind the
facade that photos see over or beside it stay. What stands behind the glass and is seen through it (a room,
a shelf) is mirrored as well: its points cannot be told from a reflection's, and its image stands as close
in front of the glass as it stands behind it. A curved glass is no plane mirror: its points are kept.

A reflected ray from X_r along w_r ends at its first hit on the blocks or on the ground plane; meeting
neither, it goes to the sky. On the proxy's wall maps a block hit is read at its azimuth and elevation as
seen from the eye, the facade's centre on the ground (the lower half of the maps, elevations 0 to the
highest block's, ``top``), and the sky at the ray's own azimuth and elevation (the upper half). The floor
maps are read where the ray meets the ground, out to ``reach_m`` and clamped beyond.

The heights are a buffer of the module, so they are saved with the proxy's weights (``reflection.pt``,
checkpoints) and a loaded model casts against the same surface without the points. The casts run without
gradient (a hit is a step function of the ray, and the features learn from every ray that reads them) on the
rays' device: on a GPU in torch, batched and without a copy to the host, so that a training step never waits
for one (``cast_blocks``); on the CPU through open3d against the same blocks as triangles
(``surface_mesh``) where it is installed, in torch where it is not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

#: The heights below are in cells of the surface model (``cell_m``, itself a fraction of the facade's size),
#: so that a model of a building at 1:25 has the building's surroundings at 1:25: 1 m cells on demo.
#: Points this many cells above the ground or less are ground; the proxy's floor stands for them.
MIN_HEIGHT_CELLS = 0.5
#: A cell whose lowest point is at most this many cells high stands on the ground (walls, trunks).
GROUND_SNAP_CELLS = 1.5
#: Rays start this many cells along w_r from X_r: off the facade, whatever the mesh's numerical noise.
RAY_OFFSET_CELLS = 0.05
#: The elevation of the highest point is at most this (rad).
MAX_ELEVATION = math.radians(60.0)
#: The glass is one plane where its triangles' corners lie within this fraction of their extent of their
#: plane (RMS); a curved or folded facade is not a plane mirror, and its points are kept as they are.
PLANE_TOLERANCE = 0.01
#: At most this many cells across the surface model (a 4096 x 4096 grid of two heights is 128 MiB).
MAX_CELLS = 4096
#: Below this, a ray's vertical component counts as zero: it never meets the ground.
_EPS = 1e-6
#: Ray direction components below this are this (with their sign) in the cast: a crossing that far away
#: is never reached, and no division is by zero.
_TINY = 1e-12
#: The cast works on at most this many (ray, cell) pairs at once (bounded memory for any number of rays).
CAST_CHUNK_PAIRS = 1 << 22


def _filter3(a: np.ndarray, reduce) -> np.ndarray:
    """``reduce`` (np.max or np.min) over each cell's 3 x 3 neighbourhood (edges repeated)."""
    p = np.pad(a, 1, mode="edge")
    h, w = a.shape
    return reduce(np.stack([p[i : i + h, j : j + w] for i in range(3) for j in range(3)]), axis=0)


def surface_heights(
    points: np.ndarray, lo: np.ndarray, hi: np.ndarray, cells: int, cell_m: float, margin_m: float
) -> np.ndarray:
    """The surface model of ``points`` [N, 3] (m) around the facade with bounds [``lo``, ``hi``]: per cell of
    a square grid of ``cells`` x ``cells`` cells of ``cell_m`` centred on the facade's centre (row i at
    x = centre_x + (i - cells / 2 + 0.5) cell_m, column j likewise in y) the heights above the ground of
    the bottom and the top of what stands there, [2, cells, cells] (m; top 0: nothing there, bottom 0:
    standing on the ground)."""
    if cells < 2 or not cell_m > 0:
        raise ValueError(f"a surface model needs >= 2 cells of a positive size, got {cells} of {cell_m} m")
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    off = np.any((p[:, :2] < lo[:2] - margin_m) | (p[:, :2] > hi[:2] + margin_m), axis=1)
    q = p[off & (p[:, 2] > lo[2] + MIN_HEIGHT_CELLS * cell_m)]
    ij = np.floor((q[:, :2] - 0.5 * (lo[:2] + hi[:2])) / cell_m + 0.5 * cells).astype(np.int64)
    inside = ((ij >= 0) & (ij < cells)).all(axis=1)
    at, z = (ij[inside, 0], ij[inside, 1]), q[inside, 2] - lo[2]
    top = np.zeros((cells, cells))
    np.maximum.at(top, at, z)
    bottom = np.full((cells, cells), np.inf)
    np.minimum.at(bottom, at, z)
    # a closing (max, then min, over 3 x 3) fills the one-cell holes sparse points leave in roofs and crowns;
    # a filled cell takes the lowest bottom around it
    top = _filter3(_filter3(top, np.max), np.min)
    bottom = np.where(np.isfinite(bottom), bottom, _filter3(bottom, np.min))
    # what starts this low stands on the ground (walls, trunks: the points stop MIN_HEIGHT_CELLS above it)
    bottom = np.where(np.isfinite(bottom) & (bottom > GROUND_SNAP_CELLS * cell_m), bottom, 0.0)
    bottom = np.where(top > 0, np.minimum(bottom, top), 0.0)
    return np.stack([bottom, top])


@dataclass(frozen=True)
class GlassPlane:
    """The plane of a facade's glass: a point on it, its unit normal towards the cameras, two in-plane unit
    axes (along the facade and up it) and the glass's extent along them (m)."""

    origin: np.ndarray  # [3]
    normal: np.ndarray  # [3]
    axes: np.ndarray  # [2, 3]
    lo: np.ndarray  # [2]
    hi: np.ndarray  # [2]

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """[N] distance of ``points`` [N, 3] from the plane, positive on the cameras' side (m)."""
        return (np.asarray(points, np.float64) - self.origin) @ self.normal


def glass_plane(vertices: np.ndarray, triangles: np.ndarray, glass: np.ndarray | None,
                eyes: np.ndarray) -> GlassPlane | None:
    """The plane of the glass triangles (``glass`` [T] bool) of a mesh ``vertices`` [V, 3], ``triangles``
    [T, 3], its normal towards the mean of ``eyes`` [E, 3] (the cameras' centres): fitted to the triangles'
    corners weighted by area. None where no triangle is glass or the glass is not one plane
    (``PLANE_TOLERANCE``)."""
    if glass is None or not np.any(glass):
        return None
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(triangles)[np.asarray(glass, bool)]]  # [G, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        return None
    # each triangle's corners weighted by its area (its centroids alone: a pane of two triangles gives a line)
    weight = np.repeat(area / (3.0 * area.sum()), 3)
    origin = weight @ tri.reshape(-1, 3)
    corners = tri.reshape(-1, 3) - origin
    _, _, vt = np.linalg.svd(corners * np.sqrt(weight)[:, None], full_matrices=False)
    normal = vt[2]
    if normal @ (np.mean(eyes, axis=0) - origin) < 0:
        normal = -normal
    size = float(np.linalg.norm(corners.max(0) - corners.min(0)))
    if np.sqrt(np.mean((corners @ normal) ** 2)) > PLANE_TOLERANCE * size:
        return None
    # the extent along the facade and up it (the world's z is up), not along the fit's other two singular
    # vectors, which turn freely where the glass is as wide as it is high
    along = np.cross([0.0, 0.0, 1.0], normal)
    if np.linalg.norm(along) < 0.1:  # glass facing up or down: any axes in its plane
        along = vt[0]
    along = along / np.linalg.norm(along)
    axes = np.stack([along, np.cross(normal, along)])
    uv = corners @ axes.T
    return GlassPlane(origin, normal, axes, uv.min(0), uv.max(0))


def unmirror(points: np.ndarray, plane: GlassPlane | None, cameras, margin_m: float) -> np.ndarray:
    """[N] bool: the ``points`` [N, 3] (m) that are virtual, the mirror images of the surroundings in the
    glass (module docstring): more than ``margin_m`` behind ``plane``, in view of at least one of
    ``cameras`` (``PinholeCamera``s: in front of it and inside its image) and seen through the glass (the
    ray from the camera's centre crosses the plane within the glass's extent, ``margin_m`` wider) by every
    camera that has it in view. ``mirrored(points, plane)`` moves them to the surroundings."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if plane is None or len(p) == 0:
        return np.zeros(len(p), bool)
    dist = plane.signed_distance(p)
    behind = np.isfinite(dist) & (dist < -margin_m)
    seen = np.zeros(len(p), bool)
    through = behind.copy()
    q = p[behind]
    for cam in cameras:
        uv, z = cam.project(q)
        with np.errstate(invalid="ignore"):
            in_view = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= cam.width) & (
                uv[:, 1] <= cam.height)
        c = np.asarray(cam.center, np.float64)
        dc = float((c - plane.origin) @ plane.normal)
        # where the ray from the camera to the point crosses the plane (the camera is in front of it)
        t = dc / np.maximum(dc - dist[behind], 1e-300) if dc > 0 else np.zeros(len(q))
        x = c + t[:, None] * (q - c)
        uv_plane = (x - plane.origin) @ plane.axes.T
        inside = (dc > 0) & np.all((uv_plane >= plane.lo - margin_m) & (uv_plane <= plane.hi + margin_m), 1)
        seen[behind] |= in_view
        through[behind] &= inside | ~in_view
    return through & seen


def mirrored(points: np.ndarray, plane: GlassPlane) -> np.ndarray:
    """``points`` [N, 3] reflected across ``plane`` (m)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    return p - 2.0 * plane.signed_distance(p)[:, None] * plane.normal


def surroundings_points(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                        glass: np.ndarray | None, cameras, margin_m: float) -> tuple[np.ndarray, int]:
    """The coarse ``points`` [N, 3] (m) with the virtual ones (``unmirror``) moved across the plane of the
    mesh's glass (``glass_plane``; the cameras' centres give its front): what the surface model is binned
    from, and how many were moved."""
    plane = glass_plane(vertices, triangles, glass, np.array([c.center for c in cameras]).reshape(-1, 3))
    virtual = unmirror(points, plane, cameras, margin_m)
    if not virtual.any():
        return points, 0
    out = np.array(points, np.float64).reshape(-1, 3)
    out[virtual] = mirrored(out[virtual], plane)
    return out, int(virtual.sum())


def surface_mesh(heights: np.ndarray, cell_m: float, centre_xy: np.ndarray, ground_z: float):
    """The cells of ``heights`` [2, n, n] (bottom, top above the ground) as blocks: a top quad per cell, a
    bottom quad where it stands off the ground and walls where a neighbour does not cover the cell's span.
    Vertices [V, 3] and triangles [T, 3] (m)."""
    bottom, top = heights
    n = top.shape[0]
    x0 = centre_xy[0] - 0.5 * n * cell_m
    y0 = centre_xy[1] - 0.5 * n * cell_m
    i, j = np.nonzero(top > 0)
    zt, zb = ground_z + top[i, j], ground_z + bottom[i, j]
    xa, xb = x0 + i * cell_m, x0 + (i + 1) * cell_m
    ya, yb = y0 + j * cell_m, y0 + (j + 1) * cell_m

    def quads_of(corners, keep):  # four (x, y, z) arrays over the cells -> [kept, 4, 3]
        return np.stack([np.stack([u[keep], v[keep], z[keep]], -1) for u, v, z in corners], 1)

    def flat(z):
        return [(xa, ya, z), (xb, ya, z), (xb, yb, z), (xa, yb, z)]

    quads = [quads_of(flat(zt), np.ones_like(zt, bool)), quads_of(flat(zb), bottom[i, j] > 0)]
    pb, pt = np.pad(bottom, 1), np.pad(top, 1)
    for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        nb_b, nb_t = pb[1 + i + di, 1 + j + dj], pt[1 + i + di, 1 + j + dj]
        empty = nb_t <= 0
        if di:
            xe = xb if di > 0 else xa
            ends = ((xe, ya), (xe, yb))
        else:
            ye = yb if dj > 0 else ya
            ends = ((xa, ye), (xb, ye))
        # the cell's span [zb, zt] less the neighbour's [nb_b, nb_t]: a piece above it and one below it
        pieces = (
            (np.where(empty, zb, np.maximum(zb, ground_z + nb_t)), zt),
            (zb, np.where(empty, zb, np.minimum(zt, ground_z + nb_b))),
        )
        (ua, va), (ub, vb) = ends
        for lo_z, hi_z in pieces:
            c = [(ua, va, lo_z), (ub, vb, lo_z), (ub, vb, hi_z), (ua, va, hi_z)]
            quads.append(quads_of(c, hi_z > lo_z + 1e-6))
    q = np.concatenate(quads)  # [Q, 4, 3]
    k = 4 * np.arange(len(q))[:, None]
    return q.reshape(-1, 3), np.concatenate([k + [0, 1, 2], k + [0, 2, 3]]).astype(np.int64)



def _safe(d: Tensor) -> Tensor:
    """``d`` with components nearer zero than ``_TINY`` set to +-``_TINY``: no division by zero, and the
    crossings of a plane the ray runs along land beyond any distance cast."""
    return torch.where(d.abs() < _TINY, torch.where(d < 0, -_TINY, _TINY), d)


def _slab(p: Tensor, d: Tensor, lo: float, hi: float) -> tuple[Tensor, Tensor]:
    """The interval of t in which p + t d is in [lo, hi] (``d`` from ``_safe``)."""
    t1, t2 = (lo - p) / d, (hi - p) / d
    return torch.minimum(t1, t2), torch.maximum(t1, t2)


def _cell(v: Tensor, dv: Tensor, entering: bool) -> Tensor:
    """The cell index of coordinate ``v`` of a ray moving by ``dv``; on a cell border, the cell it enters
    there (``entering``) or the one it leaves."""
    ahead = dv >= 0 if entering else dv < 0
    return torch.where(ahead, torch.floor(v), torch.ceil(v) - 1.0)


@dataclass(frozen=True)
class BlockGrid:
    """The blocks of a surface model as the cast needs them: cell (i, j) of an ``nx`` x ``ny`` grid of
    ``cell_m`` cells (x from ``corner[0] + i cell_m``, y likewise) holds a block from ``zlo[i, j]`` to
    ``zhi[i, j]`` (m; ``zlo`` -inf where it stands on the ground, which the cast leaves to the floor), where
    ``present``. ``z_range``: the heights the blocks span (m)."""

    zlo: Tensor  # [nx * ny]
    zhi: Tensor  # [nx * ny]
    present: Tensor  # [nx * ny] bool
    nx: int
    ny: int
    corner: tuple[float, float]
    cell_m: float
    z_range: tuple[float, float]


def cast_blocks(o: Tensor, d: Tensor, grid: BlockGrid, columns: int) -> Tensor:
    """Distance [P] along unit ``d`` [P, 3] from ``o`` [P, 3] (m) to the first crossing of the blocks'
    surface: from outside the blocks where the ray first enters one, from inside one where it leaves them
    (as a ray cast against a mesh of their outer surface); inf where it does neither. ``columns``: at least
    the number of columns of the ray's major axis (x or y) it crosses inside the grid and the blocks'
    heights; ``grid.nx`` + ``grid.ny`` always is.

    Each ray walks the columns of its major axis in order. Within a column (one cell wide) it crosses at
    most two cells of the other axis, so each column gives two (cell, t-interval) pairs, the second empty
    where it stays in one cell; the cells' blocks cut each interval to where the ray is inside them."""
    nx, ny = grid.nx, grid.ny
    p = torch.stack([(o[:, 0] - grid.corner[0]) / grid.cell_m, (o[:, 1] - grid.corner[1]) / grid.cell_m], -1)
    q = _safe(d[:, :2] / grid.cell_m)
    dz = _safe(d[:, 2])
    (x0, x1), (y0, y1) = _slab(p[:, 0], q[:, 0], 0.0, nx), _slab(p[:, 1], q[:, 1], 0.0, ny)
    z0, z1 = _slab(o[:, 2], dz, *grid.z_range)
    box_out = torch.minimum(x1, y1)
    t0 = torch.clamp(torch.maximum(torch.maximum(x0, y0), z0), min=0.0)
    t1 = torch.minimum(box_out, z1)
    # the major axis, and the ray in (u, v): u along it, v across
    major_x = q[:, 0].abs() >= q[:, 1].abs()
    u0, v0 = torch.where(major_x, p[:, 0], p[:, 1]), torch.where(major_x, p[:, 1], p[:, 0])
    du, dv = torch.where(major_x, q[:, 0], q[:, 1]), torch.where(major_x, q[:, 1], q[:, 0])
    nu = torch.where(major_x, nx, ny)
    nv = torch.where(major_x, ny, nx)
    step = torch.where(du >= 0, 1.0, -1.0)
    k0 = _cell(u0 + t0 * du, du, entering=True)
    m = torch.arange(columns, device=o.device, dtype=o.dtype)
    k = k0[:, None] + step[:, None] * m  # [P, M] column indices in the order the ray meets them
    u_in, u_out = k + (step[:, None] < 0), k + (step[:, None] > 0)
    t_in = torch.maximum(t0[:, None], (u_in - u0[:, None]) / du[:, None])
    t_out = torch.minimum(t1[:, None], (u_out - u0[:, None]) / du[:, None])
    col_ok = (k >= 0) & (k < nu[:, None]) & (t_in <= t_out)
    r_a = _cell(v0[:, None] + t_in * dv[:, None], dv[:, None], entering=True)
    r_b = _cell(v0[:, None] + t_out * dv[:, None], dv[:, None], entering=False)
    r_a = torch.minimum(torch.maximum(r_a, torch.zeros_like(r_a)), nv[:, None] - 1.0)
    r_b = torch.minimum(torch.maximum(r_b, torch.zeros_like(r_b)), nv[:, None] - 1.0)
    t_c = (torch.maximum(r_a, r_b) - v0[:, None]) / _safe(dv)[:, None]
    t_c = torch.minimum(torch.maximum(t_c, t_in), t_out)
    two = r_a != r_b
    # the pairs [P, 2M]: per column its first cell, then its second
    ta = torch.stack([t_in, torch.where(two, t_c, t_in)], -1).flatten(1)
    tb = torch.stack([torch.where(two, t_c, t_out), t_out], -1).flatten(1)
    rows = torch.stack([r_a, r_b], -1).flatten(1)
    cols = k.repeat_interleave(2, dim=1)
    real = (col_ok[..., None] & torch.stack([torch.ones_like(two), two], -1)).flatten(1)
    kc = cols.clamp(0, None).long()
    rc = rows.long()
    mx = major_x[:, None]
    flat = torch.where(mx, kc * ny + rc, rc * ny + kc).clamp(0, nx * ny - 1)
    zlo, zhi = grid.zlo[flat], grid.zhi[flat]
    tz0 = torch.minimum((zlo - o[:, 2:3]) / dz[:, None], (zhi - o[:, 2:3]) / dz[:, None])
    tz1 = torch.maximum((zlo - o[:, 2:3]) / dz[:, None], (zhi - o[:, 2:3]) / dz[:, None])
    a = torch.maximum(ta, tz0)
    b = torch.minimum(tb, tz1)
    inside = real & grid.present[flat] & (a <= b)
    inf = torch.full_like(a, math.inf)
    enter = torch.where(inside, a, inf).amin(1)
    # from inside a block: the first pair (of positive length) that the blocks do not fill ends it
    eps = 1e-6 * (1.0 + tb.abs())
    full = inside & (a <= ta + eps) & (b >= tb - eps)
    gap = real & (tb > ta + eps) & ~full
    first = gap.to(torch.uint8).argmax(1, keepdim=True)
    ends = torch.where(inside & (a <= ta + eps), b, ta).gather(1, first)[:, 0]
    # filled to the end: out through the grid's side (a wall), or through its heights (none: the floor)
    leave = torch.where(gap.any(1), ends, torch.where(box_out <= z1, t1, math.inf))
    ix = torch.floor(p[:, 0]).clamp(0, nx - 1).long()
    iy = torch.floor(p[:, 1]).clamp(0, ny - 1).long()
    c0 = ix * ny + iy
    in_grid = (p[:, 0] >= 0) & (p[:, 0] < nx) & (p[:, 1] >= 0) & (p[:, 1] < ny)
    start_inside = in_grid & grid.present[c0] & (grid.zlo[c0] <= o[:, 2]) & (o[:, 2] <= grid.zhi[c0])
    out = torch.where(start_inside, leave, enter)
    return torch.where(t0 <= t1, out, torch.full_like(out, math.inf))


class Surroundings(nn.Module):
    """The surface model as the proxy's shape: ``hit`` gives where a ray meets it (see the module
    docstring for the coordinates)."""

    def __init__(
        self,
        lo: Tensor,
        hi: Tensor,
        reach_m: float,
        cell_m: float,
        points: np.ndarray | None = None,
        margin_m: float = 1.0,
    ):
        """Around the facade with bounds [``lo``, ``hi``] (m), out to ``reach_m`` from its centre in cells of
        ``cell_m``. With ``points`` [N, 3] (the coarse point cloud, m) the heights come from them; without,
        they are 0 (ground only) until a saved state is loaded."""
        super().__init__()
        if not (reach_m > 0 and cell_m > 0):
            raise ValueError(
                f"the surroundings need a positive reach and cell size, got {reach_m} m, {cell_m} m"
            )
        cells = max(2, int(math.ceil(2.0 * reach_m / cell_m)))
        if cells > MAX_CELLS:
            raise ValueError(
                f"the surroundings' surface model would have {cells} x {cells} cells ({reach_m} m out in "
                f"{cell_m} m cells); at most {MAX_CELLS} across: use larger cells"
            )
        lo_ = lo.detach().double().cpu().numpy()
        hi_ = hi.detach().double().cpu().numpy()
        if points is None:
            heights = np.zeros((2, cells, cells))
        else:
            heights = surface_heights(points, lo_, hi_, cells, cell_m, margin_m)
        self.eye_xy = (0.5 * (lo_[:2] + hi_[:2])).tolist()
        self.ground_z = float(lo_[2])
        self.cell_m = float(cell_m)
        self.reach_m = float(reach_m)
        self.register_buffer("heights", torch.as_tensor(heights, dtype=torch.float32))
        self._describe()

    def _load_from_state_dict(self, *args, **kwargs):
        super()._load_from_state_dict(*args, **kwargs)
        self._describe()  # new heights

    def _describe(self) -> None:
        """What the casts need to know of the heights on the host, read once when they change (never in a
        cast, which would wait for the device): the cells with blocks (their bounding box of cells), the
        heights they span and the highest elevation (``top``)."""
        h = self.heights.detach().cpu().double().numpy()
        bottom, top = h
        i, j = np.nonzero(top > 0)
        n = top.shape[0]
        self._box = (int(i.min()), int(i.max()) + 1, int(j.min()), int(j.max()) + 1) if len(i) else None
        self._z_range = (self.ground_z, self.ground_z + float(top.max()))
        # the cell's nearest point to the eye, horizontally
        rel = (np.stack([i, j], 1) - 0.5 * n + 0.5) * self.cell_m
        near = np.maximum(np.linalg.norm(rel, axis=1) - 0.71 * self.cell_m, self.cell_m)
        elevation = float(np.arctan2(top[i, j], near).max()) if len(i) else 0.0
        self._top = float(np.clip(elevation, math.radians(1.0), MAX_ELEVATION))
        self._caster = None  # the mesh of other heights

    @property
    def top(self) -> float:
        """The highest elevation of the surface seen from the eye (rad; at least 1 deg, at most
        ``MAX_ELEVATION``): the wall maps' object half spans 0 to this."""
        return self._top

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The surface model's vertices [V, 3] and triangles [T, 3] (m, training frame)."""
        h = self.heights.cpu().double().numpy()
        return surface_mesh(h, self.cell_m, np.array(self.eye_xy), self.ground_z)

    def blocks(self, dtype: torch.dtype = torch.float32) -> BlockGrid | None:
        """The blocks on the heights' device in ``dtype``, over the bounding box of the cells that have one
        (None: no cell has)."""
        if self._box is None:
            return None
        i0, i1, j0, j1 = self._box
        bottom, top = self.heights[:, i0:i1, j0:j1].to(dtype)
        half = 0.5 * self.heights.shape[1]
        corner = (self.eye_xy[0] + (i0 - half) * self.cell_m, self.eye_xy[1] + (j0 - half) * self.cell_m)
        return BlockGrid(
            zlo=torch.where(bottom > 0, self.ground_z + bottom, -math.inf).flatten(),
            zhi=(self.ground_z + top).flatten(),
            present=(top > 0).flatten(),
            nx=i1 - i0,
            ny=j1 - j0,
            corner=corner,
            cell_m=self.cell_m,
            z_range=self._z_range,
        )

    @torch.no_grad()
    def cast(self, o: Tensor, d: Tensor) -> Tensor:
        """Distance [P] along unit ``d`` [P, 3] from ``o`` [P, 3] (m) to the first hit on the surface model's
        blocks (inf: none; the ground is not part of it), on the rays' device. On the CPU through open3d
        (Embree walks a tree of the blocks' faces: about 50 times faster there than ``cast_torch``'s walk
        of every cell on the way, benchmarks/RESULTS.md) where it is installed; elsewhere ``cast_torch``."""
        caster = self._mesh_caster() if o.device.type == "cpu" else None
        if caster is None:
            return self.cast_torch(o, d)
        t = caster.cast(o.detach().numpy(), d.detach().numpy()).t
        return torch.as_tensor(t, dtype=o.dtype)

    def _mesh_caster(self):
        """open3d's caster of the blocks' mesh (``surface_mesh``), made once per heights; None where open3d
        is not importable (a machine with torch alone)."""
        if self._caster is None:
            try:
                from facade_pipeline.geometry.raycast import MeshRaycaster
            except ImportError:
                self._caster = False
            else:
                self._caster = MeshRaycaster(*self.mesh())
        return self._caster or None

    @torch.no_grad()
    def cast_torch(self, o: Tensor, d: Tensor) -> Tensor:
        """``cast`` in torch on the rays' device (``cast_blocks``), ``CAST_CHUNK_PAIRS`` (ray, cell) pairs at
        a time: no copy to the host, so a training step on a GPU never waits for one."""
        grid = self.blocks(o.dtype)
        if grid is None or len(o) == 0:
            return torch.full_like(o[:, 0], math.inf)
        # every column a ray can cross; on the CPU, where reading a value costs no wait, the most any of
        # these rays crosses (far fewer for rays that leave the blocks' heights soon)
        columns = max(grid.nx, grid.ny) + 1
        if o.device.type == "cpu":
            columns = min(columns, _columns_needed(o, d, grid))
        chunk = max(1, CAST_CHUNK_PAIRS // (2 * columns))
        return torch.cat([cast_blocks(o[a : a + chunk], d[a : a + chunk], grid, columns)
                          for a in range(0, len(o), chunk)])  # fmt: skip

    @torch.no_grad()
    def hit(self, x: Tensor, w: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Rays x + t w (t > 0; x [P, 3] m, w [P, 3] unit) -> ``on_floor`` [P] bool, floor coordinates
        [P, 2] in [-1, 1] and wall coordinates [P, 2] in [-1, 1] (lower half: the surface model, upper half:
        the sky). Finite for any input; on the rays' device."""
        x, w = x.detach(), w.detach()
        ok = torch.isfinite(x).all(1) & torch.isfinite(w).all(1) & (w.norm(dim=1) > 0.5)
        # (0, 0, 1) made by a kernel: a tensor from host values, or an element set from a Python number, is a
        # copy from the host, which waits for the device
        up = (torch.arange(3, device=w.device) == 2).to(w.dtype)[None]
        w = torch.where(ok[:, None], w, up)
        o = torch.where(ok[:, None], x, torch.zeros_like(x)) + RAY_OFFSET_CELLS * self.cell_m * w
        t_obj = self.cast(o, w)
        wz = w[:, 2]
        down = wz < -_EPS
        height = torch.clamp(o[:, 2] - self.ground_z, min=0.0)
        t_floor = torch.where(down, height / torch.where(down, -wz, torch.ones_like(wz)), math.inf)
        on_floor = down & (t_floor < t_obj)
        on_obj = torch.isfinite(t_obj) & ~on_floor
        ex, ey = self.eye_xy
        floor_xy = o[:, :2] + torch.where(on_floor, t_floor, 0.0)[:, None] * w[:, :2]
        floor_xy = torch.stack([floor_xy[:, 0] - ex, floor_xy[:, 1] - ey], 1)
        floor_uv = torch.clamp(floor_xy / self.reach_m, -1.0, 1.0)
        p = o + torch.where(on_obj, t_obj, 0.0)[:, None] * w
        rel = torch.stack([p[:, 0] - ex, p[:, 1] - ey], 1)
        obj_az = torch.atan2(rel[:, 1], rel[:, 0])
        obj_el = torch.atan2(p[:, 2] - self.ground_z, rel.norm(dim=1))
        obj_v = -1.0 + torch.clamp(obj_el / self.top, 0.0, 1.0)
        flat = w[:, :2].abs().sum(1) < _EPS
        sky_az = torch.atan2(w[:, 1], w[:, 0] + torch.where(flat, _EPS, 0.0))
        up_z = torch.clamp(wz, 0.0, 1.0)
        # asin as atan2: the same angle, and torch's CPU asin is many times slower than its atan2
        sky_v = torch.atan2(up_z, torch.sqrt(torch.clamp(1.0 - up_z * up_z, min=0.0))) / (0.5 * math.pi)
        wall_u = torch.where(on_obj, obj_az, sky_az) / math.pi
        wall_uv = torch.stack([wall_u, torch.where(on_obj, obj_v, sky_v)], dim=1)
        return on_floor, torch.nan_to_num(floor_uv), torch.clamp(torch.nan_to_num(wall_uv), -1.0, 1.0)


def _columns_needed(o: Tensor, d: Tensor, grid: BlockGrid) -> int:
    """The most columns of their major axis that rays ``o`` + t ``d`` cross inside ``grid`` and its heights
    (reads the rays' values: for the CPU)."""
    p = torch.stack([(o[:, 0] - grid.corner[0]) / grid.cell_m, (o[:, 1] - grid.corner[1]) / grid.cell_m], -1)
    q = _safe(d[:, :2] / grid.cell_m)
    (x0, x1), (y0, y1) = _slab(p[:, 0], q[:, 0], 0.0, grid.nx), _slab(p[:, 1], q[:, 1], 0.0, grid.ny)
    z0, z1 = _slab(o[:, 2], _safe(d[:, 2]), *grid.z_range)
    t0 = torch.clamp(torch.maximum(torch.maximum(x0, y0), z0), min=0.0)
    t1 = torch.minimum(torch.minimum(x1, y1), z1)
    span = torch.where(t1 >= t0, (t1 - t0) * q.abs().amax(1), 0.0)
    return int(torch.nan_to_num(span, posinf=0.0).max()) + 2
