"""Does a cell's structure continue across the frame bars around it? A pane mirrors a scene that goes on
behind the bar into its neighbour; a unit without glass (an opening) shows its own box, which stops at the
frame. Per bar between two neighbouring candidate panels of a rectified view: the profiles along the bar of a
strip beside it on either side (STRIP of the pitch wide, SKIP of the bar's width clear of it), high-passed
(SMOOTH of the pitch), each divided by its local contrast, compared by the NCC, best over shifts up to SHIFT
of the pitch (a pane's tilt); no vote where both sides are flat (RMS under FLAT grey levels) or too little is
shown. A cell is labelled by the truth as ``bench_opening_cue.py`` did (an opening: less than half of the
panel truth glass).

Prints, per family of scenes: the AUC of the cell's best continuation (lower: an opening) over the cells with
a vote and over all cells (no vote: taken as continuing); the openings caught and the glass panels lost by two
rules at the threshold t that catches the most openings of the simulated scenes (``--sim``) while losing at
most 2 % of their glass panels (rule A: every voting side of the cell continues below t; rule C: rule A, and a
neighbour across one of them continues at t or above with another cell, so the view's glass does continue
there); then the chance table: the median NCC of glass|glass bars, of glass|opening bars, and of a glass|glass
bar's first side against another glass|glass bar's second side (unrelated profiles, the chance level).

Inputs: gcw_dev and real_like in ``--data-root`` through segment_panels (as ``bench_segmentation.py`` leaves
them), gcw_dev's photos with truth (``--real``), and real_like's variants rl_v1..rl_v6 through segment_panels
under ``--sim-root`` (default DATA_ROOT/sim) with their building configs in ``--sim-configs`` (default
DATA_ROOT/sim_configs), as 60b21d5's ``bench_opening_cue.py`` made them.

    python benchmarks/bench_opening_continuity.py --data-root D --real ../shared/real/gcw_dev \
        [--sim-root D/sim] [--sim-configs D/sim_configs] [--sim real_like rl_v1 ...]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_segmentation import truth_views  # noqa: E402

from facade_pipeline.io.images import read_image  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.segmentation.real_truth import quad_mask  # noqa: E402

VARIANTS = ("rl_v1", "rl_v2", "rl_v3", "rl_v4", "rl_v5", "rl_v6")
SKIP = 0.15  # of the bar's width found, kept clear of each side of it (beside a minimum of 2 px)
STRIP = 0.02  # of the pitch across the bar: the strip's width (at least 2 px)
SMOOTH = 0.1  # of the pitch along the bar: the high-pass's smoothing
SHIFT = 0.04  # of the pitch along the bar: the search over shift (pane tilt)
FLAT = 2.0  # 8-bit grey levels: a high-passed profile whose RMS is below this is flat
LOST = 0.02  # of the simulated scenes' glass panels, the most a threshold may call openings


def _inner_box(c: np.ndarray) -> tuple[float, float, float, float]:
    """x0, x1, y0, y1 of the largest axis-aligned box inside a rectified panel's quad."""
    return max(c[0, 0], c[3, 0]), min(c[1, 0], c[2, 0]), max(c[2, 1], c[3, 1]), min(c[0, 1], c[1, 1])


def _smooth1d(x: np.ndarray, s: float) -> np.ndarray:
    k = max(3, int(round(s)) | 1)
    x2 = x.reshape(len(x), -1).astype(np.float32)
    y = cv2.GaussianBlur(x2, (1, k), s / 2.5, borderType=cv2.BORDER_REFLECT).reshape(x2.shape)
    return y.reshape(x.shape)


def _hp(p: np.ndarray, s: float) -> np.ndarray:
    return p - _smooth1d(p, s)


def _strip(lum, ok, vertical, a, b, lo, hi):
    """Mean profile of the strip [a, b) across, [lo, hi) along; per-position validity."""
    if vertical:
        return lum[lo:hi, a:b].mean(1), ok[lo:hi, a:b].all(1)
    return lum[a:b, lo:hi].mean(0), ok[a:b, lo:hi].all(0)


def _best_ncc(np_, nq, vp, vq, m):
    """The best NCC of two normalised profiles over shifts up to ``m`` px (-1: no shift with 16 valid px)."""
    best = -1.0
    n = len(np_)
    for d in range(-m, m + 1):
        i0, i1 = max(0, d), min(n, n + d)
        if i1 - i0 < 16:
            continue
        x, y, vv = np_[i0:i1], nq[i0 - d:i1 - d], (vp[i0:i1] & vq[i0 - d:i1 - d])
        if vv.sum() < 16:
            continue
        x, y = x[vv] - x[vv].mean(), y[vv] - y[vv].mean()
        den = np.sqrt((x ** 2).sum() * (y ** 2).sum())
        if den > 0:
            best = max(best, float((x * y).sum() / den))
    return best


def bar_ncc(lum, ok, vertical, gap0, gap1, lo, hi, pitch_across, pitch_along):
    """(best NCC over shifts or None where no evidence, rms of each side's high-passed profile, the
    normalised profiles and their validity as ``_best_ncc`` took them or None)."""
    gap = max(gap1 - gap0, 0.0)
    skip = max(2.0, SKIP * gap)
    w = max(2, int(round(STRIP * pitch_across)))
    a1 = int(np.floor(gap0 - skip)) - w
    b0 = int(np.ceil(gap1 + skip))
    n_across = lum.shape[1] if vertical else lum.shape[0]
    lo, hi = int(np.ceil(lo)), int(np.floor(hi))
    if a1 < 0 or b0 + w > n_across or hi - lo < 16:
        return None, 0.0, 0.0, None
    p, vp = _strip(lum, ok, vertical, a1, a1 + w, lo, hi)
    q, vq = _strip(lum, ok, vertical, b0, b0 + w, lo, hi)
    s = SMOOTH * pitch_along
    hp, hq = _hp(p, s), _hp(q, s)
    # local contrast: the smoothed magnitude of the high-passed profile
    cp = np.sqrt(_smooth1d(hp ** 2, 2 * s)) + FLAT / 2
    cq = np.sqrt(_smooth1d(hq ** 2, 2 * s)) + FLAT / 2
    v = vp & vq
    rp = float(np.sqrt((hp[vp] ** 2).mean())) if vp.sum() > 8 else 0.0
    rq = float(np.sqrt((hq[vq] ** 2).mean())) if vq.sum() > 8 else 0.0
    if max(rp, rq) < FLAT or v.sum() < 16:
        return None, rp, rq, None
    m = int(round(SHIFT * pitch_along))
    prof = (hp / cp, hq / cq, vp, vq, m)
    return _best_ncc(*prof), rp, rq, prof


def view_bars(rimg: np.ndarray, panels: list):
    """Per bar between neighbouring panels of a rectified view: (i, j, ncc, rms_i, rms_j, profiles,
    vertical); i left of or below j."""
    lum = rimg.astype(np.float32).mean(2)
    ok = (rimg.max(2) > 0) & (rimg.max(2) < 250)
    boxes = [_inner_box(np.asarray(p.corners_rectified_px, float)) for p in panels]
    where = {(p.row, p.col): k for k, p in enumerate(panels)}
    cx = {k: (b[0] + b[1]) / 2 for k, b in enumerate(boxes)}
    cy = {k: (b[2] + b[3]) / 2 for k, b in enumerate(boxes)}
    px = [cx[where[(p.row, p.col + 1)]] - cx[k] for k, p in enumerate(panels) if (p.row, p.col + 1) in where]
    py = [cy[k] - cy[where[(p.row + 1, p.col)]] for k, p in enumerate(panels) if (p.row + 1, p.col) in where]
    # cut panels' centres are off: the median over the view
    pitch_x = float(np.median(px)) if px else None
    pitch_y = float(np.median(py)) if py else None
    pitch_x = pitch_x or (pitch_y or 100.0) * 0.67
    pitch_y = pitch_y or pitch_x * 1.5
    out = []
    for i, p in enumerate(panels):
        x0, x1, y0, y1 = boxes[i]
        j = where.get((p.row, p.col + 1))
        if j is not None:
            X0, X1, Y0, Y1 = boxes[j]
            lo, hi = max(y0, Y0), min(y1, Y1)
            cut = 0.05 * pitch_y
            out.append((i, j, *bar_ncc(lum, ok, True, x1, X0, lo + cut, hi - cut, pitch_x, pitch_y), True))
        j = where.get((p.row + 1, p.col))  # rows count from the bottom: row + 1 lies above
        if j is not None:
            X0, X1, Y0, Y1 = boxes[j]
            lo, hi = max(x0, X0), min(x1, X1)
            cut = 0.05 * pitch_x
            out.append((j, i, *bar_ncc(lum, ok, False, Y1, y0, lo + cut, hi - cut, pitch_y, pitch_x), False))
    return out


def samples(layout: BuildingLayout, src: Path | None) -> list:
    """Per view of a building with truth: (labels [n] True: an opening, panels, bars)."""
    out = []
    for stem, seg, mask, _, _ in truth_views(layout, src):
        rimg = read_image(layout.path("rectify_image", stem=stem))
        H, W = mask.shape
        panels = list(seg.panels)
        lab = []
        for p in panels:
            m = quad_mask(p.corners_px, W, H)
            lab.append((float(mask[m].mean()) if m.any() else 0.0) < 0.5)
        out.append((np.array(lab, bool), panels, view_bars(rimg, panels)))
    return out


def auc(score: np.ndarray, y: np.ndarray) -> float:
    """P(an opening scores above a glass panel), ties half."""
    score, y = np.asarray(score, float), np.asarray(y, bool)
    a, b = score[y][:, None], score[~y][None, :]
    return float(((a > b) + 0.5 * (a == b)).mean()) if len(a) and b.size else float("nan")


def _sides(n: int, bars: list) -> dict:
    """Per cell: (neighbour, NCC) of each of its voting sides."""
    sides = {k: [] for k in range(n)}
    for i, j, ncc, *_ in bars:
        if ncc is not None:
            sides[i].append((j, ncc))
            sides[j].append((i, ncc))
    return sides


def cell_scores(panels: list, bars: list) -> np.ndarray:
    """Per cell: the best continuation over its voting sides (nan: none votes)."""
    sides = _sides(len(panels), bars)
    return np.array([max(c for _, c in sides[k]) if sides[k] else np.nan for k in range(len(panels))])


def called(panels: list, bars: list, t: float) -> np.ndarray:
    """Openings called by rule C at threshold t: every voting side of the cell continues below t, and a
    neighbour across one of them continues at t or above with another cell (so the view's glass does
    continue here)."""
    sides = _sides(len(panels), bars)
    out = np.zeros(len(panels), bool)
    for k in range(len(panels)):
        if not sides[k] or max(c for _, c in sides[k]) >= t:
            continue
        out[k] = any(any(cc >= t for jj, cc in sides[j] if jj != k) for j, _ in sides[k])
    return out


def count(views: list, t: float, rule: str) -> tuple[int, int, int, int]:
    """Openings caught, openings, glass panels lost, glass panels of a family at threshold t."""
    y, c = [], []
    for lab, panels, bars in views:
        if rule == "A":
            A = cell_scores(panels, bars)
            c.append(np.isfinite(A) & (A < t))
        else:
            c.append(called(panels, bars, t))
        y.append(lab)
    y, c = np.concatenate(y), np.concatenate(c)
    return int((c & y).sum()), int(y.sum()), int((c & ~y).sum()), int((~y).sum())


def threshold(data: dict, sim: list[str], rule: str) -> float:
    """The threshold that catches the most openings of the simulated scenes while losing at most LOST of
    their glass panels."""
    best, most = None, -1
    for t in np.arange(-0.2, 1.0, 0.01):
        got = [count(data[nm], t, rule) for nm in sim]
        lost, glass, caught = (sum(g[k] for g in got) for k in (2, 3, 0))
        if lost <= LOST * glass and caught > most:
            best, most = t, caught
    return best


def chance(data: dict) -> list[str]:
    """Rows of the chance table: per family, the median NCC of glass|glass bars, of glass|opening bars and
    of each glass|glass bar's first side against another's second side (a random one, at random offsets)."""
    rng = np.random.default_rng(0)
    rows = []
    for name, views in data.items():
        gg, go, profs, rnd = [], [], [], []
        for lab, _, bars in views:
            for i, j, ncc, _, _, prof, _ in bars:
                if ncc is None:
                    continue
                if not lab[i] and not lab[j]:
                    gg.append(ncc)
                    profs.append(prof)
                elif lab[i] != lab[j]:
                    go.append(ncc)
        for a in range(len(profs)):
            c = rng.integers(len(profs) - 1)
            c += c >= a
            p, q = profs[a], profs[c]
            n = min(len(p[0]), len(q[1]))
            s0, s1 = rng.integers(len(p[0]) - n + 1), rng.integers(len(q[1]) - n + 1)
            rnd.append(_best_ncc(p[0][s0:s0 + n], q[1][s1:s1 + n], p[2][s0:s0 + n], q[3][s1:s1 + n], p[4]))
        med = [f"{np.median(v):.2f} ({len(v)})" if v else "-" for v in (gg, go, rnd)]
        rows.append(f"| {name} | {' | '.join(med)} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-root", type=Path, required=True,
                    help="gcw_dev and real_like through segment_panels")
    ap.add_argument("--real", type=Path, required=True, help="gcw_dev's photos with truth")
    ap.add_argument("--sim-root", type=Path,
                    help="real_like's variants through segment_panels (DATA_ROOT/sim)")
    ap.add_argument("--sim-configs", type=Path, help="the variants' config folder (DATA_ROOT/sim_configs)")
    ap.add_argument("--sim", nargs="+", default=["real_like", *VARIANTS],
                    help="the simulated scenes the thresholds are chosen on")
    args = ap.parse_args()
    sim_root = args.sim_root or args.data_root / "sim"
    sim_configs = args.sim_configs or args.data_root / "sim_configs"
    data = {"gcw_dev": samples(BuildingLayout(args.data_root, "gcw_dev"), args.real.resolve()),
            "real_like": samples(BuildingLayout(args.data_root, "real_like"), None)}
    os.environ["FACADE_CONFIG_DIR"] = str(sim_configs)
    for name in VARIANTS:
        if (sim_root / name).is_dir():
            data[name] = samples(BuildingLayout(sim_root, name), None)
    rules = {rule: threshold(data, args.sim, rule) for rule in ("A", "C")}
    lines = [f"thresholds chosen on {', '.join(args.sim)}: rule A t = {rules['A']:.2f}, "
             f"rule C t = {rules['C']:.2f}", "",
             "| family | cells / openings | voting cells, openings / glass | AUC, voting cells (all cells) "
             "| rule A caught / openings, lost / glass | rule C caught / openings, lost / glass |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, views in data.items():
        y = np.concatenate([lab for lab, _, _ in views])
        A = np.concatenate([cell_scores(panels, bars) for _, panels, bars in views])
        v = np.isfinite(A)
        got = [count(views, rules[rule], rule) for rule in ("A", "C")]
        lines.append(f"| {name} | {len(y)} / {int(y.sum())} | {int(v[y].sum())} / {int(v[~y].sum())} | "
                     f"{auc(-A[v], y[v]):.2f} ({auc(np.nan_to_num(-A, nan=-1.0), y):.2f}) | "
                     + " | ".join(f"{g[0]} / {g[1]}, {g[2]} / {g[3]}" for g in got) + " |")
    lines += ["", "| family | median NCC (bars): glass / glass | glass / opening | unrelated glass sides |",
              "| --- | --- | --- | --- |", *chance(data)]
    print("\n".join(lines))


if __name__ == "__main__":
    main()
