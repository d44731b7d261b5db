"""Can an opening (a cell between frame bars without glass) be told from a glass panel by the room's box
behind it, drawn in perspective about the camera's foot point?

Every candidate panel ``segment_panels`` wrote on a planar view is labelled by the truth (an opening: less
than half of it is truth glass, as ``real_truth.mask_losses`` counts a false panel). The camera's foot point f
on the rectified plane (from 02_rectify's mapping: C = -R^T t, D = (C - origin) . normal, f = C - D normal, in
rectified px) is the vanishing point of the edges running straight back from the wall. For each cell and a
depth t behind its mouth (the panel's rectified quad), the back wall is the mouth scaled about f by D/(D+t)
and the side edges run from the mouth's corners to the back wall's. An edge counts where it shows inside
the mouth at least ``MARGIN`` pitch clear of the bars (and at least ``MIN_LEN`` pitch of it); its evidence is
the best |g . n| within ``TOL`` pitch across it after a blur of ``BLUR`` pitch, normalised by the cell's mean
|g|, or by its 90th percentile with the ratio capped at 1 (``_p90``). Four combinations of the edges
(``mean``: weighted by visible length; ``min``: the weakest edge; ``ray``: the side edges only; ``back``: the
back wall's only), each maximised over t from ``T_MIN`` to ``T_MAX`` pitch in ``N_T`` steps, and each as it
is, less the median over 8 wrong foot points (f +- ``WRONG_FOOT`` pitch), and over the view's median cell: 24
variants. Higher: more like an opening. Per variant the threshold is the lowest that loses at most
``MAX_LOST`` of the simulated scenes' glass panels; printed are, per family of scenes, the AUC and the
openings caught and glass panels lost at that threshold, then a summary per family over the 24 variants.

Inputs: ``DATA_ROOT`` holds gcw_dev (``--real``: its photos with truth, shared/real/gcw_dev) and real_like
through segment_panels (``bench_segmentation.py``); real_like's variants (``VARIANTS``, as
``bench_opening_cue.py`` makes them) are read from ``--sim-root`` (default ``DATA_ROOT/sim``) and made there
from config copies in ``--sim-configs`` (default ``DATA_ROOT/sim_configs``) where they are missing.
``--fixed-t METRES`` instead prints, per building, the AUC of each combination at one depth with no search.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_opening_box.py --data-root /tmp/ov \
        --real ../shared/real/gcw_dev [--sim-root DIR] [--sim-configs DIR] [--jobs 2] [--draw DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
from multiprocessing import Pool
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_segmentation import truth_views  # noqa: E402

from facade_pipeline.io.images import read_image  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.rectification.surface_map import ViewRectification  # noqa: E402
from facade_pipeline.segmentation.real_truth import quad_mask  # noqa: E402

#: the simulated variants of real_like: (seed, units without glass as (part, row, col)), as
#: bench_opening_cue.py makes them
VARIANTS = {
    "rl_v1": (101, [[0, 2, 0], [0, 1, 3], [0, 0, 2]]),
    "rl_v2": (202, [[0, 1, 0], [0, 2, 2], [0, 0, 4]]),
    "rl_v3": (303, [[0, 0, 1], [0, 1, 2], [0, 2, 4]]),
    "rl_v4": (404, [[0, 2, 1], [0, 1, 4], [0, 0, 0]]),
    "rl_v5": (505, [[0, 2, 3], [0, 1, 1], [0, 0, 4]]),
    "rl_v6": (606, [[0, 0, 3], [0, 2, 2], [0, 1, 0]]),
}
T_MIN = 0.2  # pitches: deeper than the frames' own reveal
T_MAX = 1.5  # pitches
N_T = 24
MARGIN = 0.05  # of the pitch, kept clear of the mouth's edges (the bars' own edges)
TOL = 0.02  # of the pitch: the perpendicular search for an edge
MIN_LEN = 0.1  # of the pitch: an edge shorter than this inside the mouth is not counted
BLUR = 0.006  # of the pitch: sigma of the smoothing before the gradient
WRONG_FOOT = 0.75  # of the pitch: the wrong foot points' offset, each way
MAX_LOST = 0.02  # of the simulated scenes' glass panels a threshold may lose
AGG = ("mean", "min", "ray", "back")
SCORES = tuple(h + sfx for h in AGG for sfx in ("", "_p90"))
RELATIVE = ("", " - wrong feet", " / view median")


def make_variants(sim_root: Path, cfg: Path) -> list[BuildingLayout]:
    """real_like's variants (``VARIANTS``: each room's style drawn anew) made and segmented under
    ``sim_root`` from config copies in ``cfg``, where they are not made yet."""
    out = []
    for name, (seed, units) in VARIANTS.items():
        layout = BuildingLayout(sim_root, name)
        if not layout.path("segment_corners", stem="frontal_0000").is_file():
            if not (cfg / "default.toml").is_file():
                (cfg / "buildings").mkdir(parents=True, exist_ok=True)
                for fname in ("default.toml", "synthetic.toml"):
                    shutil.copy(REPO / "configs" / fname, cfg / fname)
            base = (REPO / "configs" / "buildings" / "real_like.toml").read_text()
            text = re.sub(r"(?m)^seed = .*$", f"seed = {seed}", base)
            text = re.sub(r"(?m)^unglazed_units = .*$", f"unglazed_units = {json.dumps(units)}", text)
            (cfg / "buildings" / f"{name}.toml").write_text(text)
            env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
            for stage in ("synthesize", "import_photogrammetry", "rectify", "segment_panels"):
                print(f"{name}: {stage}", file=sys.stderr, flush=True)
                subprocess.run([sys.executable, "-m", "stages", stage, "--building", name, "--data-root",
                                str(sim_root)], cwd=REPO, env=env, check=True, capture_output=True)
        out.append(layout)
    return out


def auc(score: np.ndarray, y: np.ndarray) -> float:
    """P(an opening scores above a glass panel), ties half."""
    a, b = score[y][:, None], score[~y][None, :]
    return float(((a > b) + 0.5 * (a == b)).mean()) if len(a) and b.size else float("nan")


def views(layout: BuildingLayout, src: Path | None):
    """(stem, rectification, rectified image, panels, labels (True: an opening)) of every planar view with
    truth."""
    for stem, seg, mask, _, _ in truth_views(layout, src):
        rect = ViewRectification.load(layout.path("rectify_mapping", stem=stem))
        if rect.chart is None or rect.kind != "plane":
            continue
        rimg = read_image(layout.path("rectify_image", stem=stem))
        H, W = mask.shape
        labels = []
        for p in seg.panels:
            m = quad_mask(p.corners_px, W, H)
            labels.append((float(mask[m].mean()) if m.any() else 0.0) < 0.5)
        yield stem, rect, rimg, list(seg.panels), labels


def foot(rect: ViewRectification) -> tuple[np.ndarray, float]:
    """The camera's foot point on the rectified plane (px) and its distance to the plane (px)."""
    c, m = rect.chart, rect.metres_per_px
    R, t = rect.camera.cam_from_world[:3, :3], rect.camera.cam_from_world[:3, 3]
    C = -R.T @ t
    D = float((C - c.origin) @ c.normal)
    F = C - D * c.normal
    q = F - c.origin
    return np.array([(q @ c.right - rect.s0_m) / m, (rect.h0_m - q @ c.up) / m]), D / m


def pitch_px(quads: list[np.ndarray], panels) -> float:
    """The view's panel pitch along x (px), from neighbouring panels' centres; their width where none."""
    cen = {(p.row, p.col): q.mean(0) for p, q in zip(panels, quads, strict=True)}
    d = [abs(cen[k][0] - cen[(k[0], k[1] + 1)][0]) for k in cen if (k[0], k[1] + 1) in cen]
    if d:
        return float(np.median(d))
    return float(np.median([np.ptp(q[:, 0]) for q in quads])) * 1.1


def inside(q: np.ndarray, pts: np.ndarray, margin: float) -> np.ndarray:
    """Points [N, 2] at least ``margin`` px inside the convex quad ``q`` (either winding)."""
    ok = np.ones(len(pts), bool)
    cen = q.mean(0)
    for i in range(4):
        a, b = q[i], q[(i + 1) % 4]
        n = np.array([-(b - a)[1], (b - a)[0]])
        n /= np.linalg.norm(n)
        if (cen - a) @ n < 0:
            n = -n
        ok &= (pts - a) @ n >= margin
    return ok


def template(q: np.ndarray, f: np.ndarray, s: float) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """The box's edges (p0, p1, kind) for the mouth ``q`` [4, 2] with its back wall at scale ``s`` about f."""
    b = f + (q - f) * s
    out = [(b[i], b[(i + 1) % 4], "back") for i in range(4)]
    out += [(q[i], b[i], "ray") for i in range(4)]
    return out


class Grad:
    """The rectified image's luminance gradient after a blur of ``sigma`` px, and where it is valid (inside
    the rectified image, clear of its empty border by the blur's reach and ``erode_px``)."""

    def __init__(self, img: np.ndarray, sigma: float, erode_px: float = 0.0):
        lum = img.astype(np.float32).mean(2) / 255
        if sigma > 0.5:
            lum = cv2.GaussianBlur(lum, (0, 0), sigma)
        self.gx = cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3) / 8
        self.gy = cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3) / 8
        self.valid = cv2.erode((img.max(2) > 0).astype(np.uint8), np.ones((3, 3), np.uint8),
                               iterations=int(np.ceil(3 * sigma + erode_px)) + 2) > 0

    def sample(self, pts: np.ndarray):
        x = pts[:, 0].astype(np.float32).reshape(1, -1) - 0.5
        y = pts[:, 1].astype(np.float32).reshape(1, -1) - 0.5
        gx = cv2.remap(self.gx, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)[0]
        gy = cv2.remap(self.gy, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)[0]
        return gx, gy


def edge_evidence(G: Grad, p0, p1, q, margin, tol, step=1.0):
    """Points inside the mouth along p0-p1, and per point the best |g . n| within tol across the edge."""
    L = float(np.linalg.norm(p1 - p0))
    if L < 1e-6:
        return None, None
    n_s = max(2, int(L / step))
    u = np.linspace(0, 1, n_s)
    pts = p0 + u[:, None] * (p1 - p0)
    ok = inside(q, pts, margin)
    pts = pts[ok]
    xi = np.clip(pts[:, 0].astype(int), 0, G.valid.shape[1] - 1)
    yi = np.clip(pts[:, 1].astype(int), 0, G.valid.shape[0] - 1)
    pts = pts[G.valid[yi, xi]]
    if len(pts) == 0:
        return pts, np.zeros(0)
    d = (p1 - p0) / L
    n = np.array([-d[1], d[0]])
    best = np.zeros(len(pts))
    for o in np.arange(-tol, tol + 0.01, 1.0):
        gx, gy = G.sample(pts + o * n)
        best = np.maximum(best, np.abs(gx * n[0] + gy * n[1]))
    return pts, best


def cell_contrast(G: Grad, q: np.ndarray, margin: float, P: float) -> tuple[float, float]:
    """The mean and the 90th percentile of the gradient magnitude inside the mouth (the cell's own
    contrast)."""
    x0, y0 = np.floor(q.min(0)).astype(int)
    x1, y1 = np.ceil(q.max(0)).astype(int)
    ys, xs = np.mgrid[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)]
    pts = np.c_[xs.ravel() + 0.5, ys.ravel() + 0.5]
    pts = pts[inside(q, pts, margin)]
    if len(pts) < 20:
        return np.nan, np.nan
    xi, yi = pts[:, 0].astype(int), pts[:, 1].astype(int)
    xi, yi = np.clip(xi, 0, G.gx.shape[1] - 1), np.clip(yi, 0, G.gx.shape[0] - 1)
    keep = G.valid[yi, xi]
    if keep.sum() < 0.02 * P * P:
        return np.nan, np.nan
    xi, yi = xi[keep], yi[keep]
    g = np.hypot(G.gx[yi, xi], G.gy[yi, xi])
    return float(g.mean()), float(np.percentile(g, 90))


def edges_at(G, q, f, D, t_px, P, contrast):
    """(kind, evidence / mean contrast, visible length, evidence / 90th percentile capped at 1) of each
    visible template edge at depth ``t_px``."""
    s = D / (D + t_px)
    out = []
    for p0, p1, kind in template(q, f, s):
        pts, best = edge_evidence(G, p0, p1, q, MARGIN * P, TOL * P)
        if pts is None or len(pts) < MIN_LEN * P:
            continue
        out.append((kind, float(best.mean()) / contrast[0], len(pts),
                    float(np.minimum(best / contrast[1], 1.0).mean())))
    return out


def aggregate(e, how):
    """Per normalisation (by the cell's mean gradient; by its 90th percentile, capped at 1)."""
    out = []
    for j in (1, 3):
        x = [(v[0], v[j], v[2]) for v in e]
        if how == "mean":
            out.append(float(np.average([v for _, v, _ in x], weights=[n for _, _, n in x])) if x else np.nan)
        elif how == "min":
            out.append(float(min(v for _, v, _ in x)) if len(x) >= 2 else np.nan)
        else:
            sel = [(v, n) for k, v, n in x if k == how]
            out.append(float(np.average([v for v, _ in sel], weights=[n for _, n in sel])) if sel else np.nan)
    return out


def best_t(G, q, f, D, P, contrast):
    """Per aggregation and normalisation: the best score over t and that t (pitches)."""
    ts = np.linspace(T_MIN, T_MAX, N_T) * P
    sc = np.array([sum((aggregate(edges_at(G, q, f, D, t, P, contrast), h) for h in AGG), []) for t in ts])
    out = {}
    for j, h in enumerate(SCORES):
        col = sc[:, j]
        if np.all(np.isnan(col)):
            out[h] = (np.nan, np.nan)
        else:
            k = int(np.nanargmax(col))
            out[h] = (float(col[k]), float(ts[k] / P))
    return out


def study(layout: BuildingLayout, src: Path | None, draw_dir: Path | None) -> list[dict]:
    """One row per scored panel: its label, and per score the best over t, that t, and the median and maximum
    over the wrong foot points."""
    rows = []
    for stem, rect, rimg, panels, labels in views(layout, src):
        f, D = foot(rect)
        quads = [np.asarray(p.corners_rectified_px, float) for p in panels]
        P = pitch_px(quads, panels)
        G = Grad(rimg, BLUR * P, TOL * P)
        canvas = rimg[..., ::-1].copy() if draw_dir else None
        for p, q, lab in zip(panels, quads, labels, strict=True):
            c = cell_contrast(G, q, MARGIN * P, P)
            if not np.all(np.isfinite(c)) or min(c) <= 0:
                continue
            bt = best_t(G, q, f, D, P, c)
            wrong = [best_t(G, q, f + WRONG_FOOT * P * np.array([dx, dy]), D, P, c)
                     for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]
            row = dict(view=f"{layout.building}/{stem}", row=p.row, col=p.col, complete=p.complete,
                       opening=lab, contrast=c[0])
            for h in SCORES:
                w = [x[h][0] for x in wrong]
                row[h] = bt[h][0]
                row[h + "_t"] = bt[h][1]
                row[h + "_wmed"] = float(np.nanmedian(w)) if np.isfinite(w).any() else np.nan
                row[h + "_wmax"] = float(np.nanmax(w)) if np.isfinite(w).any() else np.nan
            rows.append(row)
            if canvas is not None:
                s, t = bt["mean"]
                col = (0, 0, 255) if lab else (0, 200, 0)
                cv2.polylines(canvas, [np.int32(q)], True, col, 2)
                sc = D / (D + t * P)
                for p0, p1, _ in template(q, f, sc):
                    n = max(2, int(np.linalg.norm(p1 - p0)))
                    pts = p0 + np.linspace(0, 1, n)[:, None] * (p1 - p0)
                    pts = pts[inside(q, pts, 0)]
                    for a in np.int32(pts):
                        cv2.circle(canvas, tuple(int(v) for v in a), 1, (255, 0, 255), -1)
                cv2.putText(canvas, f"{s:.2f} t{t:.2f} m{row['min']:.2f}", tuple(int(v) for v in q.mean(0)),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.6 if P > 200 else 0.35, (255, 255, 0), 1)
        if canvas is not None:
            cv2.circle(canvas, tuple(int(v) for v in f), 6, (0, 255, 255), -1)
            cv2.imwrite(str(draw_dir / f"{layout.building}_{stem}.png"), canvas)
    return rows


def fixed_t(layout: BuildingLayout, src: Path | None, t_m: float) -> str:
    """The AUC of each score at one depth ``t_m`` (metres behind the chart's plane), no search."""
    rows = []
    for stem, rect, rimg, panels, labels in views(layout, src):
        f, D = foot(rect)
        quads = [np.asarray(p.corners_rectified_px, float) for p in panels]
        P = pitch_px(quads, panels)
        G = Grad(rimg, BLUR * P, TOL * P)
        t_px = t_m / rect.metres_per_px
        for q, lab in zip(quads, labels, strict=True):
            c = cell_contrast(G, q, MARGIN * P, P)
            if not np.all(np.isfinite(c)):
                continue
            e = edges_at(G, q, f, D, t_px, P, c)
            r = dict(view=f"{layout.building}/{stem}", opening=lab)
            r.update(zip(SCORES, sum((aggregate(e, h) for h in AGG), []), strict=True))
            rows.append(r)
    y = np.array([r["opening"] for r in rows])
    return f"{layout.building} t = {t_m} m: {len(y)} panels ({int(y.sum())} openings); " + " ".join(
        f"{h} {auc(np.nan_to_num(np.array([r[h] for r in rows], float), nan=-1e9), y):.2f}" for h in SCORES)


def values(rs: list[dict], h: str, rel: int) -> np.ndarray:
    """Score ``h`` of rows ``rs`` as it is (rel 0), less the wrong feet's median (1), over the view's median
    cell (2); a panel with no score ranks lowest."""
    s = np.array([x[h] for x in rs], float)
    if rel == 2:
        v = np.array([x["view"] for x in rs])
        med = {k: np.nanmedian(s[v == k]) if np.isfinite(s[v == k]).any() else 1.0 for k in set(v)}
        s = s / np.array([med[k] for k in v])
    elif rel:
        s = s - np.nan_to_num(np.array([x[h + "_wmed"] for x in rs], float), nan=0)
    return np.nan_to_num(s, nan=-1e9)


def verdict(rows: list[dict], real: str) -> list[str]:
    """Per variant: the threshold set on the simulated scenes, and per family AUC, caught and lost; then a
    summary per family (gcw_dev, real_like, every simulated scene) over the variants."""
    fam: dict[str, list[dict]] = {}
    for x in rows:
        fam.setdefault(x["view"].split("/")[0], []).append(x)
    sim = [x for x in rows if x["view"].split("/")[0] != real]
    families = list(fam.items()) + [("simulated", sim)]
    lines, summary = [], {name: [] for name, _ in families}
    for h in SCORES:
        for rel in range(3):
            ys, ss = np.array([x["opening"] for x in sim]), values(sim, h, rel)
            g = np.sort(ss[~ys])
            k = int(np.floor(MAX_LOST * len(g)))
            thr = g[len(g) - 1 - k]  # strictly above: at most k glass panels lost
            line = [f"{h}{RELATIVE[rel]}: thr {thr:.2f}"]
            for name, rs in families:
                y, s = np.array([x["opening"] for x in rs]), values(rs, h, rel)
                a, caught, lost = auc(s, y), int((s[y] > thr).sum()), int((s[~y] > thr).sum())
                summary[name].append((a, caught, lost, f"{h}{RELATIVE[rel]}"))
                line.append(f"{name} AUC {a:.2f} caught {caught}/{int(y.sum())} "
                            f"lost {lost}/{int((~y).sum())}")
            lines.append(" | ".join(line))
    lines += ["", "| family | panels (openings) | AUC range over variants | most caught (variant, lost) |",
              "| --- | --- | --- | --- |"]
    for name, rs in families:
        y = np.array([x["opening"] for x in rs])
        s = summary[name]
        best = max(s, key=lambda v: (v[1], -v[2]))
        lo, hi = min(v[0] for v in s), max(v[0] for v in s)
        lines.append(f"| {name} | {len(y)} ({int(y.sum())}) | {lo:.2f}-{hi:.2f}"
                     f" | {best[1]}/{int(y.sum())} ({best[3]}, lost {best[2]}/{int((~y).sum())}) |")
    return lines


def _study(job):
    layout, src, draw = job
    print(f"{layout.building}: scoring", file=sys.stderr, flush=True)
    return study(layout, src, draw)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-root", type=Path, required=True,
                    help="gcw_dev and real_like through segment_panels")
    ap.add_argument("--real", type=Path, required=True, help="gcw_dev's photos with truth")
    ap.add_argument("--sim-root", type=Path, help="real_like's variants (default DATA_ROOT/sim)")
    ap.add_argument("--sim-configs", type=Path, help="their config copies (default DATA_ROOT/sim_configs)")
    ap.add_argument("--real-building", default="gcw_dev")
    ap.add_argument("--jobs", type=int, default=1, help="buildings scored at once")
    ap.add_argument("--rows", type=Path, help="write every panel's scores here (JSON)")
    ap.add_argument("--draw", type=Path, help="draw each view's best template here")
    ap.add_argument("--fixed-t", type=float, help="metres: only the AUC per building at this one depth")
    args = ap.parse_args()
    real = args.real.resolve()
    sim = make_variants(args.sim_root or args.data_root / "sim",
                        args.sim_configs or args.data_root / "sim_configs")
    layouts = [(BuildingLayout(args.data_root, args.real_building), real),
               (BuildingLayout(args.data_root, "real_like"), None)] + [(v, None) for v in sim]
    if args.fixed_t is not None:
        for layout, src in layouts:
            print(fixed_t(layout, src, args.fixed_t), flush=True)
        return
    if args.draw:
        args.draw.mkdir(parents=True, exist_ok=True)
    jobs = [(layout, src, args.draw) for layout, src in layouts]
    if args.jobs > 1:
        with Pool(args.jobs) as pool:
            per = pool.map(_study, jobs, chunksize=1)
    else:
        per = [_study(j) for j in jobs]
    rows = sum(per, [])
    if args.rows:
        args.rows.write_text(json.dumps(rows))
    print("\n".join(verdict(rows, args.real_building)))


if __name__ == "__main__":
    main()
