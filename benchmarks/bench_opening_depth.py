"""Whether a unit without glass can be told from a pane by the depth behind the panel's plane at which the
views agree: a plane sweep over each 3D panel's interior (``04_regularize/panels.json``) between every pair
of frontal views that see at least half of it (``MIN_SEEN``), at their registered poses
(``04_regularize/poses.json``).

A pane mirrors things in front of it, so its image agrees across views at their mirrored depth, metres
behind the glass (or nowhere, where the backing is black); an opening shows its unit's box at most about a
pitch behind the frame plane. For each depth d behind the panel's plane (``DEPTHS``, in panel pitches), the
pixels of view A inside the panel's interior are cast onto the plane at d, projected into view B (kept where
B's ray passes through the panel's opening) and compared by zero-mean NCC on a band-pass (difference of
Gaussians, ``--band``) grey image; pixels clipped in either view are left out. Two cues per panel:
- whole interior: one NCC per pair and depth, the curve averaged over the pairs (weighted by the pixels
  compared), its peak's depth; opening where the peak lies within one pitch;
- windows: an NCC per pixel over a window (``--window`` of the panel's projected width), averaged over the
  other views for each reference view, each pixel's best depth where its best NCC reaches ``CONFIDENT``;
  the shares of the interior's pixels best at the plane (nearer than ``PLANE_PITCH``: dust, the glass's
  own surface), within a pitch behind it, and beyond; opening where more lie within a pitch than at the
  plane and beyond together.
The threshold, one pitch, is the physics' (the box of a unit is no deeper than a unit is wide), not fitted.
Labels from the truth: the share of the panel's projected interior that the truth mask calls glass (gcw_dev:
``--real``'s masks; a synthetic scene: its gt/ as ``accuracy.truth_as_real`` gives it), median over the
views; under 0.5: opening. Prints, per building, the AUC of each cue and the openings caught / glass panels
lost at the threshold; ``--plot DIR`` draws the whole-interior curves, ``--json`` keeps every panel's.

    .venv/bin/python benchmarks/bench_opening_depth.py --data-root D [--real ../shared/real/gcw_dev]
        [--band FINE COARSE] [--window W] [--plot DIR] [--json FILE] [buildings...]
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from facade_pipeline.io.images import read_image  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.panels3d.model import Panel, PanelSet, PartSurface, frame_width  # noqa: E402
from facade_pipeline.panels3d.poses import registered_scene  # noqa: E402
from facade_pipeline.scene import ImportedScene  # noqa: E402
from facade_pipeline.segmentation.accuracy import truth_as_real  # noqa: E402
from facade_pipeline.segmentation.real_truth import quad_mask  # noqa: E402
from facade_pipeline.synthetic.truth import SyntheticTruth  # noqa: E402

#: depths behind the panel's plane, in panel pitches (the last one stands for a mirror image at infinity)
DEPTHS = np.array([0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.2, 1.5, 2.0,
                   3.0, 5.0, 8.0, 12.0, 20.0, 50.0, 1000.0])
INTERIOR = 0.1  # margin of the interior sampled in A, as a fraction of the panel's width and height
OPENING = 0.02  # margin of the opening B's ray must pass through (fraction): the frames' inner edges
CLIPPED = 250  # a channel at or above this (0-255) is clipped
STRIDE_PX = 2
FINE, COARSE = 300.0, 60.0  # the band-pass's scales: the panel's projected width over these
MIN_SEEN = 0.5  # a view counts for a panel where this share of its interior is in the view
MIN_SHARE = 0.3  # a pair counts at a depth where at least this share of A's pixels are compared
THRESHOLD_PITCH = 1.0
PLANE_PITCH = 0.15  # nearer than this a match is the glass's own surface (dust, film), within pose error
WINDOW = 0.15  # the local NCC's window, as a fraction of the panel's projected width
CONFIDENT = 0.6  # a pixel's depth counts where its best mean NCC reaches this


def band_pass(rgb: np.ndarray, scale_px: float) -> np.ndarray:
    """Grey difference of Gaussians at ``scale_px`` / ``FINE`` and / ``COARSE`` (the panel's projected
    width)."""
    g = rgb.astype(np.float32).mean(axis=2) / 255.0
    s1, s2 = max(scale_px / FINE, 0.7), max(scale_px / COARSE, 2.0)
    return cv2.GaussianBlur(g, (0, 0), s1) - cv2.GaussianBlur(g, (0, 0), s2)


def panel_szh(panel: Panel, surface: PartSurface) -> tuple[float, float, float, float]:
    szh = surface.coords(panel.corners)
    return szh[:, 0].min(), szh[:, 0].max(), szh[:, 1].min(), szh[:, 1].max()


def inner_quad(panel: Panel, surface: PartSurface, margin: float) -> np.ndarray:
    """World corners [4, 3] of the panel's rectangle shrunk by ``margin`` of its size on each side."""
    s0, s1, z0, z1 = panel_szh(panel, surface)
    ds, dz = margin * (s1 - s0), margin * (z1 - z0)
    s, z = (s0 + ds, s1 - ds, s1 - ds, s0 + ds), (z0 + dz, z0 + dz, z1 - dz, z1 - dz)
    return surface.points(np.stack([s, z, np.zeros(4)], axis=1))


def seen_share(cam, panel: Panel, surface: PartSurface) -> float:
    """The share of the panel's interior (``INTERIOR``) that lies inside the view (0 behind it)."""
    uv, z = cam.project(inner_quad(panel, surface, INTERIOR))
    if not (z > 0).all():
        return 0.0
    full = cv2.contourArea(uv.astype(np.float32))
    box = np.array([[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]], np.float32)
    inter, _ = cv2.intersectConvexConvex(uv.astype(np.float32), box)
    return float(inter / full) if full > 0 else 0.0


def sweep_pair(A, B, panel: Panel, surface: PartSurface, pitch_m: float) -> tuple[np.ndarray, np.ndarray]:
    """NCC [D] and pixels compared [D] of view B against view A over the panel's interior, per depth."""
    camA, imA, clipA, fA = A
    camB, imB, clipB, fB = B
    quad, _ = camA.project(inner_quad(panel, surface, INTERIOR))
    m = quad_mask(quad, camA.width, camA.height) & ~clipA
    ys, xs = np.nonzero(m[::STRIDE_PX, ::STRIDE_PX])
    ys, xs = ys * STRIDE_PX + 0.5, xs * STRIDE_PX + 0.5
    a = fA[ys.astype(int), xs.astype(int)]
    o, d = camA.pixel_rays(xs, ys)
    s0, s1, z0, z1 = panel_szh(panel, surface)
    ms, mz = OPENING * (s1 - s0), OPENING * (z1 - z0)
    ncc, count = np.full(len(DEPTHS), np.nan), np.zeros(len(DEPTHS), int)
    for k, dk in enumerate(DEPTHS):
        back = surface.shifted(-dk * pitch_m)
        X = o + back.intersect(o, d)[:, None] * d
        uv, _ = camB.project(X)
        cB = camB.center
        dirB = X - cB
        dirB /= np.linalg.norm(dirB, axis=1, keepdims=True)
        P = cB + surface.intersect(np.broadcast_to(cB, dirB.shape), dirB)[:, None] * dirB
        szh = surface.coords(P)
        ok = (np.isfinite(uv).all(1) & (szh[:, 0] > s0 + ms) & (szh[:, 0] < s1 - ms)
              & (szh[:, 1] > z0 + mz) & (szh[:, 1] < z1 - mz))
        ok &= (uv[:, 0] > 1) & (uv[:, 0] < camB.width - 1) & (uv[:, 1] > 1) & (uv[:, 1] < camB.height - 1)
        if ok.sum() < max(50, MIN_SHARE * len(a)):
            continue
        u = uv[ok].astype(np.float32) - 0.5
        b, cb = sample(fB, u), sample(clipB.astype(np.float32), u) < 0.01
        if cb.sum() < 50:
            continue
        aa, bb = a[ok][cb] - a[ok][cb].mean(), b[cb] - b[cb].mean()
        den = np.sqrt((aa * aa).sum() * (bb * bb).sum())
        if den > 0:
            ncc[k], count[k] = float((aa * bb).sum() / den), int(cb.sum())
    return ncc, count


def sample(img: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Bilinear samples [N] of a float image at pixel positions u [N, 2] (pixel centres at 0)."""
    n = len(u)
    side = int(np.ceil(np.sqrt(n)))
    grid = np.zeros((side * side, 2), np.float32)
    grid[:n] = u
    g = grid.reshape(side, side, 2)
    return cv2.remap(img, g[..., 0], g[..., 1], cv2.INTER_LINEAR).reshape(-1)[:n]


def through_opening(camB, X: np.ndarray, panel: Panel, surface: PartSurface) -> np.ndarray:
    """[N] whether view B's rays to the points X [N, 3] pass through the panel's opening (``OPENING``)
    and land inside B's image."""
    s0, s1, z0, z1 = panel_szh(panel, surface)
    ms, mz = OPENING * (s1 - s0), OPENING * (z1 - z0)
    uv, _ = camB.project(X)
    cB = camB.center
    dirB = X - cB
    dirB /= np.linalg.norm(dirB, axis=1, keepdims=True)
    szh = surface.coords(cB + surface.intersect(np.broadcast_to(cB, dirB.shape), dirB)[:, None] * dirB)
    return (np.isfinite(uv).all(1) & (szh[:, 0] > s0 + ms) & (szh[:, 0] < s1 - ms) & (szh[:, 1] > z0 + mz)
            & (szh[:, 1] < z1 - mz) & (uv[:, 0] > 1) & (uv[:, 0] < camB.width - 1) & (uv[:, 1] > 1)
            & (uv[:, 1] < camB.height - 1))


def window_ncc(a: np.ndarray, b: np.ndarray, valid: np.ndarray, win: int) -> np.ndarray:
    """Zero-mean NCC [h, w] of a and b [h, w] over win x win windows of the valid pixels (NaN where a
    window holds under half its pixels or no contrast)."""
    box = lambda z: cv2.boxFilter(z, -1, (win, win), normalize=False)  # noqa: E731
    aa, bb, w = np.where(valid, a, 0.0), np.where(valid, b, 0.0), valid.astype(np.float64)
    n, sa, sb = box(w), box(aa), box(bb)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = box(aa * bb) - sa * sb / n
        va, vb = box(aa * aa) - sa * sa / n, box(bb * bb) - sb * sb / n
        r = cov / np.sqrt(va * vb)
    return np.where(valid & (n >= 0.5 * win * win) & (va > 1e-6 * n) & (vb > 1e-6 * n), r, np.nan)


def local_pair(A, B, panel: Panel, surface: PartSurface, pitch_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Windowed NCC [D, h, w] of view B against view A on a grid (``STRIDE_PX``) over the panel's
    interior in A, per depth, and where the grid lies in the interior [h, w]."""
    camA, _, clipA, fA = A
    camB, _, clipB, fB = B
    quad, _ = camA.project(inner_quad(panel, surface, INTERIOR))
    m = quad_mask(quad, camA.width, camA.height) & ~clipA
    ys, xs = np.nonzero(m)
    if len(ys) < 50:
        return np.full((len(DEPTHS), 1, 1), np.nan), np.zeros((1, 1), bool)
    gy, gx = np.mgrid[ys.min():ys.max() + 1:STRIDE_PX, xs.min():xs.max() + 1:STRIDE_PX]
    inside, a = m[gy, gx], fA[gy, gx].astype(np.float64)
    o, d = camA.pixel_rays(gx + 0.5, gy + 0.5)
    win = max(3, int(WINDOW * np.linalg.norm(quad[1] - quad[0]) / STRIDE_PX)) | 1
    out = np.full((len(DEPTHS),) + a.shape, np.nan)
    for k, dk in enumerate(DEPTHS):
        X = o + surface.shifted(-dk * pitch_m).intersect(o, d)[:, None] * d
        u = np.nan_to_num(camB.project(X)[0]).astype(np.float32) - 0.5
        ok = through_opening(camB, X, panel, surface) & (sample(clipB.astype(np.float32), u) < 0.01)
        b = sample(fB, u).reshape(a.shape).astype(np.float64)
        out[k] = window_ncc(a, b, ok.reshape(a.shape) & inside, win)
    return out, inside


def local_depths(feats: dict, panel: Panel, surface: PartSurface, pitch_m: float):
    """Per reference view: its interior grid pixels, and the best depths (pitches) of those whose best
    mean NCC over the other views reaches ``CONFIDENT``."""
    for sa in feats:
        curves = [local_pair(feats[sa], feats[sb], panel, surface, pitch_m) for sb in feats if sb != sa]
        if not curves or not curves[0][1].any():
            continue
        with np.errstate(invalid="ignore"):
            mean = np.nanmean(np.array([c for c, _ in curves]), axis=0)  # [D, h, w]
        valid = np.isfinite(mean).any(0) & curves[0][1]
        mm = np.where(np.isfinite(mean), mean, -np.inf)
        sel = valid & (mm.max(0) >= CONFIDENT)
        yield int(valid.sum()), DEPTHS[mm.argmax(0)[sel]]


def truth_masks(layout: BuildingLayout, building: str, real: Path | None, stems: list[str]) -> dict:
    if real is not None and building == "gcw_dev":
        return {s: cv2.imread(str(real / "masks" / f"{s}.png"), cv2.IMREAD_GRAYSCALE) > 127 for s in stems}
    scene = ImportedScene.load(layout)
    truth = SyntheticTruth.load(layout, scene.georef_from_local)
    return {s: truth_as_real(truth, s)[0] for s in stems}


def measure(layout: BuildingLayout, building: str, real: Path | None) -> list[dict]:
    scene = registered_scene(layout)
    ps = PanelSet.load(layout.path("regularize_panels"))
    views = {}
    for v in scene.frontal_views:
        rgb = read_image(layout.import_frontal_image(v.stem))
        views[v.stem] = (v.camera, rgb)
    masks = truth_masks(layout, building, real, list(views))
    out = []
    for i, p in enumerate(ps.panels):
        surf = ps.parts[p.part]
        pitch = p.width_m + frame_width(ps.of_part(p.part), surf)
        seen = [s for s, (cam, _) in views.items() if seen_share(cam, p, surf) >= MIN_SEEN]
        shares, feats = [], {}
        for s in seen:
            cam, rgb = views[s]
            q, _ = cam.project(inner_quad(p, surf, INTERIOR))
            qm = quad_mask(q, cam.width, cam.height)
            shares.append(float(masks[s][qm].mean()))
            width_px = float(np.linalg.norm(q[1] - q[0]) / (1 - 2 * INTERIOR))
            feats[s] = (cam, rgb, (rgb >= CLIPPED).any(axis=2), band_pass(rgb, width_px))
        curves, counts = [], []
        for sa, sb in itertools.combinations(seen, 2):
            c, n = sweep_pair(feats[sa], feats[sb], p, surf, pitch)
            curves.append(c)
            counts.append(n)
        rec = {"index": i, "row": p.row, "col": p.col, "views": len(seen), "pairs": len(curves),
               "glass_share": float(np.median(shares)) if shares else float("nan")}
        if curves:
            C, N = np.array(curves), np.array(counts, float)
            w = np.where(np.isfinite(C), N, 0.0)
            with np.errstate(invalid="ignore"):
                mean = np.nansum(np.nan_to_num(C) * w, 0) / w.sum(0)
            rec["curve"] = mean.tolist()
            rec["pair_curves"] = C.tolist()
            k = int(np.nanargmax(mean)) if np.isfinite(mean).any() else -1
            rec["best_depth_pitch"] = float(DEPTHS[k]) if k >= 0 else float("nan")
            hist, tot = np.zeros(len(DEPTHS)), 0
            for nv, dep in local_depths(feats, p, surf, pitch):
                tot += nv
                hist += np.bincount(np.searchsorted(DEPTHS, dep), minlength=len(DEPTHS))
            h = hist / max(tot, 1)
            rec["local_hist"] = h.tolist()
            rec["plane"] = float(h[DEPTHS < PLANE_PITCH].sum())
            rec["near"] = float(h[(DEPTHS >= PLANE_PITCH) & (DEPTHS <= THRESHOLD_PITCH)].sum())
            rec["far"] = float(h[DEPTHS > THRESHOLD_PITCH].sum())
        out.append(rec)
    return out


def auc(score_open: list[float], score_glass: list[float]) -> float:
    """P(an opening scores above a glass panel), ties counted half."""
    if not score_open or not score_glass:
        return float("nan")
    a, b = np.array(score_open)[:, None], np.array(score_glass)[None]
    return float(((a > b) + 0.5 * (a == b)).mean())


def report(building: str, recs: list[dict]) -> str:
    """The building's figures: the AUC and the physical rule's counts of both cues, then every panel."""
    ok = [r for r in recs if "curve" in r]
    op = [r for r in ok if r["glass_share"] < 0.5]
    gl = [r for r in ok if r["glass_share"] >= 0.5]
    peak = auc([-r["best_depth_pitch"] for r in op], [-r["best_depth_pitch"] for r in gl])
    caught = sum(r["best_depth_pitch"] <= THRESHOLD_PITCH for r in op)
    lost = sum(r["best_depth_pitch"] <= THRESHOLD_PITCH for r in gl)
    near = auc([r["near"] for r in op], [r["near"] for r in gl])
    caught_l = sum(r["near"] > r["plane"] + r["far"] for r in op)
    lost_l = sum(r["near"] > r["plane"] + r["far"] for r in gl)
    lines = [
        f"{building}: {len(recs)} panels, {len(ok)} seen by two views or more: {len(op)} openings, "
        f"{len(gl)} glass",
        f"  whole interior: AUC of the peak depth {peak:.2f}; peak within {THRESHOLD_PITCH} pitch: "
        f"openings caught {caught}/{len(op)}, glass lost {lost}/{len(gl)}",
        f"  windows: AUC of the share within a pitch {near:.2f}; more within a pitch than at the plane and "
        f"beyond: openings caught {caught_l}/{len(op)}, glass lost {lost_l}/{len(gl)}",
    ]
    nan = float("nan")
    for r in recs:
        lines.append(f"  r{r['row']} c{r['col']} glass {r['glass_share']:.2f} views {r['views']} pairs "
                     f"{r['pairs']} peak {r.get('best_depth_pitch', nan):g} pitch; windows: plane "
                     f"{r.get('plane', nan):.2f} near {r.get('near', nan):.2f} far {r.get('far', nan):.2f}")
    return "\n".join(lines)


def plot(path: Path, building: str, recs: list[dict]) -> None:
    """The panels' curves (NCC against log depth) drawn with OpenCV: red openings, blue glass, the
    threshold dotted."""
    W, H, m = 900, 500, 40
    img = np.full((H, W, 3), 255, np.uint8)
    x = np.log10(DEPTHS + 0.01)
    px = lambda v: int(m + (v - x[0]) / (x[-1] - x[0]) * (W - 2 * m))  # noqa: E731
    py = lambda c: int(H - m - (c + 0.2) / 1.2 * (H - 2 * m))  # noqa: E731  NCC -0.2..1
    cv2.line(img, (px(np.log10(THRESHOLD_PITCH + 0.01)), m), (px(np.log10(THRESHOLD_PITCH + 0.01)), H - m),
             (0, 0, 0), 1)
    for c in (0.0, 0.5, 1.0):
        cv2.putText(img, f"{c:.1f}", (2, py(c)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
        cv2.line(img, (m, py(c)), (W - m, py(c)), (200, 200, 200), 1)
    for r in recs:
        if "curve" not in r:
            continue
        col = (0, 0, 255) if r["glass_share"] < 0.5 else (255, 0, 0)
        pts = [(px(xv), py(c)) for xv, c in zip(x, r["curve"], strict=True) if np.isfinite(c)]
        if not pts:
            continue
        cv2.polylines(img, [np.array(pts, np.int32)], False, col, 1, cv2.LINE_AA)
        cv2.putText(img, f"r{r['row']}c{r['col']}", pts[-1], cv2.FONT_HERSHEY_SIMPLEX, 0.35, col, 1)
    title = f"{building}: NCC against log10(depth / pitch + 0.01); red openings, blue glass"
    cv2.putText(img, title, (m, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    cv2.imwrite(str(path), img)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-root", required=True)
    ap.add_argument("--real", type=Path, default=None, help="gcw_dev's truth folder (shared/real/gcw_dev)")
    ap.add_argument("--plot", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None, help="write every panel's curves here")
    ap.add_argument("--band", type=float, nargs=2, default=(FINE, COARSE),
                    help="the band-pass's scales: the panel's projected width over these")
    ap.add_argument("--window", type=float, default=WINDOW)
    ap.add_argument("buildings", nargs="*")
    args = ap.parse_args()
    globals().update(FINE=args.band[0], COARSE=args.band[1], WINDOW=args.window)
    buildings = (["gcw_dev"] if args.real else []) + (args.buildings or ["real_like"])
    everything = {}
    for b in buildings:
        recs = measure(BuildingLayout.for_building(b, args.data_root), b, args.real)
        everything[b] = recs
        print(report(b, recs), flush=True)
        if args.plot:
            args.plot.mkdir(parents=True, exist_ok=True)
            plot(args.plot / f"{b}.png", b, recs)
    if args.json:
        args.json.write_text(json.dumps({"depths_pitch": DEPTHS.tolist(), "buildings": everything}))


if __name__ == "__main__":
    main()
