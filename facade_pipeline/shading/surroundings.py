"""The surroundings as a surface model from the coarse point cloud: what a reflected ray meets in front of
the facade.

A proxy that put everything above the ground on one cylinder wall, twice the facade's half-diagonal away,
smeared the surroundings that stand at other distances (on demo, trees 16-32 m from the facade and
buildings 50-75 m): rays from different points of the facade that meet the same tree read different texels
of that wall. Photogrammetry reconstructs the surroundings with the facade: its coarse point cloud holds
them. Here they become a surface model (a DSM, as photogrammetry software exports one) that the reflected
rays of the environment proxy (``shading.proxy``) are cast against:

- points off the facade (beyond its bounds by ``margin_m``, horizontally) and above the ground (by
  ``MIN_HEIGHT_M``) are binned into square cells of ``cell_m`` around the facade's centre, out to
  ``reach_m``; a cell's top is its highest point's height, and a grey-level closing over 3 x 3 cells fills
  the one-cell holes that sparse points leave in roofs and crowns; its bottom is its lowest point's, or the
  ground where that is within ``GROUND_SNAP_M`` of it (walls and trunks);
- each cell with something in it is a block from its bottom to its top, with walls where a neighbour does
  not cover that span: a building is a box, a tree's crown a lump that rays can pass under.

A reflected ray from X_r along w_r ends at its first hit on the blocks or on the ground plane; meeting
neither, it goes to the sky. On the proxy's wall maps a block hit is read at its azimuth and elevation as
seen from the eye, the facade's centre on the ground (the lower half of the maps, elevations 0 to the
highest block's, ``top``), and the sky at the ray's own azimuth and elevation (the upper half). The floor
maps are read where the ray meets the ground, out to ``reach_m`` and clamped beyond.

The heights are a buffer of the module, so they are saved with the proxy's weights (``reflection.pt``,
checkpoints) and a loaded model casts against the same surface without the points. The casts run on the
host through open3d (``geometry.raycast``), without gradient: a hit is a step function of the ray, and the
features learn from every ray that reads them.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

#: Points this far above the ground or less are ground; the proxy's floor stands for them (m).
MIN_HEIGHT_M = 0.5
#: A cell whose lowest point is at most this high stands on the ground (walls, trunks) (m).
GROUND_SNAP_M = 1.5
#: Rays start this far along w_r from X_r (m): off the facade, whatever the mesh's numerical noise.
RAY_OFFSET_M = 0.05
#: The elevation of the highest point is at most this (rad).
MAX_ELEVATION = math.radians(60.0)
#: At most this many cells across the surface model (a 4096 x 4096 grid of two heights is 128 MiB).
MAX_CELLS = 4096
#: Below this, a ray's vertical component counts as zero: it never meets the ground.
_EPS = 1e-6


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
    q = p[off & (p[:, 2] > lo[2] + MIN_HEIGHT_M)]
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
    # what starts this low stands on the ground (walls, trunks: the points stop MIN_HEIGHT_M above it)
    bottom = np.where(np.isfinite(bottom) & (bottom > GROUND_SNAP_M), bottom, 0.0)
    bottom = np.where(top > 0, np.minimum(bottom, top), 0.0)
    return np.stack([bottom, top])


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
        self._caster = None
        self._top: float | None = None

    def _load_from_state_dict(self, *args, **kwargs):
        self._caster, self._top = None, None  # new heights: a new mesh
        super()._load_from_state_dict(*args, **kwargs)

    @property
    def top(self) -> float:
        """The highest elevation of the surface seen from the eye (rad; at least 1 deg, at most
        ``MAX_ELEVATION``): the wall maps' object half spans 0 to this."""
        if self._top is None:
            h = self.heights[1].cpu().double().numpy()
            i, j = np.nonzero(h > 0)
            n = h.shape[0]
            # the cell's nearest point to the eye, horizontally
            rel = (np.stack([i, j], 1) - 0.5 * n + 0.5) * self.cell_m
            near = np.maximum(np.linalg.norm(rel, axis=1) - 0.71 * self.cell_m, self.cell_m)
            top = float(np.arctan2(h[i, j], near).max()) if len(i) else 0.0
            self._top = float(np.clip(top, math.radians(1.0), MAX_ELEVATION))
        return self._top

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The surface model's vertices [V, 3] and triangles [T, 3] (m, training frame)."""
        h = self.heights.cpu().double().numpy()
        return surface_mesh(h, self.cell_m, np.array(self.eye_xy), self.ground_z)

    def _cast(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        if self._caster is None:
            try:
                from facade_pipeline.geometry.raycast import MeshRaycaster
            except ImportError as e:
                raise ImportError(
                    f"the environment proxy's surroundings cast rays with open3d, which is not importable "
                    f"({e}); install it or train with [train_gs.reflection.proxy] channels = 0"
                ) from e
            self._caster = MeshRaycaster(*self.mesh())
        return self._caster.cast(o, d).t.astype(np.float64)

    @torch.no_grad()
    def hit(self, x: Tensor, w: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Rays x + t w (t > 0; x [P, 3] m, w [P, 3] unit) -> ``on_floor`` [P] bool, floor coordinates
        [P, 2] in [-1, 1] and wall coordinates [P, 2] in [-1, 1] (lower half: the surface model, upper half:
        the sky). Finite for any input."""
        xn = x.detach().double().cpu().numpy()
        wn = w.detach().double().cpu().numpy()
        ok = np.isfinite(xn).all(1) & np.isfinite(wn).all(1) & (np.linalg.norm(wn, axis=1) > 0.5)
        wn = np.where(ok[:, None], wn, [0.0, 0.0, 1.0])
        o = np.where(ok[:, None], xn, 0.0) + RAY_OFFSET_M * wn
        t_obj = self._cast(o, wn) if len(o) else np.zeros(0)
        down = wn[:, 2] < -_EPS
        height = np.maximum(o[:, 2] - self.ground_z, 0.0)
        t_floor = np.where(down, height / np.where(down, -wn[:, 2], 1.0), np.inf)
        on_floor = down & (t_floor < t_obj)
        on_obj = np.isfinite(t_obj) & ~on_floor
        eye = np.array(self.eye_xy)
        floor_xy = o[:, :2] + np.where(on_floor, t_floor, 0.0)[:, None] * wn[:, :2] - eye
        floor_uv = np.clip(floor_xy / self.reach_m, -1.0, 1.0)
        p = o + np.where(on_obj, t_obj, 0.0)[:, None] * wn
        rel = p[:, :2] - eye
        top = self.top
        obj_az = np.arctan2(rel[:, 1], rel[:, 0])
        obj_el = np.arctan2(p[:, 2] - self.ground_z, np.linalg.norm(rel, axis=1))
        obj_v = -1.0 + np.clip(obj_el / top, 0.0, 1.0)
        sky_az = np.arctan2(wn[:, 1], wn[:, 0] + np.where(np.abs(wn[:, :2]).sum(1) < _EPS, _EPS, 0.0))
        sky_v = np.arcsin(np.clip(wn[:, 2], 0.0, 1.0)) / (0.5 * math.pi)
        wall_u = np.where(on_obj, obj_az, sky_az) / math.pi
        wall_uv = np.stack([wall_u, np.where(on_obj, obj_v, sky_v)], axis=1)
        as_t = lambda a, dtype: torch.as_tensor(np.nan_to_num(a), dtype=dtype, device=x.device)  # noqa: E731
        return as_t(on_floor, torch.bool), as_t(floor_uv, x.dtype), as_t(np.clip(wall_uv, -1.0, 1.0), x.dtype)
