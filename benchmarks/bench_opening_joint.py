"""How well a logistic regression over per-panel cues tells an opening (a frame cell without glass, which
segment_panels takes for a glass panel) from a glass panel when trained on both families of scenes at once:
the simulated real-like scenes and gcw_dev's real photos, each family with equal total weight. gcw_dev is
scored leave-one-photo-out (the other photos and every simulated scene in training), each simulated scene
held out in turn (the other simulated scenes and every gcw_dev photo in training). A panel is an opening
where less than half of it is truth glass (as ``real_truth.mask_losses`` counts a false panel).

The features, all measured relative to the same view: the 13 of ``FEATURES`` (texture, clipped light,
colour, continuity across the bars), ``clipped_view`` (the clipped fraction less the view's median) and the
five of ``EXTRA`` (blue and 90th-percentile saturation against the view, the gradient in the panel's border
band against its centre, the top-to-bottom brightness slope, the saturation over the neighbours'). The model:
Newton's method, an L2 penalty of 1.0 on the standardised weights, an opening where p > 0.5.
Prints, per feature set, the AUC, the openings caught and the glass panels lost on each family.

Inputs: ``DATA_ROOT`` holds gcw_dev (scripts/make_gcw_building.py) and real_like, both through
segment_panels (``bench_segmentation.py``); ``--real`` is gcw_dev's photos with truth. The variants of
real_like (``VARIANTS``: other seeds, three other units without glass each) are read from ``--sim-root``
(default ``DATA_ROOT/sim``); any missing there is made from config copies written to ``--sim-configs``
(default ``DATA_ROOT/sim_configs``) and run through segment_panels.

    .venv/bin/python benchmarks/bench_opening_joint.py --data-root /tmp/d --real ../shared/real/gcw_dev \
        [--sim-root /tmp/d/sim] [--sim-configs /tmp/d/sim_configs]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_segmentation import truth_views  # noqa: E402

from facade_pipeline.io.images import read_image  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.segmentation.quads import inside_quads  # noqa: E402
from facade_pipeline.segmentation.real_truth import quad_mask  # noqa: E402

#: the simulated variants of real_like: (seed, units without glass as (part, row, col))
VARIANTS = {
    "rl_v1": (101, [[0, 2, 0], [0, 1, 3], [0, 0, 2]]),
    "rl_v2": (202, [[0, 1, 0], [0, 2, 2], [0, 0, 4]]),
    "rl_v3": (303, [[0, 0, 1], [0, 1, 2], [0, 2, 4]]),
    "rl_v4": (404, [[0, 2, 1], [0, 1, 4], [0, 0, 0]]),
    "rl_v5": (505, [[0, 2, 3], [0, 1, 1], [0, 0, 4]]),
    "rl_v6": (606, [[0, 0, 3], [0, 2, 2], [0, 1, 0]]),
}
FEATURES = ("texture", "clipped", "chroma", "spread", "axial", "lum_view", "lum_frame", "saturation",
            "sat_frame", "sat_view", "cont_min", "cont_median", "cont_max")
PATCH = 48  # px of the square each panel's inner quad is resampled to
SHRINK = 0.08  # of the quad's size, kept clear of the bars on each side
STRIP = 3  # px (rectified) of the strips compared across a bar
MARGIN = 2  # px (rectified) between a strip and the panel's edge
EXTRA = ("blue_view", "sat90_view", "band_ratio", "slope_view", "sat_nb")
#: the feature sets of the table
SETS = {
    "the 13": FEATURES,
    "the 13 + clipped_view": FEATURES + ("clipped_view",),
    "all 19": FEATURES + ("clipped_view",) + EXTRA,
}
RIDGE = 1.0


def make_variants(sim_root: Path, sim_configs: Path) -> list[BuildingLayout]:
    """real_like's variants (``VARIANTS``: each room's style drawn anew) under ``sim_root``; those not yet
    through segment_panels are made from config copies written to ``sim_configs``."""
    env = {**os.environ, "FACADE_CONFIG_DIR": str(sim_configs), "TQDM_DISABLE": "1"}
    out = []
    for name, (seed, units) in VARIANTS.items():
        layout = BuildingLayout(sim_root, name)
        out.append(layout)
        if layout.path("segment_corners", stem="frontal_0000").is_file():
            continue
        (sim_configs / "buildings").mkdir(parents=True, exist_ok=True)
        for cfg in ("default.toml", "synthetic.toml"):
            (sim_configs / cfg).write_text((REPO / "configs" / cfg).read_text())
        text = (REPO / "configs" / "buildings" / "real_like.toml").read_text()
        text = re.sub(r"(?m)^seed = .*$", f"seed = {seed}", text)
        text = re.sub(r"(?m)^unglazed_units = .*$", f"unglazed_units = {json.dumps(units)}", text)
        (sim_configs / "buildings" / f"{name}.toml").write_text(text)
        for stage in ("synthesize", "import_photogrammetry", "rectify", "segment_panels"):
            print(f"{name}: {stage}", file=sys.stderr, flush=True)
            subprocess.run([sys.executable, "-m", "stages", stage, "--building", name, "--data-root",
                            str(sim_root)], cwd=REPO, env=env, check=True, capture_output=True)
    return out


def _patch(img: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The inner quad of ``corners`` [4, 2] (bottom-left, bottom-right, top-right, top-left) resampled to
    PATCH x PATCH."""
    c = np.asarray(corners, float)
    c = c.mean(0) + (1 - 2 * SHRINK) * (c - c.mean(0))
    dst = np.float32([[0, PATCH], [PATCH, PATCH], [PATCH, 0], [0, 0]])
    m = cv2.getPerspectiveTransform(np.float32(c), dst)
    return cv2.warpPerspective(img, m, (PATCH, PATCH), flags=cv2.INTER_AREA)


def _inner_box(c: np.ndarray) -> tuple[float, float, float, float]:
    """x0, x1, y0, y1 of the largest axis-aligned box inside a rectified panel's quad."""
    return max(c[0, 0], c[3, 0]), min(c[1, 0], c[2, 0]), max(c[2, 1], c[3, 1]), min(c[0, 1], c[1, 1])


def _profile(f: np.ndarray, valid: np.ndarray, vertical: bool, pos: float, lo: float, hi: float):
    """The colour profile [n, 3] along a strip STRIP px wide starting at ``pos`` across, [lo, hi) along,
    and where it shows the view; None off the image."""
    H, W = f.shape[:2]
    lo, hi, a = int(np.ceil(lo)), int(np.floor(hi)), int(round(pos))
    if hi <= lo or a < 0 or a + STRIP > (W if vertical else H):
        return None
    if vertical:
        return f[lo:hi, a:a + STRIP].mean(1), valid[lo:hi, a:a + STRIP].all(1)
    return f[a:a + STRIP, lo:hi].mean(0), valid[a:a + STRIP, lo:hi].all(0)


def _continuity(f: np.ndarray, valid: np.ndarray, boxes: list, panels: list, i: int) -> list[float]:
    """Per side of panel ``i`` with a neighbouring panel: log of the colour difference between the strips
    either side of the bar over the difference between this panel's strip and one as far again inside it
    (a reflection that continues across the bar: about 0; content that stops at the frame: > 0)."""
    x0, x1, y0, y1 = boxes[i]
    where = {(p.row, p.col): k for k, p in enumerate(panels)}
    out = []
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        j = where.get((panels[i].row + dr, panels[i].col + dc))
        if j is None:
            continue
        X0, X1, Y0, Y1 = boxes[j]
        if dc:
            lo, hi = max(y0, Y0) + 2, min(y1, Y1) - 2
            mine, theirs = ((x1 - MARGIN - STRIP, X0 + MARGIN) if dc == 1
                            else (x0 + MARGIN, X1 - MARGIN - STRIP))
        else:  # rows count from the bottom: row + 1 lies above
            lo, hi = max(x0, X0) + 2, min(x1, X1) - 2
            mine, theirs = ((y0 + MARGIN, Y1 - MARGIN - STRIP) if dr == 1
                            else (y1 - MARGIN - STRIP, Y0 + MARGIN))
        inner = mine - (theirs - mine)
        got = [_profile(f, valid, bool(dc), x, lo, hi) for x in (mine, theirs, inner)]
        if any(g is None for g in got):
            continue
        ok = got[0][1] & got[1][1] & got[2][1]
        if ok.sum() < 8:
            continue
        a, b, c = (g[0][ok] for g in got)
        across, within = np.abs(a - b).sum(1).mean(), np.abs(a - c).sum(1).mean()
        out.append(float(np.log((across + 0.01) / (within + 0.01))))
    return out


def view_features(rimg: np.ndarray, panels: list) -> list[dict | None]:
    """The features (``FEATURES``) of each panel of one rectified view (None: too little of it shown)."""
    f = rimg.astype(np.float32) / 255
    valid = rimg.max(2) > 0
    lum = f.mean(2)
    gx, gy = cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3)
    quads = [np.asarray(p.corners_rectified_px, float) for p in panels]
    P = [_patch(f, q) for q in quads]
    V = [_patch(valid.astype(np.float32), q) > 0.5 for q in quads]
    C = [_patch((rimg.max(2) >= 250).astype(np.float32), q) for q in quads]
    GX, GY = [_patch(gx, q) for q in quads], [_patch(gy, q) for q in quads]
    shown = [v.sum() > 20 for v in V]
    if not any(shown):
        return [None] * len(panels)
    ys, xs = np.mgrid[0:rimg.shape[0], 0:rimg.shape[1]] + 0.5
    inside = inside_quads(quads, xs, ys) >= 0
    ring = cv2.dilate(inside.astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool) & ~inside & valid
    frame = float(np.median(lum[ring])) if ring.any() else float(np.median(lum[valid]))
    # the frames' colour as the view's white (a von Kries balance): a frame is near grey, a white balance
    # off tints it as much as the glass
    white = np.median(f[ring] if ring.any() else f[valid], axis=0) + 1e-3
    unclipped = [v & (p.max(2) < 250 / 255) for p, v in zip(P, V, strict=True)]
    sat_frame = []
    for p, u in zip(P, unclipped, strict=True):
        q = p[u] / white
        sat = float(np.median((q.max(1) - q.min(1)) / (q.max(1) + 1e-3))) if u.sum() > 20 else np.nan
        sat_frame.append(sat)
    each = list(zip(P, V, shown, strict=True))
    grad = [float(np.hypot(gx_[v], gy_[v]).mean()) if s else np.nan
            for gx_, gy_, v, s in zip(GX, GY, V, shown, strict=True)]
    mean = [p[v].mean(0) if s else np.full(3, np.nan) for p, v, s in each]
    chrom = [m / max(float(m.sum()), 1e-3) for m in mean]
    spread = [float(p[v].mean(1).std()) if s else np.nan for p, v, s in each]
    light = [float(np.median(p[v].mean(1))) if s else np.nan for p, v, s in each]
    ref = dict(grad=np.nanmedian(grad), chrom=np.nanmedian(chrom, axis=0), spread=np.nanmedian(spread),
               light=np.nanmedian(light), sat=np.nanmedian(sat_frame))
    boxes = [_inner_box(q) for q in quads]
    out = []
    for k in range(len(panels)):
        if not shown[k]:
            out.append(None)
            continue
        v = V[k]
        e = GX[k][v] ** 2 + GY[k][v] ** 2
        ang = np.arctan2(GY[k][v], GX[k][v])
        px = P[k][v]
        cont = _continuity(f, valid, boxes, panels, k) or [0.0]
        out.append({
            "texture": np.log(grad[k] / max(ref["grad"], 1e-6) + 1e-3),
            "clipped": float(C[k][v].mean()),
            "chroma": 100 * float(np.linalg.norm(chrom[k] - ref["chrom"])),
            "spread": spread[k] / max(ref["spread"], 1e-3),
            "axial": float((e * np.cos(2 * ang) ** 2).sum() / max(e.sum(), 1e-9)),
            "lum_view": float(np.log((light[k] + 0.02) / (ref["light"] + 0.02))),
            "lum_frame": float(np.log((light[k] + 0.02) / (frame + 0.02))),
            "saturation": float(np.median((px.max(1) - px.min(1)) / (px.max(1) + 1e-3))),
            # a panel clipped all over shows no colour: no evidence either way, taken as the view's median
            "sat_frame": sat_frame[k] if np.isfinite(sat_frame[k]) else ref["sat"],
            "sat_view": sat_frame[k] / max(ref["sat"], 1e-3) if np.isfinite(sat_frame[k]) else 1.0,
            "cont_min": min(cont), "cont_median": float(np.median(cont)), "cont_max": max(cont),
        })
    return out




def view_extra(rimg: np.ndarray, panels: list) -> list[dict | None]:
    """The features of ``EXTRA`` of each panel of one rectified view (None where ``view_features`` has
    none: too little of the panel shown)."""
    f = rimg.astype(np.float32) / 255
    valid = rimg.max(2) > 0
    lum = f.mean(2)
    gx, gy = cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3)
    quads = [np.asarray(p.corners_rectified_px, float) for p in panels]
    P = [_patch(f, q) for q in quads]
    V = [_patch(valid.astype(np.float32), q) > 0.5 for q in quads]
    G = [np.hypot(_patch(gx, q), _patch(gy, q)) for q in quads]
    shown = [v.sum() > 20 for v in V]
    ys, xs = np.mgrid[0:rimg.shape[0], 0:rimg.shape[1]] + 0.5
    inside = inside_quads(quads, xs, ys) >= 0
    ring = cv2.dilate(inside.astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool) & ~inside & valid
    # the frames' colour as the view's white, as in view_features
    white = np.median(f[ring] if ring.any() else f[valid], axis=0) + 1e-3
    band = np.zeros((PATCH, PATCH), bool)
    b = PATCH // 4
    band[:b] = band[-b:] = True
    band[:, :b] = band[:, -b:] = True
    top = np.zeros((PATCH, PATCH), bool)
    top[:PATCH // 2] = True  # patch row 0 is the panel's top
    raw = []
    for p, v, g, s in zip(P, V, G, shown, strict=True):
        if not s:
            raw.append(None)
            continue
        u = v & (p.max(2) < 250 / 255)
        q = p[u] / white if u.sum() > 20 else None
        blue = float(np.median((q[:, 2] - q[:, 0]) / (q[:, 2] + q[:, 0] + 1e-3))) if q is not None else np.nan
        sat = (q.max(1) - q.min(1)) / (q.max(1) + 1e-3) if q is not None else None
        sat90 = float(np.percentile(sat, 90)) if sat is not None else np.nan
        sat50 = float(np.median(sat)) if sat is not None else np.nan
        ib, ic = v & band, v & ~band
        br = float(np.log((g[ib].mean() + 1e-3) / (g[ic].mean() + 1e-3))) if ib.any() and ic.any() else 0.0
        lm = p.mean(2)
        t, bo = v & top, v & ~top
        sl = float(np.log((lm[t].mean() + 0.02) / (lm[bo].mean() + 0.02))) if t.any() and bo.any() else 0.0
        raw.append(dict(blue=blue, sat90=sat90, br=br, sl=sl, sat50=sat50))
    ok = [r for r in raw if r is not None]
    med = {k: np.nanmedian([r[k] for r in ok]) if ok else 0.0 for k in ("blue", "sat90", "sl", "br")}
    where = {(p.row, p.col): k for k, p in enumerate(panels)}
    out = []
    for k, r in enumerate(raw):
        if r is None:
            out.append(None)
            continue
        around = [(panels[k].row + dr, panels[k].col + dc) for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0))]
        nb = [raw[where[rc]] for rc in around if rc in where]
        nbs = [x["sat50"] for x in nb if x is not None and np.isfinite(x["sat50"])]
        out.append(dict(
            blue_view=r["blue"] - med["blue"] if np.isfinite(r["blue"]) else 0.0,
            sat90_view=r["sat90"] / max(med["sat90"], 1e-3) if np.isfinite(r["sat90"]) else 1.0,
            band_ratio=r["br"] - med["br"],
            slope_view=r["sl"] - med["sl"],
            sat_nb=(r["sat50"] / max(float(np.max(nbs)), 1e-3)) if nbs and np.isfinite(r["sat50"]) else 1.0))
    return out


def samples(layout: BuildingLayout, src: Path | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features [n, F] (the columns of ``SETS["all 19"]``), labels [n] (True: an opening) and views [n] of
    every panel of a building."""
    X, y, views = [], [], []
    for stem, seg, mask, _, _ in truth_views(layout, src):
        rimg = read_image(layout.path("rectify_image", stem=stem))
        H, W = mask.shape
        panels = list(seg.panels)
        each = zip(panels, view_features(rimg, panels), view_extra(rimg, panels), strict=True)
        for p, feats, extra in each:
            if feats is None:
                continue
            m = quad_mask(p.corners_px, W, H)
            X.append([feats[k] for k in FEATURES] + [extra[k] for k in EXTRA])
            y.append((float(mask[m].mean()) if m.any() else 0.0) < 0.5)
            views.append(stem)
    X, views = np.nan_to_num(np.array(X, float)), np.array(views)
    # how much more of the panel is clipped than of the view's other panels
    clipped = X[:, FEATURES.index("clipped")]
    clipped_view = np.zeros(len(clipped))
    for v in set(views):
        s = views == v
        clipped_view[s] = clipped[s] - np.median(clipped[s])
    X = np.c_[X[:, :len(FEATURES)], clipped_view, X[:, len(FEATURES):]]
    return X, np.array(y, bool), views


def fit(X: np.ndarray, y: np.ndarray, w: np.ndarray, ridge: float = RIDGE):
    """A weighted logistic regression (Newton's method, an L2 penalty on the weights of the features
    standardised over the weighted samples); returns p(X)."""
    w = w / w.sum() * len(w)
    mu = (w[:, None] * X).sum(0) / w.sum()
    sd = np.sqrt((w[:, None] * (X - mu) ** 2).sum(0) / w.sum()) + 1e-6
    Z = np.c_[(X - mu) / sd, np.ones(len(X))]
    b, pen = np.zeros(Z.shape[1]), ridge * np.r_[np.ones(Z.shape[1] - 1), 0.0]
    for _ in range(50):
        p = 1 / (1 + np.exp(-Z @ b))
        b -= np.linalg.solve((Z * (w * p * (1 - p))[:, None]).T @ Z + np.diag(pen),
                             Z.T @ (w * (p - y)) + pen * b)
    return lambda Xn: 1 / (1 + np.exp(-np.c_[(Xn - mu) / sd, np.ones(len(Xn))] @ b))


def auc(score: np.ndarray, y: np.ndarray) -> float:
    """P(an opening scores above a glass panel), ties half."""
    a, b = score[y][:, None], score[~y][None, :]
    return float(((a > b) + 0.5 * (a == b)).mean()) if len(a) and b.size else float("nan")


def family_weights(n_sim: int, n_real: int) -> np.ndarray:
    """Sample weights giving the simulated and the real family half the total weight each."""
    return np.r_[np.full(n_sim, 0.5 / n_sim), np.full(n_real, 0.5 / n_real)]


def evaluate(sims: dict, real: tuple, cols: list[int]) -> str:
    """The table row of the features ``cols``: gcw_dev leave-one-photo-out, each simulated scene held out."""
    Xs = np.concatenate([d[0][:, cols] for d in sims.values()])
    ys = np.concatenate([d[1] for d in sims.values()])
    scene = np.concatenate([[k] * len(d[1]) for k, d in sims.items()])
    Xr, yr, vr = real[0][:, cols], real[1], real[2]
    pr = np.zeros(len(yr))
    for v in sorted(set(vr)):
        t = vr == v
        f = fit(np.r_[Xs, Xr[~t]], np.r_[ys, yr[~t]], family_weights(len(ys), int((~t).sum())))
        pr[t] = f(Xr[t])
    ps = np.zeros(len(ys))
    for k in sims:
        t = scene == k
        f = fit(np.r_[Xs[~t], Xr], np.r_[ys[~t], yr], family_weights(int((~t).sum()), len(yr)))
        ps[t] = f(Xs[t])
    cells = []
    for p, y in ((pr, yr), (ps, ys)):
        cells += [f"{auc(p, y):.2f}", f"{int((p[y] > 0.5).sum())}/{int(y.sum())}",
                  f"{int((p[~y] > 0.5).sum())}/{int((~y).sum())}"]
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-root", type=Path, required=True, help="holds gcw_dev and real_like")
    ap.add_argument("--real", type=Path, required=True, help="gcw_dev's photos with truth")
    ap.add_argument("--sim-root", type=Path, help="the variants' data root (default DATA_ROOT/sim)")
    ap.add_argument("--sim-configs", type=Path,
                    help="where configs of variants still to be made go (default DATA_ROOT/sim_configs)")
    args = ap.parse_args()
    sim_root = args.sim_root or args.data_root / "sim"
    sim_configs = args.sim_configs or args.data_root / "sim_configs"
    layouts = [BuildingLayout(args.data_root, "real_like")] + make_variants(sim_root, sim_configs)
    sims = {layout.building: samples(layout, None) for layout in layouts}
    real = samples(BuildingLayout(args.data_root, "gcw_dev"), args.real.resolve())
    ys = np.concatenate([d[1] for d in sims.values()])
    print(f"simulated: {len(ys)} panels, {int(ys.sum())} openings ({len(sims)} scenes); "
          f"gcw_dev: {len(real[1])} panels, {int(real[1].sum())} openings\n")
    print("| features | gcw AUC | gcw caught | gcw lost | sim AUC | sim caught | sim lost |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    all_cols = SETS["all 19"]
    for name, cols in SETS.items():
        print(f"| {name} " + evaluate(sims, real, [all_cols.index(c) for c in cols]))


if __name__ == "__main__":
    main()
