"""The panel grid of each facade part and the regularised 3D panels (the paper, section 3.1.2, end):
rows of corners share one height, columns of corners one position along the surface (a ruling on
cylinders). See ``facade_pipeline.panels3d.regularize`` for the steps before. Local frame, metres."""

from __future__ import annotations

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.panels3d.model import Panel, PanelSet, PartSurface
from facade_pipeline.panels3d.params import RegularizeConfig
from facade_pipeline.panels3d.regularize import (
    GHOST,
    OK,
    OUTLIER_MAD_FACTOR,
    STATUS_NAMES,
    CornerRays,
    cast_corners,
    cluster_1d,
    corner_rays,
    fit_surface_robust,
    footprints_of,
    glass_offset,
    group_parts,
    quad_flatness,
    quad_frames,
    robust_inliers,
)

# Constants of the panel grid, relative to a panel's size or in pixels, so they hold at any facade scale;
# no building ever needed other values.
#: two panels belong to one part when their centres are closer than this times the panel size (-):
#: neighbours in a row or column lie about one pitch (a panel and a frame) apart
PART_LINK_FACTOR = 1.6
#: panel centres farther apart than this times the panel size (-) start a new row or column: half a pitch
CLUSTER_GAP_FACTOR = 0.5
#: glass evidence is taken inside panels shrunk about their centre by this factor (0-1), away from frames
FOOTPRINT_SHRINK = 0.8
#: corners of a quad cut by the image border within this (px) of the border are not panel corners and are
#: left out (its other corners count like any other)
BORDER_MARGIN_PX = 1.5


def surface_corners(surface: PartSurface, rays: CornerRays, sel: np.ndarray) -> np.ndarray:
    """Surface coordinates [Q, 4, 3] where the corner rays of quads ``sel`` meet ``surface`` (NaN: never)."""
    o, d = rays.origins[sel].reshape(-1, 3), rays.dirs[sel].reshape(-1, 3)
    t = surface.intersect(o, d)
    p = o + np.where(np.isfinite(t), t, np.nan)[:, None] * d
    return surface.coords(p).reshape(-1, 4, 3)


def assign_parts(
    rays: CornerRays,
    points: np.ndarray,
    status: np.ndarray,
    part: np.ndarray,
    surfaces: list[PartSurface],
    extents: list[np.ndarray],
    ghost_max_m: float,
) -> np.ndarray:
    """Part [Q] of every quad: anchors keep theirs; another quad goes to the part whose surface all its
    rays meet inside the part's extent [4] (s0, s1, z0, z1), preferring the surface its mesh hits lie on
    (then the nearest surface). -1 when no part fits."""
    out = part.copy()
    for q in np.flatnonzero(part < 0):
        best, best_score = -1, np.inf
        for p, (surf, ext) in enumerate(zip(surfaces, extents, strict=True)):
            szh = surface_corners(surf, rays, np.array([q]))[0]
            if not np.isfinite(szh).all():
                continue
            c = szh[:, :2].mean(axis=0)
            if not (ext[0] <= c[0] <= ext[1] and ext[2] <= c[1] <= ext[3]):
                continue
            good = status[q] == OK
            h = np.abs(surf.coords(points[q][good])[:, 2]) if good.any() else np.array([])
            if len(h) and np.median(h) > ghost_max_m:
                continue
            t = surf.intersect(rays.origins[q], rays.dirs[q]).mean()
            score = (np.median(h) if len(h) else ghost_max_m) * 1e6 + t
            if score < best_score:
                best, best_score = p, score
        out[q] = best
    return out


LEFT, BOTTOM = np.array([True, False, False, True]), np.array([True, True, False, False])  # of BL BR TR TL


def panel_size(szh: np.ndarray, ok: np.ndarray) -> tuple[float, float]:
    """Median panel width and height (m) from corner surface coordinates [Q, 4, 3] where the corners of an
    edge are both true corners (``ok`` [Q, 4]): bottom and top edges for the width, the sides for the
    height."""
    w = [szh[ok[:, b] & ok[:, a], b, 0] - szh[ok[:, b] & ok[:, a], a, 0] for a, b in ((0, 1), (3, 2))]
    h = [szh[ok[:, b] & ok[:, a], b, 1] - szh[ok[:, b] & ok[:, a], a, 1] for a, b in ((0, 3), (1, 2))]
    w, h = np.concatenate(w), np.concatenate(h)
    return (float(np.median(w)) if len(w) else np.nan), (float(np.median(h)) if len(h) else np.nan)


def grid_cells(
    szh: np.ndarray, ok: np.ndarray, width: float, height: float, gap_factor: float
) -> tuple[np.ndarray, np.ndarray]:
    """Row and column [Q] of every quad (-1: none) from its true corners only (``ok`` [Q, 4]): each true
    corner, moved half a panel (``width``, ``height``, m) inward, votes for its panel's centre; the votes
    are clustered (gaps over ``gap_factor`` times the panel size) and a quad takes its corners' majority.
    So a panel cut by the image border in one view and seen whole, or cut on the other side, in another
    falls in the same cell."""
    q_idx, k_idx = np.nonzero(ok)
    sc = szh[q_idx, k_idx, 0] + np.where(LEFT[k_idx], 0.5, -0.5) * width
    zc = szh[q_idx, k_idx, 1] + np.where(BOTTOM[k_idx], 0.5, -0.5) * height
    col_of, row_of = cluster_1d(sc, gap_factor * width), cluster_1d(zc, gap_factor * height)
    rows, cols = np.full(len(szh), -1, np.int64), np.full(len(szh), -1, np.int64)
    for q in np.unique(q_idx):
        rows[q] = np.bincount(row_of[q_idx == q]).argmax()
        cols[q] = np.bincount(col_of[q_idx == q]).argmax()
    return rows, cols


def _line_ids(rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[Q, 4] index of the z line (a row's bottom or top) and of the s line (a column's left or right)
    each corner lies on, numbered together (-1: none)."""
    zl = np.where(rows[:, None] >= 0, 2 * rows[:, None] + ~BOTTOM[None], -1)
    sl = np.where(cols[:, None] >= 0, 2 * cols[:, None] + ~LEFT[None], -1)
    return zl, np.where(sl >= 0, sl + int(zl.max()) + 1, -1)


def _linked_groups(lines: np.ndarray, views: np.ndarray, n_views: int) -> np.ndarray:
    """[n_views] group of each view: views linked through a line (``lines`` [M]) both show ([M] view)."""
    parent = np.arange(n_views)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for line in np.unique(lines):
        seen = np.unique(views[lines == line])
        for j in seen[1:]:
            parent[find(int(j))] = find(int(seen[0]))
    return np.array([find(i) for i in range(n_views)])


def view_offsets(
    szh: np.ndarray,
    use: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    views: np.ndarray,
    cam_sz: np.ndarray,
) -> np.ndarray:
    """[Q, 4, 2] the (s, z) offset of the corners lifted from each view, fitted jointly with the grid's
    lines (linear least squares, s and z apart) over the corners ``use`` [Q, 4] of quads [Q, 4, 3] at
    ``rows``, ``cols`` seen in ``views`` [Q], whose cameras stand at surface coordinates ``cam_sz`` [V, 2].

    Every corner of a view is lifted through the view's one pose, and an error of its camera's centre (a
    few centimetres in imported poses) or a small turn moves all of them together: the corners of a line
    are not independent, and without offsets the view that shows a line most often sets it. Views linked
    by the lines they share are only measured against each other, so in each linked group the offsets
    are held to no mean and no trend along the cameras' positions: a pose error is taken to be unbiased
    and unrelated to where its camera stands. A trend would scale the whole grid, which the poses fix,
    and what scales each view's corners about its own camera alike (frames standing proud of the glass,
    an error of the surface's depth) would otherwise pass into it."""
    out = np.zeros(szh.shape[:2] + (2,))
    for axis, lid in zip((1, 0), _line_ids(rows, cols), strict=True):
        q, k = np.nonzero(use & (lid >= 0) & np.isfinite(szh[..., axis]))
        if not len(q):
            continue
        lines, line = np.unique(lid[q, k], return_inverse=True)
        seen, vi = np.unique(views[q], return_inverse=True)
        n = len(lines) + len(seen)
        a = np.zeros((len(q), n))
        a[np.arange(len(q)), line] = 1.0
        a[np.arange(len(q)), len(lines) + vi] = 1.0
        groups = _linked_groups(line, vi, len(seen))
        gauge = []
        for g in np.unique(groups):
            members = np.flatnonzero(groups == g)
            c = cam_sz[seen[members], axis]
            for basis in (np.ones(len(members)), c - c.mean()):
                row = np.zeros(n)
                row[len(lines) + members] = basis
                gauge.append(row)
        prior = np.zeros((len(seen), n))
        prior[:, len(lines) :] = OFFSET_PRIOR_WEIGHT * np.eye(len(seen))
        m = np.concatenate([a, GAUGE_WEIGHT * np.sqrt(len(q)) * np.array(gauge), prior])
        b = np.concatenate([szh[q, k, axis], np.zeros(len(gauge) + len(seen))])
        x, *_ = np.linalg.lstsq(m, b, rcond=None)
        t = np.zeros(int(views.max()) + 1)
        t[seen] = x[len(lines) :]
        out[..., axis] = t[views][:, None]
    return out


#: weight of the prior that keeps a view's offsets (``view_offsets``) near zero, against a corner's unit
#: weight: small, it only settles an offset no corner determines
OFFSET_PRIOR_WEIGHT = 1e-3
#: weight of the offsets' gauge (no mean, no trend) against a corner's, times the root of their count:
#: large, the gauge holds
GAUGE_WEIGHT = 1e3


def _grid_inliers(
    szh: np.ndarray, ok: np.ndarray, rows: np.ndarray, cols: np.ndarray, floor: float
) -> np.ndarray:
    """[Q, 4] whether each corner (of ``ok``) is within the outlier rule of its row's and column's lines."""
    keep = np.ones(ok.shape, bool)
    zl, sl = _line_ids(rows, cols)
    for lid, axis in ((zl, 1), (sl, 0)):
        for line in np.unique(lid[lid >= 0]):
            q, k = np.nonzero((lid == line) & ok & np.isfinite(szh[..., axis]))
            keep[q, k] &= robust_inliers(szh[q, k, axis], OUTLIER_MAD_FACTOR, floor)
    return keep


def grid_lines(
    szh: np.ndarray,
    ok: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    size: tuple[float, float],
    cfg: RegularizeConfig,
    views: np.ndarray | None = None,
    cam_sz: np.ndarray | None = None,
) -> tuple[dict, dict, int]:
    """Robust lines of the grid from the true corners (``ok`` [Q, 4]) of quads [Q, 4, 3] at ``rows``,
    ``cols`` [Q]: {row: (z_bottom, z_top)}, {col: (s_left, s_right)} and the number of corner outliers.
    A line no true corner shows is put one panel ``size`` (width, height, m) from the opposite line (the
    grid's regularity). Given the quads' ``views`` [Q] and the cameras' surface coordinates ``cam_sz``
    [V, 2], each view's offset (``view_offsets``) is taken off its corners first, fitted again without
    the outliers."""
    n_out = 0
    if views is not None and cam_sz is not None:
        use, raw = ok, szh
        for _ in range(3):
            szh = raw.copy()
            szh[..., :2] -= view_offsets(raw, use, rows, cols, views, cam_sz)
            use = ok & _grid_inliers(szh, ok, rows, cols, cfg.outlier_floor_m)

    def line(sel: np.ndarray, corner_mask: np.ndarray, axis: int) -> float:
        nonlocal n_out
        v = szh[sel][:, corner_mask, axis][ok[sel][:, corner_mask]]
        v = v[np.isfinite(v)]
        if not len(v):
            return np.nan
        keep = robust_inliers(v, OUTLIER_MAD_FACTOR, cfg.outlier_floor_m)
        n_out += int((~keep).sum())
        return float(v[keep].mean())

    def pair(sel: np.ndarray, lo_mask: np.ndarray, axis: int, span: float) -> tuple[float, float]:
        lo, hi = line(sel, lo_mask, axis), line(sel, ~lo_mask, axis)
        return (hi - span if np.isnan(lo) else lo), (lo + span if np.isnan(hi) else hi)

    row_lines = {int(r): pair(rows == r, BOTTOM, 1, size[1]) for r in np.unique(rows[rows >= 0])}
    col_lines = {int(c): pair(cols == c, LEFT, 0, size[0]) for c in np.unique(cols[cols >= 0])}
    return row_lines, col_lines, n_out


def part_panels(
    surface: PartSurface,
    part: int,
    szh: np.ndarray,
    ok: np.ndarray,
    views: np.ndarray,
    cfg: RegularizeConfig,
    cam_sz: np.ndarray | None = None,
) -> tuple[list[Panel], int]:
    """The regularised panels of one part from its quads' corner surface coordinates [Q, 4, 3] (h = 0)
    seen in ``views`` [Q] from cameras at surface coordinates ``cam_sz`` [V, 2] (None: no view offsets,
    ``view_offsets``); ``ok`` [Q, 4] marks the true corners (not cut by the image border). Returns the
    panels (rows and columns renumbered from 0, bottom to top and left to right) and the number of corner
    outliers."""
    ok = ok & np.isfinite(szh).all(axis=2)
    size = panel_size(szh, ok)
    if not np.isfinite(size).all() or min(size) <= 0:
        return [], 0
    rows, cols = grid_cells(szh, ok, *size, CLUSTER_GAP_FACTOR)
    row_lines, col_lines, n_out = grid_lines(szh, ok, rows, cols, size, cfg, views, cam_sz)
    cells = sorted({(int(a), int(b)) for a, b in zip(rows, cols, strict=True) if a >= 0 and b >= 0})
    r_num = {r: i for i, r in enumerate(sorted({r for r, _ in cells}))}
    c_num = {c: i for i, c in enumerate(sorted({c for _, c in cells}))}
    panels = []
    for r, c in cells:
        (zb, zt), (sl, sr) = row_lines[r], col_lines[c]
        corners = surface.points(np.array([[sl, zb, 0.0], [sr, zb, 0.0], [sr, zt, 0.0], [sl, zt, 0.0]]))
        centre3, _, n = quad_frames(corners[None])
        n = n[0] if surface.kind == "cylindrical" else surface.normal
        n_views = len(np.unique(views[(rows == r) & (cols == c)]))
        panels.append(Panel(part, r_num[r], c_num[c], corners, n, float(n @ centre3[0]), n_views))
    return panels, n_out


def drop_specks(
    surfaces: list[PartSurface], rays: CornerRays, part: np.ndarray, ok: np.ndarray, fraction: float
) -> np.ndarray:
    """``ok`` [Q, 4] with the corners of every quad cleared whose visible part spans less than ``fraction``
    of its part's panel width and of its height (a speck in the mask, a panel's corner at the image's
    corner): too little to place a panel by."""
    ok = ok.copy()
    for p, surf in enumerate(surfaces):
        sel = np.flatnonzero(part == p)
        szh = surface_corners(surf, rays, sel)
        size = np.array(panel_size(szh, ok[sel] & np.isfinite(szh).all(axis=2)))
        extent = np.nanmax(szh[..., :2], axis=1) - np.nanmin(szh[..., :2], axis=1)  # [Q, 2]
        with np.errstate(invalid="ignore"):
            small = ~((extent / size) >= fraction).any(axis=1)
        ok[sel[small]] = False
    return ok


def true_corners(
    quads_px: list[np.ndarray],
    complete: np.ndarray,
    view: list[int],
    cameras: list[PinholeCamera],
    margin_px: float,
) -> np.ndarray:
    """[Q, 4] bool: the corners that are real panel corners: all of a complete quad's, and those of an
    incomplete quad (cut by the image border) farther than ``margin_px`` (px) inside the image."""
    ok = np.ones((len(quads_px), 4), bool)
    for q in np.flatnonzero(~complete):
        c, cam = quads_px[q], cameras[view[q]]
        ok[q] = (
            (c[:, 0] > margin_px)
            & (c[:, 1] > margin_px)
            & (c[:, 0] < cam.width - margin_px)
            & (c[:, 1] < cam.height - margin_px)
        )
    return ok


def _refit_parts(
    surfaces: list[PartSurface],
    offsets: list[dict],
    rays: CornerRays,
    points: np.ndarray,
    good_hit: np.ndarray,
    part: np.ndarray,
    ok: np.ndarray,
    anchor: np.ndarray,
    rc: MeshRaycaster,
    coarse_points: np.ndarray,
    cfg: RegularizeConfig,
) -> None:
    """Refit each part's surface (in place) through every true corner (``ok`` [Q, 4]) with a good hit
    (``good_hit`` [Q, 4]) of the quads assigned to it, cut quads included, when they add corners to the
    anchors' (whole quads'); the glass offset is found again on the new surface."""
    for p in range(len(surfaces)):
        use = (part == p)[:, None] & ok & good_hit
        if use.sum() <= 4 * int(anchor[part == p].sum()):
            continue
        surf, _ = fit_surface_robust(points[use], rays.centers[np.unique(rays.view[part == p])], cfg)
        feet = footprints_of(surface_corners(surf, rays, (part == p) & anchor), FOOTPRINT_SHRINK)
        delta, _, _ = glass_offset(surf, feet, coarse_points, rc, cfg)
        surfaces[p] = surf.shifted(delta)
        offsets[p].update(
            glass_offset_m=round(delta, 4), radius_m=round(surf.radius_m, 3), refit_corners=int(use.sum())
        )


def glass_support(
    panel: Panel, surface: PartSurface, coarse_points: np.ndarray, cfg: RegularizeConfig
) -> int:
    """How many coarse points lie on ``panel``'s glass (within three kernel widths of its surface, inside its
    footprint shrunk by ``FOOTPRINT_SHRINK``): the evidence that the panel is where its part puts it."""
    szh = surface.coords(coarse_points)
    feet = footprints_of(surface.coords(panel.corners)[None], FOOTPRINT_SHRINK)[0]
    inside = (szh[:, 0] >= feet[0]) & (szh[:, 0] <= feet[1]) & (szh[:, 1] >= feet[2]) & (szh[:, 1] <= feet[3])
    return int((inside & (np.abs(szh[:, 2]) <= 3 * cfg.depth_bandwidth_m)).sum())


def dedupe_across_parts(
    panels: list[Panel], surfaces: list[PartSurface], coarse_points: np.ndarray, cfg: RegularizeConfig
) -> list[Panel]:
    """Panels of different parts whose centres are closer than half a panel width are one panel placed by
    two parts (where a cylinder meets a plane tangentially both surfaces fit the quads there): the one
    with more coarse points on its glass (``glass_support``) stays."""
    drop: set[int] = set()
    for i, a in enumerate(panels):
        for j in range(i + 1, len(panels)):
            b = panels[j]
            if a.part == b.part or np.linalg.norm(a.center - b.center) >= 0.5 * min(a.width_m, b.width_m):
                continue
            sa = glass_support(a, surfaces[a.part], coarse_points, cfg)
            sb = glass_support(b, surfaces[b.part], coarse_points, cfg)
            drop.add(j if sa >= sb else i)
    return [p for k, p in enumerate(panels) if k not in drop]


def build_panel_set(
    quads_px: list[np.ndarray],
    complete: list[bool],
    view: list[int],
    cameras: list[PinholeCamera],
    rc: MeshRaycaster,
    coarse_points: np.ndarray,
    cfg: RegularizeConfig,
) -> tuple[PanelSet, dict]:
    """The 3D panels from 2D panel quads (``quads_px``, Q arrays [4, 2] px, BL BR TR TL) seen in views
    ``view`` [Q] of ``cameras``, the coarse mesh (``rc``) and the coarse points [N, 3]. Returns the panel
    set and metrics (rejected rays by cause, parts, outliers, glass offsets)."""
    metrics: dict = {
        "n_quads": len(quads_px),
        "n_incomplete_quads": int(np.sum(~np.asarray(complete, bool))),
    }
    if not quads_px:
        return PanelSet((), (), {"n_parts": 0}), {**metrics, "n_panels": 0, "n_parts": 0}
    rays = corner_rays(quads_px, view, cameras)
    points, status = cast_corners(rc, rays, cfg.grazing_max_deg)
    complete_a = np.asarray(complete, bool)
    anchor = complete_a & (status == OK).all(axis=1)
    anchor[anchor] = quad_flatness(points[anchor]) <= cfg.ghost_max_m / 2
    part = group_parts(points, anchor, PART_LINK_FACTOR, cfg.part_max_angle_deg)
    surfaces, extents, offsets = [], [], []
    for p in range(int(part.max()) + 1):
        sel = part == p
        cams = rays.centers[np.unique(rays.view[sel])]
        surf, inl = fit_surface_robust(points[sel].reshape(-1, 3), cams, cfg)
        st = status[sel]
        st[~inl.reshape(-1, 4) & (st == OK)] = GHOST
        status[sel] = st
        szh = surface_corners(surf, rays, sel)
        delta, source, n_ev = glass_offset(
            surf, footprints_of(szh, FOOTPRINT_SHRINK), coarse_points, rc, cfg
        )
        surfaces.append(surf.shifted(delta))
        offsets.append(
            {
                "part": p,
                "kind": surf.kind,
                "glass_offset_m": round(delta, 4),
                "source": source,
                "evidence": n_ev,
                "radius_m": round(surf.radius_m, 3),
            }
        )
        lo, hi = np.nanmin(szh[..., :2], axis=(0, 1)), np.nanmax(szh[..., :2], axis=(0, 1))
        span = hi - lo  # quads cut by the border may lie a whole part's size beyond the anchors
        extents.append(np.array([lo[0] - span[0], hi[0] + span[0], lo[1] - span[1], hi[1] + span[1]]))
    part = assign_parts(rays, points, status, part, surfaces, extents, cfg.ghost_max_m)
    ok = true_corners(quads_px, complete_a, view, cameras, BORDER_MARGIN_PX)
    ok = drop_specks(surfaces, rays, part, ok, cfg.min_visible_fraction)
    ok_any = ok.any(axis=1)
    for q in np.flatnonzero(part >= 0):  # hits far from the assigned surface are ghosts too
        h = np.abs(surfaces[part[q]].coords(np.nan_to_num(points[q]))[:, 2])
        status[q][(status[q] == OK) & (h > cfg.ghost_max_m + abs(offsets[part[q]]["glass_offset_m"]))] = GHOST
    _refit_parts(surfaces, offsets, rays, points, status == OK, part, ok, anchor, rc, coarse_points, cfg)
    panels, n_out = [], 0
    for p, surf in enumerate(surfaces):
        sel = np.flatnonzero((part == p) & ok_any)
        szh = surface_corners(surf, rays, sel)
        cam_sz = surf.coords(rays.centers)[:, :2]
        new, k = part_panels(surf, p, szh, ok[sel], rays.view[sel], cfg, cam_sz)
        panels += new
        n_out += k
    n_before = len(panels)
    panels = dedupe_across_parts(panels, surfaces, coarse_points, cfg)
    metrics["panels_placed_by_two_parts"] = n_before - len(panels)
    metrics.update(
        {f"rays_rejected_{name}": int((status == code).sum()) for code, name in STATUS_NAMES.items()}
    )
    metrics.update(
        {
            "rays_total": int(status.size),
            "n_parts": len(surfaces),
            "n_panels": len(panels),
            "n_quads_unplaced": int(np.sum(part < 0)),
            "n_incomplete_quads_used": int(np.sum((part >= 0) & ~complete_a & ok_any)),
            "corners_on_border": int((~ok).sum()),
            "corner_outliers": n_out,
            "panels_seen_in_one_view": int(sum(p.n_views == 1 for p in panels)),
            "parts": offsets,
        }
    )
    return PanelSet(tuple(surfaces), tuple(panels), {"parts": offsets}), metrics
