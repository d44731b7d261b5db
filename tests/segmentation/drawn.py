"""Hand-drawn frontal views with exact truth: a curtain-wall grid rendered at 4x and box-filtered down
(anti-aliased edges, like the simulator's supersampling), with optional distractors."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

S = 4  # supersampling


@dataclass
class Drawing:
    W: int = 96
    H: int = 80
    x0: float = 6.3  # left edge of the first mullion (px, continuous)
    y0: float = 5.6  # top edge of the first transom
    pitch: tuple[float, float] = (27.4, 23.3)
    bar: float = 3.2  # frame width (px)
    cols: int = 3
    rows: int = 3
    reflections: bool = False
    occluder: tuple[float, float, float] | None = None  # circle (x, y, r) in px
    seed: int = 0
    glass_rects: list = field(default_factory=list)
    #: the last column's and the last row's pitch (px), where they differ from ``pitch`` (a wider end bay, a
    #: taller ground floor)
    last_pitch: tuple[float | None, float | None] = (None, None)
    #: the transoms' colour where it differs from the mullions' (a cylinder's transoms face the sky)
    transom_colour: tuple[float, float, float] | None = None
    #: the transoms' grey level from the left to the right end, where their shading turns along them (a
    #: cylinder's transoms lit from one side: 0.29 to 0.55 across one of curved12's views)
    transom_ramp: tuple[float, float] | None = None
    #: the frames' colour (above 1: clipped white, a photo brighter than its frames' full scale)
    frame_colour: tuple[float, float, float] = (0.62, 0.64, 0.66)

    def _lines(self, axis: int) -> np.ndarray:
        """[n + 1] left (top) edges of the bars of one family (px), ``axis`` 0: mullions."""
        n = (self.cols, self.rows)[axis]
        p = np.full(n, self.pitch[axis])
        if self.last_pitch[axis] is not None:
            p[-1] = self.last_pitch[axis]
        return (self.x0, self.y0)[axis] + np.concatenate([[0.0], np.cumsum(p)])

    def render(self) -> np.ndarray:
        W, H = self.W * S, self.H * S
        rng = np.random.default_rng(self.seed)
        img = np.zeros((H, W, 3), np.float32)
        img[: H // 2] = (0.55, 0.7, 0.95)  # sky
        img[H // 2 :] = (0.6, 0.58, 0.52)  # paving
        xl, yl = self._lines(0), self._lines(1)
        gx0, gy0 = self.x0 * S, self.y0 * S
        gx1, gy1 = (xl[-1] + self.bar) * S, (yl[-1] + self.bar) * S
        ys, xs = np.mgrid[0:H, 0:W] + 0.5
        facade = (xs >= gx0) & (xs < gx1) & (ys >= gy0) & (ys < gy1)
        img[facade] = self.frame_colour
        glass = np.zeros((H, W), bool)
        self.glass_rects = []
        for r in range(self.rows):
            for c in range(self.cols):
                x, y = xl[c] + self.bar, yl[r] + self.bar
                w, h = xl[c + 1] - x, yl[r + 1] - y
                self.glass_rects.append((x, y, x + w, y + h))
                glass |= (xs >= x * S) & (xs < (x + w) * S) & (ys >= y * S) & (ys < (y + h) * S)
        if self.transom_colour is not None:
            for y in yl:
                img[facade & ~glass & (ys >= y * S) & (ys < (y + self.bar) * S)] = self.transom_colour
        if self.transom_ramp is not None:
            lo, hi = self.transom_ramp
            grey = lo + (hi - lo) * np.clip((xs - gx0) / (gx1 - gx0), 0.0, 1.0)
            for y in yl:
                on = facade & ~glass & (ys >= y * S) & (ys < (y + self.bar) * S)
                img[on] = grey[on][:, None]
        sky = ys < gy0 + 0.45 * (gy1 - gy0)
        img[glass & sky] = (0.35, 0.45, 0.6)
        img[glass & ~sky] = (0.25, 0.35, 0.22)
        if self.reflections:  # reflected building edges: long, straight, strong, off the grid
            for x in (0.3, 0.62):
                band = glass & (np.abs(xs - x * W) < 1.2 * S)
                img[band] = (0.08, 0.08, 0.1)
            img[glass & (np.abs(ys - 0.3 * H) < 1.0 * S)] = (0.95, 0.95, 0.9)
            img[glass & (xs > 0.62 * W) & (ys > 0.3 * H)] *= 0.5  # a reflected building face
        if self.occluder is not None:
            ox, oy, orad = (v * S for v in self.occluder)
            img[(xs - ox) ** 2 + (ys - oy) ** 2 < orad**2] = (0.15, 0.4, 0.12)  # a tree in front
        img += rng.normal(0, 0.01, img.shape).astype(np.float32)
        small = cv2.resize(img, (self.W, self.H), interpolation=cv2.INTER_AREA)
        return np.clip(np.rint(small * 255), 0, 255).astype(np.uint8)

    def corners(self) -> np.ndarray:
        """[P, 4, 2] true glass corners (BL, BR, TR, TL), clipped to the image."""
        out = [[(x0, y1), (x1, y1), (x1, y0), (x0, y0)] for x0, y0, x1, y1 in self.glass_rects]
        return np.clip(np.array(out, float), 0, [self.W, self.H])
