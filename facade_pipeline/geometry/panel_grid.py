"""The panel grid of each facade part and the regularised 3D panels (the paper, section 3.1.2, end):
rows of corners share one height, columns of corners one position along the surface (a ruling on
cylinders). See ``facade_pipeline.geometry.regularize`` for the steps before. Local frame, metres."""

from __future__ import annotations

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.geometry.regularize import (
    GHOST,
    OK,
    STATUS_NAMES,
    CornerRays,
    RegularizeConfig,
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
from facade_pipeline.panels import Panel, PanelSet, PartSurface


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


def grid_lines(
    szh: np.ndarray, rows: np.ndarray, cols: np.ndarray, cfg: RegularizeConfig
) -> tuple[dict, dict, int]:
    """Robust lines of the grid from corner surface coordinates [Q, 4, 3] of quads at ``rows``, ``cols``
    [Q]: {row: (z_bottom, z_top)}, {col: (s_left, s_right)} and the number of corner outliers."""
    n_out = 0

    def line(values: np.ndarray) -> float:
        nonlocal n_out
        v = values[np.isfinite(values)]
        keep = robust_inliers(v, cfg.outlier_mad_factor, cfg.outlier_floor_m)
        n_out += int((~keep).sum())
        return float(v[keep].mean())

    row_lines = {
        int(r): (line(szh[rows == r][:, [0, 1], 1].ravel()), line(szh[rows == r][:, [2, 3], 1].ravel()))
        for r in np.unique(rows)
    }
    col_lines = {
        int(c): (line(szh[cols == c][:, [0, 3], 0].ravel()), line(szh[cols == c][:, [1, 2], 0].ravel()))
        for c in np.unique(cols)
    }
    return row_lines, col_lines, n_out


def part_panels(
    surface: PartSurface, part: int, szh: np.ndarray, views: np.ndarray, cfg: RegularizeConfig
) -> tuple[list[Panel], int]:
    """The regularised panels of one part from its quads' corner surface coordinates [Q, 4, 3] (h = 0)
    seen in ``views`` [Q]. Returns the panels (rows bottom to top, columns left to right) and the number
    of corner outliers."""
    centre = np.nanmean(szh[..., :2], axis=1)
    width = np.nanmedian(np.ptp(szh[..., 0], axis=1))
    height = np.nanmedian(np.ptp(szh[..., 1], axis=1))
    rows = cluster_1d(centre[:, 1], cfg.cluster_gap_factor * height)
    cols = cluster_1d(centre[:, 0], cfg.cluster_gap_factor * width)
    row_lines, col_lines, n_out = grid_lines(szh, rows, cols, cfg)
    panels = []
    for r, c in sorted({(int(a), int(b)) for a, b in zip(rows, cols, strict=True)}):
        (zb, zt), (sl, sr) = row_lines[r], col_lines[c]
        corners = surface.points(np.array([[sl, zb, 0.0], [sr, zb, 0.0], [sr, zt, 0.0], [sl, zt, 0.0]]))
        centre3, _, n = quad_frames(corners[None])
        n = n[0] if surface.kind == "cylindrical" else surface.normal
        n_views = len(np.unique(views[(rows == r) & (cols == c)]))
        panels.append(Panel(part, r, c, corners, n, float(n @ centre3[0]), n_views))
    return panels, n_out


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
        "n_incomplete_quads_skipped": int(np.sum(~np.asarray(complete, bool))),
    }
    if not quads_px:
        return PanelSet((), (), {"n_parts": 0}), {**metrics, "n_panels": 0, "n_parts": 0}
    rays = corner_rays(quads_px, view, cameras)
    points, status = cast_corners(rc, rays, cfg.grazing_max_deg)
    complete_a = np.asarray(complete, bool)
    anchor = complete_a & (status == OK).all(axis=1)
    anchor[anchor] = quad_flatness(points[anchor]) <= cfg.ghost_max_m / 2
    part = group_parts(points, anchor, cfg.part_link_factor, cfg.part_max_angle_deg)
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
            surf, footprints_of(szh, cfg.footprint_shrink), coarse_points, rc, cfg
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
        extents.append(np.array([lo[0] - (hi[0] - lo[0]), hi[0] + (hi[0] - lo[0]), lo[1] - 1.0, hi[1] + 1.0]))
    part = assign_parts(rays, points, status, part, surfaces, extents, cfg.ghost_max_m)
    part[~complete_a] = -1
    for q in np.flatnonzero(part >= 0):  # hits far from the assigned surface are ghosts too
        h = np.abs(surfaces[part[q]].coords(np.nan_to_num(points[q]))[:, 2])
        status[q][(status[q] == OK) & (h > cfg.ghost_max_m + abs(offsets[part[q]]["glass_offset_m"]))] = GHOST
    panels, n_out = [], 0
    for p, surf in enumerate(surfaces):
        sel = np.flatnonzero(part == p)
        szh = surface_corners(surf, rays, sel)
        good = np.isfinite(szh).all(axis=(1, 2))
        new, k = part_panels(surf, p, szh[good], rays.view[sel][good], cfg)
        panels += new
        n_out += k
    metrics.update(
        {f"rays_rejected_{name}": int((status == code).sum()) for code, name in STATUS_NAMES.items()}
    )
    metrics.update(
        {
            "rays_total": int(status.size),
            "n_parts": len(surfaces),
            "n_panels": len(panels),
            "n_quads_unplaced": int(np.sum((part < 0) & complete_a)),
            "corner_outliers": n_out,
            "panels_seen_in_one_view": int(sum(p.n_views == 1 for p in panels)),
            "parts": offsets,
        }
    )
    return PanelSet(tuple(surfaces), tuple(panels), {"parts": offsets}), metrics
