"""What a held-out view's appearance can be predicted from, without training: the training photos warped
into the held-out view through a plane, scored as the evaluation scores a model (PSNR over the facade and
the glass masks), as imported and aligned.

    .venv/bin/python benchmarks/bench_view_prediction.py --bundle gcw.npz --building gcw_dev

The plane is the corrected mesh's glass (a plane fitted to its glass triangles) moved d metres behind
itself, away from the cameras. At d = 0 the warp carries what lies on the glass (the frames, dirt, the
glass's own colour); at d > 0 what stands d behind it: an interior, or a reflection, since a plane
mirror's image of a point d in front of the glass behaves as a point d behind it; d = inf carries the
directions alone (a distant scene seen through, or mirrored in, the glass). The last rows take two layers:
the pixels off the view's glass mask from d = 0, those on it from d = inf. Each held-out view is predicted
from its nearest training photo (camera centres), from the best single training photo (an oracle: the one
with the highest glass PSNR at that d) and from the mean of every training photo that sees the pixel (what
a layer at that depth, one colour per point, learns at best from these views). A training photo is brought
to the model's exposure by its estimated gain (the bundle's), as training does; pixels the warp leaves
uncovered take the photo's mean facade colour. *Aligned*: the held-out view's pose and a gain per colour
channel fitted to the nearest photo's prediction at that d first (``training.corrections.align_view`` with
the building's ``[evaluate.align]``, as the evaluate stage aligns a view to a model), then every source's
prediction made from that pose with that gain.

``--panes`` makes another table instead: each pane of the corrected mesh's glass as its own plane mirror of
a scene d in front of the glass, tilted as the training views alone prefer (``fit_tilts``), against the
glass plane; the held-out view from its nearest training photo, aligned to each prediction.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import machine, record_results  # noqa: E402

from facade_pipeline.config import load_building_config  # noqa: E402
from facade_pipeline.evaluation.image_eval import region_masks  # noqa: E402
from facade_pipeline.evaluation.metrics import psnr  # noqa: E402
from facade_pipeline.training.corrections import align_view  # noqa: E402
from facade_pipeline.training.data import (  # noqa: E402
    TrainData,
    downscale_view,
    load_bundle,
    pixel_budget_factor,
)
from facade_pipeline.training.params import AlignParams  # noqa: E402

#: float32, as the evaluation renders
DTYPE = torch.float32
#: depths behind the glass (m); inf: directions only
DEPTHS = (0.0, 0.03, 0.3, 3.0, math.inf)
#: two layers: the frames (off the glass mask) from the glass plane, the glass from directions alone
TWO_LAYERS = (0.0, math.inf)
#: distances (m) in front of the glass of the scene the panes mirror (``--panes``); inf: a distant scene
MIRROR_DEPTHS = (0.1, 0.3, 1.0, 3.0, math.inf)
#: offsets of a pane's tilt searched on the training views (deg, about each of two axes in the glass plane):
#: a coarse grid around the current tilt, then a fine one around the coarse best
TILT_COARSE_DEG = tuple(np.arange(-6.0, 6.01, 2.0))
TILT_FINE_DEG = tuple(np.arange(-0.5, 0.51, 0.25))
#: the tilts are fitted on every this-many-th row and column of the training views
FIT_STRIDE = 4
#: a pane's neighbours: the panes whose centres lie within this many times its nearest neighbour's distance
#: (its row, its column and the diagonals of a grid); a view near another sees its image in one of them
NEIGHBOUR_REACH = 1.9
#: sweeps of the search over the panes (the later ones on the fine grid alone)
TILT_SWEEPS = 2


def _depth(depth) -> str:
    return f"{depth[0]:g} off the glass, {depth[1]:g} on it" if isinstance(depth, tuple) else f"{depth:g}"


def glass_plane(data: TrainData) -> tuple[np.ndarray, float]:
    """The plane n . x = c fitted to the vertices of the corrected mesh's glass triangles (least squares), n
    pointing away from the cameras."""
    init = data.init
    tri = init.mesh_triangles if init.mesh_glass is None else init.mesh_triangles[init.mesh_glass]
    p = init.mesh_vertices[np.unique(tri)]
    mean = p.mean(axis=0)
    n = np.linalg.svd(p - mean, full_matrices=False)[2][-1]
    cams = np.array([v.camera.center for v in data.views])
    if float(((cams - mean) @ n).mean()) > 0:
        n = -n
    return n, float(n @ mean)


class Warp:
    """Training photo ``src`` seen from a camera through the plane n . x = c + d (or along directions,
    d = inf), differentiable in the camera's pose (for ``align_view``)."""

    def __init__(self, data: TrainData, src: int, plane: tuple[np.ndarray, float], depth: float):
        v = data.views[src]
        gain = 1.0 if data.exposure is None else np.exp(data.exposure.log_gain[src])
        self.image = torch.as_tensor(v.image / gain, dtype=DTYPE).permute(2, 0, 1)[None]
        self.K = torch.as_tensor(v.camera.K, dtype=DTYPE)
        self.T = torch.as_tensor(v.camera.cam_from_world, dtype=DTYPE)
        self.size = (v.camera.width, v.camera.height)
        self.n = torch.as_tensor(plane[0], dtype=DTYPE)
        self.c = plane[1] + (0.0 if math.isinf(depth) else depth)
        self.inf = math.isinf(depth)
        m = v.facade_mask
        facade = self.image[0].permute(1, 2, 0).numpy()[m]
        self.fill = torch.as_tensor(facade.mean(0) if m.any() else [0.5] * 3)

    def __call__(self, K: torch.Tensor, cam_from_world: torch.Tensor, hw: tuple[int, int]):
        """[H, W, 3] the prediction and [H, W] bool where the source photo covers it."""
        h, w = hw
        ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
        pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).to(DTYPE).reshape(-1, 3)
        R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
        d = pix @ torch.linalg.inv(K).T @ R  # world directions (rows: R^T d_cam)
        if self.inf:
            xc = d @ self.T[:3, :3].T
        else:
            o = -R.T @ t
            s = (self.c - self.n @ o) / (d @ self.n)
            x = o + s[:, None] * d
            xc = x @ self.T[:3, :3].T + self.T[:3, 3]
            xc = torch.where((s > 0)[:, None], xc, torch.full_like(xc, -1.0))
        z = xc[:, 2]
        uv = (xc @ self.K.T)[:, :2] / z.clamp_min(1e-9)[:, None]
        sw, sh = self.size
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= sw) & (uv[:, 1] >= 0) & (uv[:, 1] <= sh)
        grid = torch.stack([2 * uv[:, 0] / sw - 1, 2 * uv[:, 1] / sh - 1], -1).reshape(1, h, w, 2)
        grid = torch.where(ok.reshape(1, h, w, 1), grid, torch.zeros_like(grid))
        rgb = torch.nn.functional.grid_sample(self.image, grid, align_corners=False)[0].permute(1, 2, 0)
        ok = ok.reshape(h, w)
        return torch.where(ok[..., None], rgb, self.fill), ok


def predict(warps: list[Warp], K: torch.Tensor, cam_from_world: torch.Tensor, hw) -> torch.Tensor:
    """The mean over ``warps`` of the photos that cover each pixel (one photo: its warp)."""
    if len(warps) == 1:
        return warps[0](K, cam_from_world, hw)[0]
    acc = torch.zeros(*hw, 3, dtype=DTYPE)
    cnt = torch.zeros(*hw, 1, dtype=DTYPE)
    for wp in warps:
        rgb, ok = wp(K, cam_from_world, hw)
        acc = acc + rgb * ok[..., None]
        cnt = cnt + ok[..., None]
    return torch.where(cnt > 0, acc / cnt.clamp_min(1), warps[0].fill)


def rays(K: torch.Tensor, cam_from_world: torch.Tensor, hw) -> tuple[torch.Tensor, torch.Tensor]:
    """[H*W, 3] origin and (unnormalised) world direction of each pixel centre's ray, row-major."""
    h, w = hw
    ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).to(DTYPE).reshape(-1, 3)
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    d = pix @ torch.linalg.inv(K).T @ R
    return (-R.T @ t).expand_as(d), d


class Panes:
    """The corrected mesh's glass panes (groups of glass triangles that share vertices) as plane mirrors: pane
    k is the plane through its vertices' mean whose normal is the glass plane's tilted by (a_k, b_k) degrees
    about two axes in the glass plane (``u`` and ``v``). Which pane a ray meets is the mesh's (its triangles,
    untilted): a tilt of a few degrees moves a pane's outline by a fraction of its frame bar."""

    def __init__(self, data: TrainData, plane: tuple[np.ndarray, float]):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        init = data.init
        tri = init.mesh_triangles if init.mesh_glass is None else init.mesh_triangles[init.mesh_glass]
        rows = np.repeat(np.arange(len(tri)), 3)
        inc = coo_matrix(
            (np.ones(rows.size), (rows, tri.ravel())), (len(tri), len(init.mesh_vertices))
        ).tocsr()
        count, pane_of_tri = connected_components(inc @ inc.T, directed=False)
        self.count = int(count)
        self.tris = torch.as_tensor(init.mesh_vertices[tri], dtype=DTYPE)  # [T, 3, 3]
        self.pane_of_tri = torch.as_tensor(pane_of_tri, dtype=torch.long)
        n = np.asarray(plane[0], np.float64)
        e = np.eye(3)[int(np.argmin(np.abs(n)))]
        u = e - (e @ n) * n
        u /= np.linalg.norm(u)
        self.n, self.c = torch.as_tensor(n, dtype=DTYPE), float(plane[1])
        self.u, self.v = torch.as_tensor(u, dtype=DTYPE), torch.as_tensor(np.cross(n, u), dtype=DTYPE)
        verts = [init.mesh_vertices[np.unique(tri[pane_of_tri == k])] for k in range(self.count)]
        self.centre = torch.as_tensor(np.array([p.mean(0) for p in verts]), dtype=DTYPE)
        own = []
        for p in verts:  # each pane's own plane, fitted to its vertices, as a tilt from the glass plane
            m = np.linalg.svd(p - p.mean(0), full_matrices=False)[2][-1]
            m = m if m @ n > 0 else -m
            own.append(np.degrees(np.arctan2([m @ u, m @ np.cross(n, u)], m @ n)))
        #: [P, 2] the tilt (deg) of each pane's own vertices from the glass plane
        self.own_tilt = np.array(own)
        c = self.centre.numpy()
        dist = np.linalg.norm(c[:, None] - c[None], axis=-1)
        reach = NEIGHBOUR_REACH * np.sort(dist, axis=1)[:, 1:2] if self.count > 1 else np.zeros((1, 1))
        near = [
            [k, *(j for j in np.argsort(dist[k]) if j != k and dist[k, j] <= reach[k, 0])]
            for k in range(self.count)
        ]
        #: [P, M] each pane and then its neighbours (-1: none), the panes a nearby view can see its image in
        self.neighbours = torch.full((self.count, max(map(len, near))), -1, dtype=torch.long)
        for k, row in enumerate(near):
            self.neighbours[k, : len(row)] = torch.as_tensor(row)

    def normals(self, tilt_deg) -> torch.Tensor:
        """[P, 3] unit normals of the panes tilted by ``tilt_deg`` [P, 2] (deg about ``u`` and ``v``)."""
        t = torch.tan(torch.deg2rad(torch.as_tensor(np.asarray(tilt_deg), dtype=DTYPE)))
        n = self.n + t[:, :1] * self.u + t[:, 1:] * self.v
        return n / n.norm(dim=-1, keepdim=True)

    def hit(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """[N] the pane each ray (o, d [N, 3]) meets first (-1: none)."""
        v0, e1, e2 = self.tris[:, 0], self.tris[:, 1] - self.tris[:, 0], self.tris[:, 2] - self.tris[:, 0]
        p = torch.cross(d[:, None], e2[None].expand(len(d), -1, -1), dim=-1)
        det = (p * e1).sum(-1)
        inv = 1.0 / torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
        s = o[:, None] - v0
        a = (s * p).sum(-1) * inv
        q = torch.cross(s, e1[None].expand_as(s), dim=-1)
        b = (d[:, None] * q).sum(-1) * inv
        t = (q * e2).sum(-1) * inv
        ok = (a >= 0) & (b >= 0) & (a + b <= 1) & (t > 0)
        t = torch.where(ok, t, torch.full_like(t, math.inf))
        first = t.argmin(1)
        return torch.where(ok.any(1), self.pane_of_tri[first], -1)


class MirrorWarp:
    """Training photo ``src`` seen from a camera in the panes as plane mirrors of a scene ``depth`` metres in
    front of the glass plane (a plane parallel to it; inf: a distant scene, directions alone). A ray that
    meets pane k is reflected in pane k's plane to the scene point; the source camera sees that point in
    whichever pane j among k and its neighbours mirrors it onto a source pixel that lies on pane j (the point
    mirrored in pane j's plane, projected); where none does, in pane k's plane (one plane mirror). Pixels on
    no pane are the glass plane's (``Warp`` at d = 0): the frames."""

    def __init__(self, data: TrainData, src: int, panes: Panes, plane, depth: float):
        self.flat = Warp(data, src, plane, 0.0)
        self.panes, self.depth = panes, depth
        v = data.views[src]
        self.src_hw = (v.camera.height, v.camera.width)
        o, d = rays(self.flat.K, self.flat.T, self.src_hw)
        self.src_pane = panes.hit(o, d)  # [h * w] the pane each source pixel shows

    def lookup(self, o: torch.Tensor, d: torch.Tensor, k: torch.Tensor, normals: torch.Tensor):
        """[N, 3] colour and [N] bool covered, of rays (o, d) that meet pane ``k`` [N] (all >= 0), the panes'
        normals ``normals`` [P, 3]."""
        pn, cen = normals[k], self.panes.centre[k]
        x = o + (((cen - o) * pn).sum(-1) / (d * pn).sum(-1))[:, None] * d
        r = d - 2 * (d * pn).sum(-1, keepdim=True) * pn
        n, c = self.panes.n, self.panes.c
        T = self.flat.T
        cand = self.panes.neighbours[k]  # [N, M]: pane k first
        nj, cj = normals[cand.clamp_min(0)], self.panes.centre[cand.clamp_min(0)]
        if math.isinf(self.depth):
            front = (r @ n) < 0
            pts = r[:, None] - 2 * (r[:, None] * nj).sum(-1, keepdim=True) * nj  # [N, M, 3] directions
            xc = pts @ T[:3, :3].T
        else:
            t = (c - self.depth - x @ n) / (r @ n)
            front = t > 0
            s = x + t[:, None] * r
            off = ((s[:, None] - cj) * nj).sum(-1)  # [N, M]
            xc = (s[:, None] - 2 * off[..., None] * nj) @ T[:3, :3].T + T[:3, 3]
        z = xc[..., 2]
        uv = (xc @ self.flat.K.T)[..., :2] / z.clamp_min(1e-9)[..., None]
        sh, sw = self.src_hw
        inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < sw) & (uv[..., 1] >= 0) & (uv[..., 1] < sh)
        inside = inside & front[:, None]
        cell = uv.detach().floor().long()
        flat_idx = (cell[..., 1].clamp(0, sh - 1) * sw + cell[..., 0].clamp(0, sw - 1)).reshape(-1)
        shows = self.src_pane[flat_idx].reshape(z.shape)
        agree = inside & (shows == cand) & (cand >= 0)
        j = torch.where(agree.any(1), agree.float().argmax(1), 0)
        rows = torch.arange(len(k))
        uv, ok = uv[rows, j], inside[rows, j]
        grid = torch.stack([2 * uv[:, 0] / sw - 1, 2 * uv[:, 1] / sh - 1], -1)
        grid = torch.where(ok[:, None], grid, torch.zeros_like(grid)).reshape(1, 1, -1, 2)
        # the photo's outermost half pixel: its own colour, not a blend with zeros
        rgb = torch.nn.functional.grid_sample(
            self.flat.image, grid, padding_mode="border", align_corners=False
        )
        rgb = rgb[0, :, 0].T
        return torch.where(ok[:, None], rgb, self.flat.fill), ok

    def __call__(self, normals: torch.Tensor, K: torch.Tensor, cam_from_world: torch.Tensor, hw):
        """[H, W, 3] the prediction (the panes' pixels through the mirrors, the others through the glass
        plane; uncovered pixels the photo's mean facade colour) and [H, W] bool where the photo covers it."""
        rgb, ok = (x.reshape(-1, *x.shape[2:]) for x in self.flat(K, cam_from_world, hw))
        o, d = rays(K, cam_from_world, hw)
        with torch.no_grad():
            k = self.panes.hit(o.detach(), d.detach())
        on = k >= 0
        if bool(on.any()):
            idx = (on.nonzero()[:, 0],)
            mirrored, covered = self.lookup(o[on], d[on], k[on], normals)
            rgb, ok = rgb.index_put(idx, mirrored), ok.index_put(idx, covered)
        return rgb.reshape(*hw, 3), ok.reshape(hw)


def fit_tilts(data: TrainData, panes: Panes, plane, depth: float, log=print):
    """Each pane's tilt (deg, [P, 2]) that best predicts the training views from the training photos through
    the mirrors, and the PSNR over those pixels with no tilt and with the fitted ones. Every training view is
    predicted from its nearest other training photo; the error is the squared error over the view's
    glass-mask pixels (every ``FIT_STRIDE``-th row and column) that meet a pane: a move of one pane's tilt is
    judged over that pane's and its neighbours' pixels (it also moves where theirs are seen in it). A tilt
    common to every pane is nearly free between two nearby views (each sees the same mirror's image, only
    its depth changes), while the panes' tilts against each other decide where one pane's image continues
    in the next: so the search moves one pane at a time (the others held), then every pane together, each
    on a coarse grid around the current tilts and a fine one around its best, then again on the fine grid
    alone. No held-out view is seen."""
    centres = np.array([v.camera.center for v in data.views])
    pairs = []
    for a in data.train_idx:
        b = min(
            (s for s in data.train_idx if s != a),
            key=lambda s: float(np.linalg.norm(centres[s] - centres[a])),
        )
        v = data.views[a]
        hw = (v.camera.height, v.camera.width)
        o, d = rays(
            torch.as_tensor(v.camera.K, dtype=DTYPE),
            torch.as_tensor(v.camera.cam_from_world, dtype=DTYPE),
            hw,
        )
        k = panes.hit(o, d)
        sparse = torch.zeros(hw, dtype=torch.bool)
        sparse[::FIT_STRIDE, ::FIT_STRIDE] = True
        keep = (k >= 0) & torch.as_tensor(v.glass_mask).reshape(-1) & sparse.reshape(-1)
        gain = 1.0 if data.exposure is None else np.exp(data.exposure.log_gain[a])
        target = torch.as_tensor((v.image / gain).reshape(-1, 3), dtype=DTYPE)[keep]
        pairs.append((MirrorWarp(data, b, panes, plane, depth), o[keep], d[keep], k[keep], target))

    def sse(tilt, pane=None) -> tuple[float, int]:
        """over every pixel, or (``pane``) over those of the panes whose images ``pane``'s tilt moves"""
        normals = panes.normals(tilt)
        err, cnt = 0.0, 0
        for warp, o, d, k, target in pairs:
            sel = (
                torch.ones_like(k, dtype=torch.bool)
                if pane is None
                else torch.isin(k, panes.neighbours[pane])
            )
            if bool(sel.any()):
                rgb = warp.lookup(o[sel], d[sel], k[sel], normals)[0].clamp(0, 1)
                err += float(((rgb - target[sel]) ** 2).sum())
                cnt += int(target[sel].numel())
        return err, cnt

    def psnr_of(tilt) -> float:
        e, c = sse(tilt)
        return -10.0 * math.log10(max(e / max(c, 1), 1e-12))

    def move(tilt, pane, grids):
        """``tilt`` with pane ``pane`` (None: every pane together) moved to the best of ``grids``' offsets."""
        for grid in grids:
            offsets = [(da, db) for da in grid for db in grid]
            errs = []
            for off in offsets:
                trial = tilt.copy()
                trial[slice(None) if pane is None else pane] += off
                errs.append(sse(trial, pane)[0])
            tilt = tilt.copy()
            tilt[slice(None) if pane is None else pane] += offsets[int(np.argmin(errs))]
        return tilt

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # thousands of small lookups: threads cost more than they give
    try:
        tilt = np.zeros((panes.count, 2))
        untilted = psnr_of(tilt)
        for sweep in range(TILT_SWEEPS):
            grids = (
                [np.array(TILT_COARSE_DEG), np.array(TILT_FINE_DEG)]
                if sweep == 0
                else [np.array(TILT_FINE_DEG)]
            )
            for p in range(panes.count):
                tilt = move(tilt, p, grids)
                log(
                    f"  d = {depth:g} m, sweep {sweep + 1}/{TILT_SWEEPS}, pane {p + 1}/{panes.count}",
                    flush=True,
                )
            tilt = move(tilt, None, grids)
            log(
                f"  d = {depth:g} m, sweep {sweep + 1}: tilts {np.round(tilt, 2).tolist()} deg, "
                f"training PSNR {psnr_of(tilt):.2f} dB (no tilt {untilted:.2f})",
                flush=True,
            )
        return tilt, untilted, psnr_of(tilt)
    finally:
        torch.set_num_threads(threads)


def score(rgb: np.ndarray, view) -> tuple[float, float]:
    m = region_masks(view.facade_mask, view.glass_mask)
    return psnr(rgb, view.image, m["facade"]), psnr(rgb, view.image, m["glass"])


def predictor(data: TrainData, sources: list[int], plane, depth, glass: np.ndarray):
    """A prediction from ``sources`` at ``depth`` (m; a pair: the first for the pixels off ``glass`` [H, W],
    the second for those on it, two layers), as a function of the camera (K, cam_from_world, (H, W))."""
    near, far = depth if isinstance(depth, tuple) else (depth, depth)
    layers = [[Warp(data, s, plane, d) for s in sources] for d in dict.fromkeys((near, far))]
    on_glass = None if len(layers) == 1 else torch.as_tensor(glass)[..., None]

    def run(K: torch.Tensor, cam_from_world: torch.Tensor, hw) -> torch.Tensor:
        rgb = [predict(w, K, cam_from_world, hw) for w in layers]
        return rgb[0] if len(rgb) == 1 else torch.where(on_glass, rgb[1], rgb[0])

    return run


def measure(data: TrainData, tgt: int, sources: list[int], plane, depth, fitted=None):
    """(facade, glass) PSNR of the held-out view ``tgt`` predicted from ``sources`` at ``depth``
    (``predictor``), from its imported camera or, with ``fitted`` (``align``'s pose and gain), from that."""
    v = data.views[tgt]
    return measure_run(v, predictor(data, sources, plane, depth, v.glass_mask), fitted)


def measure_run(v, run, fitted=None) -> tuple[float, float]:
    """(facade, glass) PSNR of view ``v`` predicted by ``run`` (K, cam_from_world, (H, W)) -> [H, W, 3], from
    its imported camera or, with ``fitted`` (pose and gain), from that."""
    K = torch.as_tensor(v.camera.K, dtype=DTYPE)
    hw = (v.camera.height, v.camera.width)
    if fitted is None:
        rgb = run(K, torch.as_tensor(v.camera.cam_from_world, dtype=DTYPE), hw)
    else:
        rgb = run(K, fitted[0], hw) * fitted[1]
    return score(rgb.clamp(0, 1).detach().numpy(), v)


def align(data: TrainData, tgt: int, source: int, plane, depth, params: AlignParams):
    """The held-out view's pose and gain per channel fitted to its prediction from ``source`` at ``depth``
    (``align_view``, on the view reduced to ``params.max_pixels`` as evaluate fits it)."""
    return align_run(
        data.views[tgt], lambda fit: predictor(data, [source], plane, depth, fit.glass_mask), params
    )


def align_run(v, make_run, params: AlignParams):
    """View ``v``'s pose and gain per channel fitted to the prediction ``make_run(fit)`` makes of ``fit``, the
    view reduced to ``params.max_pixels`` as evaluate fits it (``align_view``)."""
    fit = downscale_view(v, pixel_budget_factor(v.camera.width, v.camera.height, params.max_pixels))
    run = make_run(fit)
    Kf = torch.as_tensor(fit.camera.K, dtype=DTYPE)
    with torch.enable_grad():
        a = align_view(
            lambda cfw: run(Kf, cfw, (fit.camera.height, fit.camera.width)),
            torch.as_tensor(v.camera.cam_from_world, dtype=DTYPE),
            torch.as_tensor(fit.image, dtype=DTYPE),
            torch.as_tensor(fit.facade_mask),
            params,
        )
    return a.cam_from_world.to(DTYPE), a.gain


def pane_mirrors(data: TrainData, plane, depths, align_params: AlignParams) -> list[str]:
    """The table of ``--panes``: each held-out view predicted from its nearest training photo through the
    glass plane (d = 0, the depth table's best) and through the panes as mirrors of a scene at each of
    ``depths``, with no tilt (one plane mirror) and with the tilts ``fit_tilts`` fits on the training
    views."""
    panes = Panes(data, plane)
    centres = np.array([v.camera.center for v in data.views])
    nearest = {
        t: min(data.train_idx, key=lambda s: float(np.linalg.norm(centres[s] - centres[t])))
        for t in data.test_idx
    }

    def angles(tilt) -> np.ndarray:  # [P] each pane's normal from the glass plane's (deg)
        return np.degrees(np.arccos(np.clip((panes.normals(tilt) @ panes.n).numpy(), -1.0, 1.0)))

    def held_out(make_run) -> np.ndarray:  # facade, glass as imported; facade, glass aligned
        vals = []
        for t in data.test_idx:
            v, run = data.views[t], make_run(nearest[t])
            fitted = align_run(v, lambda fit, run=run: run, align_params)
            vals.append((*measure_run(v, run), *measure_run(v, run, fitted)))
        return np.mean(vals, axis=0)

    own = angles(panes.own_tilt)
    own_rel = angles(panes.own_tilt - np.median(panes.own_tilt, axis=0))
    print(
        f"{panes.count} panes; their own vertices' tilt from the glass plane: median {np.median(own):.2f}, "
        f"max {own.max():.2f} deg",
        flush=True,
    )
    rows = []
    f = held_out(lambda s: predictor(data, [s], plane, 0.0, None))
    rows.append(("0 (the glass plane: no mirror)", "-", "-", "-", "-", f))
    print(f"glass plane: facade {f[0]:.2f} / {f[2]:.2f}, glass {f[1]:.2f} / {f[3]:.2f}", flush=True)
    for depth in depths:
        tilt, untilted, fitted = fit_tilts(data, panes, plane, depth)
        rel = angles(tilt - np.median(tilt, axis=0))
        print(f"d = {depth:g} m: tilts (deg about u, v) {np.round(tilt, 2).tolist()}", flush=True)
        for name, tl, train in (
            ("one plane", np.zeros_like(tilt), untilted),
            ("each pane tilted", tilt, fitted),
        ):
            normals = panes.normals(tl)
            warps: dict[int, MirrorWarp] = {}

            def make_run(s, normals=normals, warps=warps, depth=depth):
                warp = warps.setdefault(s, MirrorWarp(data, s, panes, plane, depth))
                return lambda K, cfw, hw: warp(normals, K, cfw, hw)[0]

            f = held_out(make_run)
            a = angles(tl)
            said = "-" if name == "one plane" else f"{np.median(a):.2f} / {a.max():.2f}"
            said_rel = "-" if name == "one plane" else f"{np.median(rel):.2f} / {rel.max():.2f}"
            rows.append((f"{depth:g}", name, f"{train:.2f}", said, said_rel, f))
            print(
                f"d = {depth:g} m, {name}: training {train:.2f}, facade {f[0]:.2f} / {f[2]:.2f}, "
                f"glass {f[1]:.2f} / {f[3]:.2f}",
                flush=True,
            )
    lines = [
        "| scene mirrored, m in front of the glass | panes | training views' glass PSNR dB | tilt from the "
        "glass "
        "plane deg, median / max | tilt against the panes' median, median / max | held-out facade PSNR dB | "
        "held-out glass PSNR dB |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for depth, name, train, a, r, f in rows:
        lines.append(
            f"| {depth} | {name} | {train} | {a} | {r} | {f[0]:.2f} / {f[2]:.2f} | {f[1]:.2f} / {f[3]:.2f} |"
        )
    lines.append(
        f"\nThe {panes.count} panes' own vertices (the corrected mesh) tilt from the glass plane by "
        f"{np.median(own):.2f} / {own.max():.2f} deg (median / max), against their median by "
        f"{np.median(own_rel):.2f} / {own_rel.max():.2f}."
    )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True, help="training data from bench_train.py --save-bundle")
    ap.add_argument("--building", default="gcw_dev", help="whose [evaluate.align] aligns the views")
    ap.add_argument(
        "--depths",
        default=",".join(f"{d:g}" for d in DEPTHS),
        help="comma-separated depths behind the glass (m; inf: directions only); the two layers always",
    )
    ap.add_argument(
        "--panes",
        nargs="?",
        const=",".join(f"{d:g}" for d in MIRROR_DEPTHS),
        help="instead of the depths: the panes as mirrors of a scene at these comma-separated distances in "
        "front of the glass (m; inf: a distant scene), each pane's tilt fitted on the training views",
    )
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    torch.set_grad_enabled(False)
    data = load_bundle(a.bundle)
    align_params = load_building_config(a.building).section("evaluate.align", AlignParams)
    plane = glass_plane(data)
    if a.panes:
        stems = ", ".join(data.views[i].stem for i in data.test_idx)
        table = pane_mirrors(data, plane, [float(x) for x in a.panes.split(",")], align_params)
        head = (
            f"`python benchmarks/bench_view_prediction.py --bundle {Path(a.bundle).name} --building "
            f"{a.building} --panes {a.panes}`: held-out {stems} from the nearest training photo, through "
            "the glass plane or through each pane as a plane mirror of a scene d in front of the glass, the "
            f"panes' tilts fitted on the {len(data.train_idx)} training views alone (each from its nearest "
            "other training photo). PSNR dB as imported / aligned (pose and gain fitted to that "
            "prediction), mean over the held-out views.\n"
        )
        title = "\n## What a held-out view can be predicted from: each pane its own mirror (no training)\n"
        text = "\n".join([title, f"{machine()}\n", head, *table]) + "\n"
        print(text)
        if not a.no_write:
            record_results(text)
        return
    centres = np.array([v.camera.center for v in data.views])
    dist = [float(abs(centres[i] @ plane[0] - plane[1])) for i in data.test_idx]
    rows = []
    for depth in (*(float(x) for x in a.depths.split(",")), TWO_LAYERS):
        res: dict[str, list] = {}
        for t in data.test_idx:
            near = min(data.train_idx, key=lambda s: float(np.linalg.norm(centres[s] - centres[t])))
            singles = {s: measure(data, t, [s], plane, depth) for s in data.train_idx}
            best = max(singles, key=lambda s: singles[s][1])
            # one fit of the view's pose and gain (to the nearest photo's prediction) serves every source:
            # the pose error is the view's, whatever predicts it
            fitted = align(data, t, near, plane, depth, align_params)
            for name, srcs in (("nearest", [near]), ("best", [best]), ("mean", list(data.train_idx))):
                imported = singles[srcs[0]] if len(srcs) == 1 else measure(data, t, srcs, plane, depth)
                res.setdefault(name, []).append((*imported, *measure(data, t, srcs, plane, depth, fitted)))
        for name, vals in res.items():
            f = np.mean(vals, axis=0)
            rows.append((depth, name, f))
            said = f"facade {f[0]:.2f} / {f[2]:.2f}, glass {f[1]:.2f} / {f[3]:.2f}"
            print(f"d = {_depth(depth)} m, {name}: {said}", flush=True)
    stems = ", ".join(data.views[i].stem for i in data.test_idx)
    lines = [
        "\n## What a held-out view can be predicted from (no training)\n",
        f"{machine()}\n",
        f"`python benchmarks/bench_view_prediction.py --bundle {Path(a.bundle).name} "
        f"--building {a.building} --depths {a.depths}`: "
        f"held-out {stems} ({data.views[data.test_idx[0]].camera.width} x "
        f"{data.views[data.test_idx[0]].camera.height} px) from the {len(data.train_idx)} training photos "
        f"warped through the glass plane moved d behind itself (the cameras stand "
        f"{', '.join(f'{x:.3f}' for x in dist)} m in front of it). PSNR dB over the facade and the glass "
        "masks, as imported / aligned (pose and gain fitted to the nearest photo's prediction at that d, "
        "`[evaluate.align]`, and used for every source), mean "
        "over the held-out views. *nearest*: the nearest training photo; *best*: the training photo "
        "with the highest glass PSNR at that d (an oracle); *mean*: the mean of the training photos that see "
        "the pixel.\n",
        "| d behind the glass (m) | source | facade PSNR dB | glass PSNR dB |",
        "| --- | --- | --- | --- |",
    ]
    for depth, name, f in rows:
        lines.append(f"| {_depth(depth)} | {name} | {f[0]:.2f} / {f[2]:.2f} | {f[1]:.2f} / {f[3]:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if not a.no_write:
        record_results(text)


if __name__ == "__main__":
    main()
