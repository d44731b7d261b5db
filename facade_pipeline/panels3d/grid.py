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


def grid_lines(
    szh: np.ndarray,
    ok: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    size: tuple[float, float],
    cfg: RegularizeConfig,
) -> tuple[dict, dict, int]:
    """Robust lines of the grid from the true corners (``ok`` [Q, 4]) of quads [Q, 4, 3] at ``rows``,
    ``cols`` [Q]: {row: (z_bottom, z_top)}, {col: (s_left, s_right)} and the number of corner outliers.
    A line no true corner shows is put one panel ``size`` (width, height, m) from the opposite line (the
    grid's regularity)."""
    n_out = 0

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
) -> tuple[list[Panel], int]:
    """The regularised panels of one part from its quads' corner surface coordinates [Q, 4, 3] (h = 0)
    seen in ``views`` [Q]; ``ok`` [Q, 4] marks the true corners (not cut by the image border). Returns
    the panels (rows and columns renumbered from 0, bottom to top and left to right) and the number of
    corner outliers."""
    ok = ok & np.isfinite(szh).all(axis=2)
    size = panel_size(szh, ok)
    if not np.isfinite(size).all() or min(size) <= 0:
        return [], 0
    rows, cols = grid_cells(szh, ok, *size, CLUSTER_GAP_FACTOR)
    row_lines, col_lines, n_out = grid_lines(szh, ok, rows, cols, size, cfg)
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
        new, k = part_panels(surf, p, szh, ok[sel], rays.view[sel], cfg)
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
