"""Does a panel's content agree with the reflection the other views' panes show along the same mirrored rays?

A glass panel mirrors its surroundings: the ray from a view's camera to a sample of the panel, reflected in
the wall, meets the environment at a point that other views see mirrored in their own panes. An opening (a
cell between frame bars without glass) shows the room behind it instead, which the other panes do not mirror.
For every panel ``segment_panels`` wrote (labelled by the truth: an opening where less than half of it is
truth glass), N x N samples inside its quad (clear of the bars, blurred by a fraction of the panel width) are
reflected and looked up in every other view's panes; the panel's own unit in the other view is left out. The
environment the reflected rays end on is one of:

- ``inf``: at infinity (the rays' directions alone);
- ``sphere K``: a sphere of radius K panel pitches about the facade's centre;
- ``ground K``: the ground plane (the 1st percentile of the coarse points' height) for rays going down, the
  sphere of radius K pitches otherwise.

Each view pair's exposure is matched by the median log colour ratio over all its matched samples. Scores of a
panel (higher: less like glass):

- ``vote`` (per-sample median vote): the median over samples of the log colour distance to the per-sample
  median of the other views' votes;
- ``dmin`` / ``dmed`` (best-agreeing other panel / median over other panels): per panel of another view seen
  by at least MIN samples, the median log colour distance; the smallest / the median of these.

The acceptance rule: the threshold is the score that at most 2 % of the simulated scenes' glass panels exceed
(set on real_like and its variants only; an unscored panel is never lost), applied to the simulated scenes and
to gcw_dev. Prints a table of AUC and openings caught / glass panels lost per environment and score, with the
gcw_dev ceiling (the openings caught by the threshold fitted to gcw_dev itself, at 2 glass panels lost), then
per scene, then how well glass agrees with glass under each environment (median colour distance and NCC over
glass-glass panel pairs, each pair's exposure removed).

Inputs: gcw_dev and real_like in ``--data-root`` through segment_panels (``bench_segmentation.py``);
real_like's variants (``VARIANTS``) under ``--sim-root`` (default ``DATA_ROOT/sim``), made there where missing
from config copies written to ``--sim-configs`` (default ``DATA_ROOT/sim_configs``); gcw_dev's photos with
truth (``--real``).

    python benchmarks/bench_opening_mirror.py --data-root /tmp/d --real ../shared/real/gcw_dev
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
from facade_pipeline.io.meshes import read_points  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.rectification.surface_map import ViewRectification  # noqa: E402
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
#: (row label, environment, its radius in panel pitches, score)
ROWS = (
    ("infinite, per-sample median vote", "inf", None, "vote"),
    ("sphere 10, per-sample median vote", "sphere", 10.0, "vote"),
    ("ground 30, per-sample median vote", "ground", 30.0, "vote"),
    ("ground 30, best-agreeing other panel", "ground", 30.0, "dmin"),
    ("ground 30, median over other panels", "ground", 30.0, "dmed"),
)
N = 14  # samples per side of a panel
SHRINK = 0.1  # of the quad's size, kept clear of the bars on each side
BLUR = 1 / 35  # of the median panel width: the blur's sigma, so that a small misregistration matters little
MIN = 12  # samples a score needs
EPS = 2.0 / 255  # added before the log, so that dark samples do not dominate
ALLOWED = 0.02  # of the simulated glass panels, above the threshold


def make_variants(sim_root: Path, cfg: Path) -> list[BuildingLayout]:
    """real_like's variants (``VARIANTS``: each room's style drawn anew) under ``sim_root``; those not yet
    segmented are made there from config copies written to ``cfg``."""
    layouts = [BuildingLayout(sim_root, name) for name in VARIANTS]
    missing = [la for la in layouts if not la.path("segment_corners", stem="frontal_0000").is_file()]
    if not missing:
        return layouts
    shutil.rmtree(cfg, ignore_errors=True)
    (cfg / "buildings").mkdir(parents=True)
    for name in ("default.toml", "synthetic.toml"):
        shutil.copy(REPO / "configs" / name, cfg / name)
    base = (REPO / "configs" / "buildings" / "real_like.toml").read_text()
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    for name, (seed, units) in VARIANTS.items():
        text = re.sub(r"(?m)^seed = .*$", f"seed = {seed}", base)
        text = re.sub(r"(?m)^unglazed_units = .*$", f"unglazed_units = {json.dumps(units)}", text)
        (cfg / "buildings" / f"{name}.toml").write_text(text)
    for layout in missing:
        for stage in ("synthesize", "import_photogrammetry", "rectify", "segment_panels"):
            print(f"{layout.building}: {stage}", file=sys.stderr, flush=True)
            subprocess.run([sys.executable, "-m", "stages", stage, "--building", layout.building,
                            "--data-root", str(sim_root)], cwd=REPO, env=env, check=True, capture_output=True)
    return layouts


def auc(score: np.ndarray, y: np.ndarray) -> float:
    """P(an opening scores above a glass panel), ties half, over the scored panels."""
    ok = np.isfinite(score)
    a, b = score[ok & y][:, None], score[ok & ~y][None, :]
    return float(((a > b) + 0.5 * (a == b)).mean()) if len(a) and b.size else float("nan")


def view_samples(layout: BuildingLayout, stem: str, seg, mask: np.ndarray) -> list[dict]:
    """Per panel of one view: its samples' colours (blurred, 8-bit), the wall points and reflected rays they
    stand for, which of them are usable (shown, not clipped), and its truth label."""
    rect = ViewRectification.load(layout.path("rectify_mapping", stem=stem))
    rimg = read_image(layout.path("rectify_image", stem=stem))
    H, W = mask.shape
    f = rimg.astype(np.float32)
    valid = rimg.max(2) > 0
    clipped = rimg.max(2) >= 250
    quads = [np.asarray(p.corners_rectified_px, float) for p in seg.panels]
    if not quads:
        return []
    widths = [np.linalg.norm(q[1] - q[0]) for q in quads]
    fb = cv2.GaussianBlur(f, (0, 0), max(0.5, float(np.median(widths)) * BLUR))
    ys, xs = np.mgrid[0:rimg.shape[0], 0:rimg.shape[1]] + 0.5
    inside = inside_quads(quads, xs, ys) >= 0
    ring = cv2.dilate(inside.astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool)
    ring &= ~inside & valid & ~clipped
    # the frames' colour as the view's white
    white = np.median(f[ring] if ring.sum() > 50 else f[valid & ~clipped], axis=0) + 1.0
    # clipped anywhere in the blur's reach
    near_clipped = cv2.dilate(clipped.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    c = rect.chart
    m = rect.metres_per_px
    u = (np.arange(N) + 0.5) / N * (1 - 2 * SHRINK) + SHRINK
    U, V = np.meshgrid(u, u)
    U, V = U.ravel(), V.ravel()
    out = []
    for p, q in zip(seg.panels, quads, strict=True):
        # bilinear in the quad: corners bottom-left, bottom-right, top-right, top-left
        bl, br, tr, tl = q
        pts = ((1 - U)[:, None] * ((1 - V)[:, None] * bl + V[:, None] * tl)
               + U[:, None] * ((1 - V)[:, None] * br + V[:, None] * tr))
        xi = np.clip(pts[:, 0].astype(int), 0, rimg.shape[1] - 1)
        yi = np.clip(pts[:, 1].astype(int), 0, rimg.shape[0] - 1)
        ok = valid[yi, xi] & ~near_clipped[yi, xi]
        P = c.point(rect.s0_m + pts[:, 0] * m, rect.h0_m - pts[:, 1] * m)
        d = P - rect.camera.center
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        r = d - 2 * (d @ c.normal)[:, None] * c.normal
        centre = c.point(np.array([rect.s0_m + q[:, 0].mean() * m]),
                         np.array([rect.h0_m - q[:, 1].mean() * m]))[0]
        mq = quad_mask(p.corners_px, W, H)
        frac = float(mask[mq].mean()) if mq.any() else 0.0
        out.append(dict(stem=stem, row=p.row, col=p.col, centre=centre, P=P, r=r, col_raw=fb[yi, xi],
                        white=white, ok=ok, quad=q, opening=frac < 0.5, complete=p.complete,
                        width_m=float(np.linalg.norm(q[1] - q[0])) * m, right=c.right, up=c.up))
    return out


def complete_pitch(panels: list[dict]) -> tuple[float, float]:
    """The panel pitch along the wall's right and up, from neighbouring complete panels' centres per view;
    NaN along a direction without such a pair (real_like and its variants have no two complete panels one
    above the other in any view: their pitch up is NaN, so ``gather`` leaves no panel's own unit out
    there)."""
    px, py = [], []
    by = {}
    for p in panels:
        if p["complete"]:
            by.setdefault(p["stem"], {})[(p["row"], p["col"])] = p
    for v in by.values():
        for (r, cc), p in v.items():
            if (r, cc + 1) in v:
                px.append(abs((v[(r, cc + 1)]["centre"] - p["centre"]) @ p["right"]))
            if (r + 1, cc) in v:
                py.append(abs((v[(r + 1, cc)]["centre"] - p["centre"]) @ p["up"]))
    return float(np.median(px)), float(np.median(py))


class ViewImage:
    """One rectified view as a mirror: what its panes show toward given environment points or directions."""

    def __init__(self, layout: BuildingLayout, stem: str, panels: list[dict]):
        self.stem = stem
        self.rect = ViewRectification.load(layout.path("rectify_mapping", stem=stem))
        rimg = read_image(layout.path("rectify_image", stem=stem))
        self.img = rimg
        self.panels = [p for p in panels if p["stem"] == stem]
        self.quads = [p["quad"] for p in self.panels]
        widths = [p["width_m"] / self.rect.metres_per_px for p in self.panels] or [50]
        sigma = max(0.5, float(np.median(widths)) * BLUR)
        self.blur = cv2.GaussianBlur(rimg.astype(np.float32), (0, 0), sigma)
        clipped = rimg.max(2) >= 250
        self.bad = cv2.dilate(clipped.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        self.bad |= rimg.max(2) == 0
        self.white = self.panels[0]["white"] if self.panels else np.ones(3)
        cam = self.rect.camera.center
        c = self.rect.chart
        self.mirror_cam = cam - 2 * ((cam - c.origin) @ c.normal) * c.normal

    def lookup(self, E: np.ndarray, inf: bool):
        """colour [n, 3] over the view's white, ok [n], panel index [n] of what this view's panes mirror
        toward E (points, or directions where ``inf``)."""
        c = self.rect.chart
        o = self.mirror_cam
        d = E if inf else E - o
        den = d @ c.normal
        lam = ((c.origin - o) @ c.normal) / np.where(np.abs(den) < 1e-12, 1e-12, den)
        Q = o + lam[:, None] * d
        s, h = c.coords(Q)
        m = self.rect.metres_per_px
        x, y = (s - self.rect.s0_m) / m, (self.rect.h0_m - h) / m
        Hh, Ww = self.img.shape[:2]
        ok = (lam > 0) & (x >= 0) & (y >= 0) & (x < Ww - 1) & (y < Hh - 1)
        xi, yi = np.clip(x, 0, Ww - 1).astype(int), np.clip(y, 0, Hh - 1).astype(int)
        ok &= ~self.bad[yi, xi]
        k = inside_quads(self.quads, x, y) if self.quads else np.full(len(x), -1)
        ok &= k >= 0
        return self.blur[yi, xi] / self.white, ok, k


class Building:
    """A building's panels' samples, its views as mirrors, its pitch, its facade centre and ground height."""

    def __init__(self, layout: BuildingLayout, src: Path | None):
        self.panels = []
        for stem, seg, mask, _, _ in truth_views(layout, src):
            self.panels += view_samples(layout, stem, seg, mask)
        self.pitch = complete_pitch(self.panels)
        self.views = {s: ViewImage(layout, s, self.panels) for s in sorted({p["stem"] for p in self.panels})}
        self.centre = np.mean([p["centre"] for p in self.panels], axis=0)
        pts = np.asarray(read_points(layout.path("import_coarse_points")).points)
        self.ground = float(np.percentile(pts @ self.panels[0]["up"], 1))
        self.y = np.array([p["opening"] for p in self.panels])


def env_points(p: dict, model: str, centre: np.ndarray, R: float, ground: float):
    """E per sample: directions (inf) or points on a sphere of radius R about centre; "ground": rays going
    down end on the ground plane (height ``ground`` along up), the others on the sphere"""
    if model == "inf":
        return p["r"], True
    P, r = p["P"], p["r"]
    q = P - centre
    b = (q * r).sum(1)
    cc = (q * q).sum(1) - R * R
    t = -b + np.sqrt(np.maximum(b * b - cc, 0))
    if model == "ground":
        ru = r @ p["up"]
        tg = (ground - P @ p["up"]) / np.where(ru < -1e-9, ru, -1e-9)
        t = np.where((ru < -1e-9) & (tg > 0), np.minimum(tg, t), t)
    return P + t[:, None] * r, False


def gather(b: Building, model: str, k: float | None) -> list[tuple[dict, list]]:
    """Per panel: (panel, votes), a vote per other view: (colour [n, 3] over that view's white, NaN where it
    shows nothing usable, its panel index [n], its stem)."""
    px, py = b.pitch
    R = (k or 1) * px
    res = []
    for p in b.panels:
        E, inf = env_points(p, model, b.centre, R, b.ground)
        votes = []
        for s, v in b.views.items():
            if s == p["stem"]:
                continue
            col, ok, kk = v.lookup(E, inf)
            # leave the panel's own unit out: seen through another view it is no mirror of anything else
            for j in np.unique(kk[ok]):
                dd = v.panels[j]["centre"] - p["centre"]
                if abs(dd @ p["right"]) < px / 2 and abs(dd @ p["up"]) < py / 2:
                    ok &= kk != j
            votes.append((np.where(ok[:, None], col, np.nan), kk, s))
        res.append((p, votes))
    return res


def pair_gains(res: list, W: dict) -> dict:
    """Per (view, other view): the exposure, the median log colour ratio over all their matched samples."""
    pair = {}
    for p, votes in res:
        own = np.log(p["col_raw"] / 255 + EPS)
        for c, _, s in votes:
            ok = p["ok"] & np.isfinite(c[:, 0])
            if ok.any():
                pair.setdefault((p["stem"], s), []).append(own[ok] - np.log(c[ok] * W[s] / 255 + EPS))
    return {k: np.median(np.concatenate(v), axis=0) for k, v in pair.items()}


def scores(res: list) -> dict[str, np.ndarray]:
    """The scores (``vote``, ``dmin``, ``dmed``) of every panel; NaN where too few samples have a vote."""
    W = {}
    for p, _ in res:
        W.setdefault(p["stem"], p["white"])
    gain = pair_gains(res, W)
    out = {"vote": [], "dmin": [], "dmed": []}
    for p, votes in res:
        own = np.log(p["col_raw"] / 255 + EPS)
        stack, ds = [], []
        for c, kk, s in votes:
            ok = p["ok"] & np.isfinite(c[:, 0])
            g = gain.get((p["stem"], s), np.zeros(3))
            th = np.log(np.where(ok[:, None], c, 1) * W[s] / 255 + EPS) + g
            stack.append(np.where(ok[:, None], th, np.nan))
            for j in np.unique(kk):
                okj = ok & (kk == j)
                if okj.sum() >= MIN:
                    ds.append(float(np.median(np.abs(own[okj] - th[okj]).sum(1))))
        st = np.array(stack)
        has = np.isfinite(st[..., 0]).sum(0) >= 1 if len(st) else np.zeros(len(own), bool)
        if has.sum() < MIN:
            out["vote"].append(np.nan)
        else:
            with np.errstate(all="ignore"):
                med = np.nanmedian(st[:, has], axis=0)
            out["vote"].append(float(np.median(np.abs(own[has] - med).sum(1))))
        out["dmin"].append(min(ds) if ds else np.nan)
        out["dmed"].append(float(np.median(ds)) if ds else np.nan)
    return {k: np.array(v) for k, v in out.items()}


def glass_agreement(res: list) -> np.ndarray:
    """Per glass-glass panel pair seen by at least MIN samples: [median colour distance with the pair's
    exposure removed, NCC of the luminances, samples]."""
    W = {p["stem"]: p["white"] for p, _ in res}
    byview = {}
    for p, _ in res:
        byview.setdefault(p["stem"], []).append(p)
    raw = []
    for p, votes in res:
        if p["opening"]:
            continue
        own = np.log(p["col_raw"] / 255 + EPS)
        for c, kk, s in votes:
            for j in np.unique(kk):
                ok = p["ok"] & np.isfinite(c[:, 0]) & (kk == j)
                if ok.sum() < MIN or byview[s][j]["opening"]:
                    continue
                th = np.log(c[ok] * W[s] / 255 + EPS)
                diff = own[ok] - th
                diff -= np.median(diff, 0)
                a, b = own[ok].mean(1), th.mean(1)
                ncc = np.corrcoef(a, b)[0, 1] if a.std() > 1e-3 and b.std() > 1e-3 else np.nan
                raw.append((np.median(np.abs(diff).sum(1)), ncc, ok.sum()))
    return np.array(raw).reshape(-1, 3)


def verdict(s: np.ndarray, y: np.ndarray, thr: float) -> str:
    ok = np.isfinite(s)
    return (f"{auc(s, y):.2f}, {int((s[y & ok] > thr).sum())}/{int(y.sum())}, "
            f"{int((s[~y & ok] > thr).sum())}/{int((~y).sum())}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data-root", type=Path, required=True,
                    help="gcw_dev and real_like through segment_panels")
    ap.add_argument("--real", type=Path, required=True, help="gcw_dev's photos with truth")
    ap.add_argument("--sim-root", type=Path, help="real_like's variants (default DATA_ROOT/sim)")
    ap.add_argument("--sim-configs", type=Path, help="their config copies (default DATA_ROOT/sim_configs)")
    args = ap.parse_args()
    sim = [BuildingLayout(args.data_root, "real_like")] + make_variants(
        args.sim_root or args.data_root / "sim", args.sim_configs or args.data_root / "sim_configs")
    sim_b = {la.building: Building(la, None) for la in sim}
    gcw = Building(BuildingLayout(args.data_root, "gcw_dev"), args.real.resolve())
    y_sim = np.concatenate([b.y for b in sim_b.values()])
    n_allow = int(np.floor(ALLOWED * (~y_sim).sum()))
    envs = list(dict.fromkeys((m, k) for _, m, k, _ in ROWS))
    got = {}
    agree = {}
    for m, k in envs:
        res = {name: gather(b, m, k) for name, b in sim_b.items()} | {"gcw_dev": gather(gcw, m, k)}
        got[m, k] = {name: scores(r) for name, r in res.items()}
        agree[m, k] = (np.concatenate([glass_agreement(r) for name, r in res.items() if name != "gcw_dev"]),
                       glass_agreement(res["gcw_dev"]))
    head = ["| environment, score | threshold | simulated AUC, caught/lost | gcw_dev AUC, caught/lost "
            "| gcw_dev threshold fitted to it |", "| --- | --- | --- | --- | --- |"]
    per = ["| environment, score | " + " | ".join(list(sim_b) + ["gcw_dev"]) + " |",
           "| --- " * (len(sim_b) + 2) + "|"]
    for label, m, k, key in ROWS:
        sc = got[m, k]
        s_sim = np.concatenate([sc[name][key] for name in sim_b])
        glass = np.sort(s_sim[~y_sim & np.isfinite(s_sim)])[::-1]
        thr = glass[n_allow] if len(glass) > n_allow else -np.inf
        g, gy = sc["gcw_dev"][key], gcw.y
        g_glass = np.sort(g[~gy & np.isfinite(g)])[::-1]
        fitted = g_glass[2] if len(g_glass) > 2 else -np.inf
        ceiling = int((g[gy & np.isfinite(g)] > fitted).sum())
        head.append(f"| {label} | {thr:.3f} | {verdict(s_sim, y_sim, thr)} | {verdict(g, gy, thr)} "
                    f"| {ceiling}/{int(gy.sum())} |")
        cells = [verdict(sc[name][key], b.y, thr) for name, b in sim_b.items()] + [verdict(g, gy, thr)]
        per.append(f"| {label} | " + " | ".join(cells) + " |")
    env_lines = ["| environment | simulated: pairs, median distance, median NCC | gcw_dev: pairs, median "
                 "distance, median NCC |", "| --- | --- | --- |"]
    for m, k in envs:
        cells = [f"{len(a)}, {np.median(a[:, 0]):.3f}, {np.nanmedian(a[:, 1]):.3f}" for a in agree[m, k]]
        env_lines.append(f"| {m}{'' if k is None else f' {k:g}'} | " + " | ".join(cells) + " |")
    print("\n".join([f"simulated: {len(y_sim)} panels, {int(y_sim.sum())} openings ({len(sim_b)} scenes); "
                     f"gcw_dev: {len(gcw.y)} panels, {int(gcw.y.sum())} openings; threshold: at most "
                     f"{n_allow} simulated glass panels above", "", *head, "",
                     "per scene (AUC, caught, lost):", "", *per, "",
                     "glass-glass agreement:", "", *env_lines]))


if __name__ == "__main__":
    main()
