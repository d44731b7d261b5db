"""Units without glass told by what the facade's other panes mirror (a panel only if its inside looks like
glass, taken literally).

A pane mirrors its surroundings: the ray from a view's camera to a point of the pane, reflected in the wall,
ends on something that the other views see mirrored in their own panes, where their mirrored camera's ray
to it crosses the wall. A unit without glass shows the room behind it instead, which no pane mirrors.

Each panel is sampled on a grid inside its quad, clear of the bars and blurred by a fraction of the panel's
width, so that a small misregistration matters little. Each sample's reflected ray ends on the ground
(rays going down, at the facade's foot: the lowest of the coarse points) or on a sphere of
``ENVIRONMENT_PITCHES`` about the facade's centre. Every other view that mirrors that point in one of its
panels votes with its colour there, the panel's own unit included: a pane seen from another view mirrors
the same point, while a unit without glass shows its room from another side, at another place. Each pair
of views' exposure is taken out by the median log colour ratio over all its matched samples, so no
decision rests on a brightness. A panel's score is the median over its samples of the distance (summed
absolute log ratio of the three channels) from its own colour to the median vote.

One panel's score is noisy (a reflected near object, glare, a vote through another unit without glass), so
the decision is the building's: the panels of every view are gathered into units by their centres on the
wall (within half the building's pitch), and a unit scored in at least ``MIN_VIEWS`` views whose median
score is above ``max_score`` (``[segment_panels] mirror_max_score``) is no pane in any view. The frame
rules (``openings``) tell a unit whose frame was put in with its glass; this cue tells the stick-built
unit, whose frames stand without it.
"""

from __future__ import annotations

import cv2
import numpy as np

from facade_pipeline.rectification.surface_map import ViewRectification
from facade_pipeline.segmentation.quads import inside_quads

#: samples per side of a panel
SAMPLES = 14
#: of the quad's size, kept clear of the bars on each side
SHRINK = 0.1
#: of the median panel width: the blur's sigma
BLUR = 1 / 35
#: the fewest samples with a vote that score a panel
MIN_SAMPLES = 12
#: added to colours (0-1) before the log, so that dark samples do not dominate
EPS = 2.0 / 255
#: a sample at this value (8-bit, brightest channel) or above is clipped: it votes for nothing
CLIPPED = 250
#: the reflected rays that miss the ground end on a sphere of this radius about the facade's centre (building
#: pitches): the surroundings a survey's panes mirror lie tens of metres away; within a few pitches the
#: mirrored points would move with the views' baseline more than the surroundings do
ENVIRONMENT_PITCHES = 30.0
#: the fewest views whose panels of a unit must be scored to decide it: one panel's score is noisy (a near
#: object reflected, glare, a vote from a view that sees the mirrored point through another unit without
#: glass), and with two views one such panel is half the median
MIN_VIEWS = 3


class MirrorView:
    """One rectified planar view as a mirror: its panels' samples, and what its panes show toward given
    points of the surroundings."""

    def __init__(self, stem: str, rect: ViewRectification, image: np.ndarray, quads: list[np.ndarray]):
        self.stem = stem
        self.rect = rect
        self.quads = [np.asarray(q, float) for q in quads]
        c = rect.chart
        m = rect.metres_per_px
        widths = [float(np.linalg.norm(q[1] - q[0])) for q in self.quads] or [50.0]
        f = image.astype(np.float32)
        self.blur = cv2.GaussianBlur(f, (0, 0), max(0.5, float(np.median(widths)) * BLUR))
        clipped = image.max(axis=2) >= CLIPPED
        self.bad = cv2.dilate(clipped.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        self.bad |= image.max(axis=2) == 0
        cam = rect.camera.center
        self.mirror_camera = cam - 2 * ((cam - c.origin) @ c.normal) * c.normal
        u = (np.arange(SAMPLES) + 0.5) / SAMPLES * (1 - 2 * SHRINK) + SHRINK
        U, V = (a.ravel()[:, None] for a in np.meshgrid(u, u))
        self.points, self.rays, self.colours, self.usable, self.centres = [], [], [], [], []
        for q in self.quads:
            bl, br, tr, tl = q  # bilinear in the quad
            px = (1 - U) * ((1 - V) * bl + V * tl) + U * ((1 - V) * br + V * tr)
            xi = np.clip(px[:, 0].astype(int), 0, image.shape[1] - 1)
            yi = np.clip(px[:, 1].astype(int), 0, image.shape[0] - 1)
            P = c.point(rect.s0_m + px[:, 0] * m, rect.h0_m - px[:, 1] * m)
            d = P - cam
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            self.points.append(P)
            self.rays.append(d - 2 * (d @ c.normal)[:, None] * c.normal)
            self.colours.append(self.blur[yi, xi])
            self.usable.append(~self.bad[yi, xi])
            centre = q.mean(axis=0)
            self.centres.append(c.point(np.array([rect.s0_m + centre[0] * m]),
                                        np.array([rect.h0_m - centre[1] * m]))[0])

    def lookup(self, E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour [n, 3] (8-bit scale, blurred) and usable [n] (inside a panel, not clipped) of what this
        view's panes mirror toward the points E [n, 3]."""
        c = self.rect.chart
        d = E - self.mirror_camera
        den = d @ c.normal
        lam = ((c.origin - self.mirror_camera) @ c.normal) / np.where(np.abs(den) < 1e-12, 1e-12, den)
        s, h = c.coords(self.mirror_camera + lam[:, None] * d)
        m = self.rect.metres_per_px
        x, y = (s - self.rect.s0_m) / m, (self.rect.h0_m - h) / m
        H, W = self.blur.shape[:2]
        ok = (lam > 0) & (x >= 0) & (y >= 0) & (x < W - 1) & (y < H - 1)
        xi, yi = np.clip(x, 0, W - 1).astype(int), np.clip(y, 0, H - 1).astype(int)
        ok &= ~self.bad[yi, xi]
        if self.quads:
            ok &= inside_quads(self.quads, x, y) >= 0
        else:
            ok[:] = False
        return self.blur[yi, xi], ok


def facade_foot(points: np.ndarray, up: np.ndarray) -> float:
    """The height of the facade's foot along ``up``: the lowest of the coarse points [n, 3], a few stray
    ones below it (their 1st percentile)."""
    return float(np.percentile(np.asarray(points) @ up, 1))


def _environment(P: np.ndarray, r: np.ndarray, centre: np.ndarray, radius: float, ground: float,
                 up: np.ndarray) -> np.ndarray:
    """Where the reflected rays (from P [n, 3] along r [n, 3]) end: on the ground (height ``ground`` along
    ``up``) for rays going down that meet it first, else on the sphere of ``radius`` about ``centre``."""
    q = P - centre
    b = (q * r).sum(axis=1)
    t = -b + np.sqrt(np.maximum(b * b - ((q * q).sum(axis=1) - radius * radius), 0.0))
    ru = r @ up
    tg = (ground - P @ up) / np.where(ru < -1e-9, ru, -1e-9)
    t = np.where((ru < -1e-9) & (tg > 0), np.minimum(tg, t), t)
    return P + t[:, None] * r


def _log(colour: np.ndarray) -> np.ndarray:
    return np.log(colour / 255.0 + EPS)


def panel_scores(views: list[MirrorView], pitch_m: tuple[float, float], ground: float) -> list[np.ndarray]:
    """Per view, the score [panels] of each of its panels (NaN: fewer than ``MIN_SAMPLES`` samples with a
    vote); ``pitch_m``: the building's pitch across the mullions and the transoms (m), the environment's
    radius in their geometric mean; ``ground``: the height of the facade's foot along the views' up."""
    radius = ENVIRONMENT_PITCHES * float(np.sqrt(pitch_m[0] * pitch_m[1]))
    centre = np.mean([c for v in views for c in v.centres], axis=0)
    votes: list[list[list[tuple[int, np.ndarray]]]] = []  # [view][panel] -> (other view, log colour)
    pair: dict[tuple[int, int], list[np.ndarray]] = {}
    for a, v in enumerate(views):
        c = v.rect.chart
        per_panel = []
        for P, r, col, ok in zip(v.points, v.rays, v.colours, v.usable, strict=True):
            E = _environment(P, r, centre, radius, ground, c.up)
            own = _log(col)
            got = []
            for b, w in enumerate(views):
                if b == a:
                    continue
                colour, seen = w.lookup(E)
                seen &= ok
                if not seen.any():
                    continue
                th = np.where(seen[:, None], _log(colour), np.nan)
                got.append((b, th))
                pair.setdefault((a, b), []).append(own[seen] - th[seen])
            per_panel.append(got)
        votes.append(per_panel)
    gain = {k: np.median(np.concatenate(d), axis=0) for k, d in pair.items()}
    out = []
    for a, v in enumerate(views):
        scores = np.full(len(v.quads), np.nan)
        for i, got in enumerate(votes[a]):
            if not got:
                continue
            stack = np.array([th + gain[(a, b)] for b, th in got])
            has = np.isfinite(stack[..., 0]).any(axis=0)
            if has.sum() < MIN_SAMPLES:
                continue
            with np.errstate(all="ignore"):
                median = np.nanmedian(stack[:, has], axis=0)
            scores[i] = float(np.median(np.abs(_log(v.colours[i][has]) - median).sum(axis=1)))
        out.append(scores)
    return out


def units(views: list[MirrorView], complete: list[np.ndarray],
          pitch_m: tuple[float, float]) -> list[np.ndarray]:
    """Per view, the unit [panels] each panel belongs to: complete panels first, each joining the first unit
    whose centre lies within half a pitch of its own along the wall's right and up (else starting one),
    then the panels cut by the border, which join a unit the same way (their centre lies inside the unit's
    visible part) or start their own."""
    px, py = pitch_m
    centres: list[np.ndarray] = []
    out = [np.full(len(v.quads), -1) for v in views]
    for whole in (True, False):
        for a, v in enumerate(views):
            c = v.rect.chart
            for i, cen in enumerate(v.centres):
                if bool(complete[a][i]) != whole:
                    continue
                for k, other in enumerate(centres):
                    dd = other - cen
                    if abs(dd @ c.right) < px / 2 and abs(dd @ c.up) < py / 2:
                        out[a][i] = k
                        break
                else:
                    centres.append(cen)
                    out[a][i] = len(centres) - 1
    return out


def unit_medians(views: list[MirrorView], complete: list[np.ndarray], pitch_m: tuple[float, float],
                 ground: float) -> tuple[list[np.ndarray], dict[int, tuple[float, list[str]]]]:
    """Per view, the unit [panels] of each panel (``units``), and per unit scored in at least
    ``MIN_VIEWS`` views its median score over its panels (``panel_scores``) and those views."""
    scores = np.concatenate(panel_scores(views, pitch_m, ground)) if views else np.zeros(0)
    unit = units(views, complete, pitch_m)
    lab = np.concatenate(unit) if unit else np.zeros(0, int)
    stem = np.concatenate([[v.stem] * len(v.quads) for v in views]) if views else np.zeros(0, str)
    medians = {}
    for u in np.unique(lab):
        ok = (lab == u) & np.isfinite(scores)
        if len(set(stem[ok])) >= MIN_VIEWS:
            medians[int(u)] = (float(np.median(scores[ok])), sorted(set(stem[ok].tolist())))
    return unit, medians


def mirror_openings(views: list[MirrorView], complete: list[np.ndarray], pitch_m: tuple[float, float],
                    ground: float, max_score: float) -> tuple[list[np.ndarray], dict]:
    """Per view, which of its panels [panels] (bool) belong to a unit the other views' panes do not mirror
    (module docstring), and the figures behind it: the units scored, the highest median score of a unit
    kept, and per unit judged no pane its median score and the views that scored it."""
    unit, medians = unit_medians(views, complete, pitch_m, ground)
    judged = {str(u): {"score": round(m, 4), "views": stems} for u, (m, stems) in medians.items()
              if m > max_score}
    kept = [m for m, _ in medians.values() if m <= max_score]
    figures = {"units_scored": len(medians), "highest_kept_score": round(max(kept), 4) if kept else None,
               "not_mirrored": judged}
    return [np.isin(u, [int(k) for k in judged]) for u in unit], figures
