"""Can a cell between frame bars be told to be glass or an opening (a unit without glass) from its own view?
Every candidate panel ``segment_panels`` wrote is described by features measured relative to the same view
(its other panels, its frames), never by absolute brightness or colour, and labelled by the truth (an opening:
less than half of the panel is truth glass, as ``real_truth.mask_losses`` counts a false panel). A logistic
regression over them is trained on simulated real-like scenes and tested on scenes it was not trained on: the
other simulated scenes, and gcw_dev's real photos (held out; also leave-one-photo-out with the other photos in
training, with and without the simulated scenes), and the other way, gcw_dev's photos to the simulated scenes.
Prints a table: per feature, the AUC of each family of scenes alone (0.5: no separation; < 0.5: the feature
points the other way); per evaluation, the AUC and, at p > 0.5, the openings caught and the glass panels lost.

The simulated scenes are ``real_like`` and variants of it (other seeds, three other units without glass
each), made under ``DATA_ROOT/sim`` from config copies and run through segment_panels; gcw_dev and
real_like must be in ``DATA_ROOT`` through segment_panels (``bench_segmentation.py``).

    python benchmarks/bench_opening_cue.py --data-root /tmp/d --real ../shared/real/gcw_dev
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
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
#: the features whose AUC points the same way on the simulated scenes and on gcw_dev (chosen by looking at
#: both: gcw_dev is not held out from this choice)
SAME_WAY = ("saturation", "sat_frame", "sat_view", "axial")
PATCH = 48  # px of the square each panel's inner quad is resampled to
SHRINK = 0.08  # of the quad's size, kept clear of the bars on each side
STRIP = 3  # px (rectified) of the strips compared across a bar
MARGIN = 2  # px (rectified) between a strip and the panel's edge


def make_variants(data_root: Path) -> list[BuildingLayout]:
    """real_like's variants (``VARIANTS``: each room's style drawn anew) made and segmented under
    ``data_root/sim`` from config copies."""
    cfg = data_root / "sim_configs"
    shutil.rmtree(cfg, ignore_errors=True)
    (cfg / "buildings").mkdir(parents=True)
    for name in ("default.toml", "synthetic.toml"):
        shutil.copy(REPO / "configs" / name, cfg / name)
    base = (REPO / "configs" / "buildings" / "real_like.toml").read_text()
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    out = []
    for name, (seed, units) in VARIANTS.items():
        text = re.sub(r"(?m)^seed = .*$", f"seed = {seed}", base)
        text = re.sub(r"(?m)^unglazed_units = .*$", f"unglazed_units = {json.dumps(units)}", text)
        (cfg / "buildings" / f"{name}.toml").write_text(text)
        layout = BuildingLayout(data_root / "sim", name)
        if not layout.path("segment_corners", stem="frontal_0000").is_file():
            for stage in ("synthesize", "import_photogrammetry", "rectify", "segment_panels"):
                print(f"{name}: {stage}", file=sys.stderr, flush=True)
                subprocess.run([sys.executable, "-m", "stages", stage, "--building", name, "--data-root",
                                str(data_root / "sim")], cwd=REPO, env=env, check=True, capture_output=True)
        out.append(layout)
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


def samples(layout: BuildingLayout, src: Path | None) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Features [n, F], labels [n] (True: an opening) and views [n] of every panel of a building."""
    X, y, views = [], [], []
    for stem, seg, mask, _, _ in truth_views(layout, src):
        rimg = read_image(layout.path("rectify_image", stem=stem))
        H, W = mask.shape
        for p, feats in zip(seg.panels, view_features(rimg, list(seg.panels)), strict=True):
            if feats is None:
                continue
            m = quad_mask(p.corners_px, W, H)
            X.append([feats[k] for k in FEATURES])
            y.append((float(mask[m].mean()) if m.any() else 0.0) < 0.5)
            views.append(f"{layout.building}/{stem}")
    return np.nan_to_num(np.array(X, float)), np.array(y, bool), views


def fit(X: np.ndarray, y: np.ndarray, ridge: float = 1.0):
    """A logistic regression (Newton's method, an L2 penalty on the standardised weights); returns p(X)."""
    mu, sd = X.mean(0), X.std(0) + 1e-6
    Z = np.c_[(X - mu) / sd, np.ones(len(X))]
    w, pen = np.zeros(Z.shape[1]), ridge * np.r_[np.ones(Z.shape[1] - 1), 0.0]
    for _ in range(50):
        p = 1 / (1 + np.exp(-Z @ w))
        w -= np.linalg.solve((Z * (p * (1 - p))[:, None]).T @ Z + np.diag(pen), Z.T @ (p - y) + pen * w)
    return lambda Xn: 1 / (1 + np.exp(-np.c_[(Xn - mu) / sd, np.ones(len(Xn))] @ w))


def auc(score: np.ndarray, y: np.ndarray) -> float:
    """P(an opening scores above a glass panel), ties half."""
    a, b = score[y][:, None], score[~y][None, :]
    return float(((a > b) + 0.5 * (a == b)).mean()) if len(a) and b.size else float("nan")


def verdict(name: str, p: np.ndarray, y: np.ndarray) -> str:
    caught, lost = int((p[y] > 0.5).sum()), int((p[~y] > 0.5).sum())
    return f"| {name} | {auc(p, y):.2f} | {caught} / {int(y.sum())} | {lost} / {int((~y).sum())} |"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data-root", type=Path, required=True)
    ap.add_argument("--real", type=Path, required=True, help="gcw_dev's photos with truth")
    args = ap.parse_args()
    sim = [BuildingLayout(args.data_root, "real_like")] + make_variants(args.data_root)
    data = {layout.building: samples(layout, None) for layout in sim}
    Xr, yr, vr = samples(BuildingLayout(args.data_root, "gcw_dev"), args.real.resolve())
    Xs = np.concatenate([d[0] for d in data.values()])
    ys = np.concatenate([d[1] for d in data.values()])
    lines = ["| feature | AUC, simulated | AUC, gcw_dev |", "| --- | --- | --- |"]
    lines += [f"| {k} | {auc(Xs[:, i], ys):.2f} | {auc(Xr[:, i], yr):.2f} |" for i, k in enumerate(FEATURES)]
    lines += ["", f"simulated: {len(ys)} panels, {int(ys.sum())} openings ({len(data)} scenes); "
              f"gcw_dev: {len(yr)} panels, {int(yr.sum())} openings", "",
              "| trained on -> tested on | AUC | openings caught | glass panels lost |",
              "| --- | --- | --- | --- |"]
    p = np.zeros(len(ys))
    at = np.cumsum([0] + [len(d[1]) for d in data.values()])
    for k in range(len(data)):
        test = np.zeros(len(ys), bool)
        test[at[k]:at[k + 1]] = True
        p[test] = fit(Xs[~test], ys[~test])(Xs[test])
    lines.append(verdict("the other simulated scenes -> each simulated scene", p, ys))
    for k, name in enumerate(data):
        sl = slice(at[k], at[k + 1])
        lines.append(verdict(f"the other simulated scenes -> {name}", p[sl], ys[sl]))
    lines.append(verdict("every simulated scene -> gcw_dev", fit(Xs, ys)(Xr), yr))
    same = [FEATURES.index(k) for k in SAME_WAY]
    lines.append(verdict(f"every simulated scene -> gcw_dev, {', '.join(SAME_WAY)} only",
                         fit(Xs[:, same], ys)(Xr[:, same]), yr))
    p = np.zeros(len(yr))
    for v in sorted(set(vr)):
        test = np.array([x == v for x in vr])
        p[test] = fit(np.r_[Xs, Xr[~test]], np.r_[ys, yr[~test]])(Xr[test])
    lines.append(verdict("the simulated scenes and gcw_dev's other photos -> each gcw_dev photo", p, yr))
    p = np.zeros(len(yr))
    for v in sorted(set(vr)):
        test = np.array([x == v for x in vr])
        p[test] = fit(Xr[~test], yr[~test])(Xr[test])
    lines.append(verdict("gcw_dev's other photos alone -> each gcw_dev photo", p, yr))
    lines.append(verdict("every gcw_dev photo -> every simulated scene", fit(Xr, yr)(Xs), ys))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
