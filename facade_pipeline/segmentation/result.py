"""The ``03_segment`` hand-off: the panels found in one frontal view and its panel mask.

``ViewSegmentation.save`` is the one writer (stage ``segment_panels``, or a stand-in built from truth) and
``ViewSegmentation.load`` the one reader (``regularize_corners``, the accuracy figures, the benchmarks and
tests) of ``03_segment/corners/{stem}.json`` and ``03_segment/masks/{stem}.png``, both specified in
data_layout.md ("Hand-off formats"). The mask is the file a person may fix by hand: it is read as any
8-bit image (``read_mask``: True where the first channel is at least 128) and only its size is checked.
Pixels: x right, y down, pixel centres at (i + 0.5, j + 0.5); corners bottom-left, bottom-right, top-right,
top-left seen from outside.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import read_json, write_json
from facade_pipeline.io.images import read_mask, write_mask
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.rectification.surface_map import ViewRectification
from facade_pipeline.segmentation.quads import inside_quads

CORNER_DECIMALS = 3  # corners are stored to a thousandth of a pixel


@dataclass(frozen=True, eq=False)
class SegmentedPanel:
    """One panel of one view: ``corners_px`` [4, 2] in ``01_import/frontal/{stem}.png``,
    ``corners_rectified_px`` [4, 2] in the rectified image (the same for a view that was not rectified;
    None in a corners file that leaves them out), row and column within the view (row 0 the lowest, col 0
    the leftmost) and ``complete`` (False: cut by the image border or occluded)."""

    row: int
    col: int
    corners_px: np.ndarray
    corners_rectified_px: np.ndarray | None
    complete: bool = True


@dataclass(frozen=True, eq=False)
class ViewSegmentation:
    """The contents of ``03_segment/corners/{stem}.json`` and ``03_segment/masks/{stem}.png``: the view's
    size (px), whether it was rectified before segmentation, whether a facade was found (else why not),
    its panels and the panel ``mask`` [H, W] bool (authoritative where it and the corners disagree)."""

    stem: str
    width: int
    height: int
    rectified: bool
    facade_found: bool
    reason: str
    panels: tuple[SegmentedPanel, ...]
    mask: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        assert self.mask.shape == (self.height, self.width), (self.stem, self.mask.shape)

    def save(self, layout: BuildingLayout) -> list[Path]:
        """Write the corners JSON and the mask PNG (atomically); returns their paths."""
        corners = layout.path("segment_corners", stem=self.stem)
        mask = layout.path("segment_mask", stem=self.stem)
        write_json(corners, self._record())
        write_mask(mask, self.mask)
        return [corners, mask]

    def _record(self) -> dict:
        def rounded(c: np.ndarray) -> list:
            return np.round(np.asarray(c, np.float64), CORNER_DECIMALS).tolist()

        return {
            "image": self.stem,
            "width": self.width,
            "height": self.height,
            "rectified": self.rectified,
            "facade_found": self.facade_found,
            "reason": self.reason,
            "panels": [
                {
                    "row": p.row,
                    "col": p.col,
                    "corners_px": rounded(p.corners_px),
                    "corners_rectified_px": rounded(
                        p.corners_px if p.corners_rectified_px is None else p.corners_rectified_px
                    ),
                    "complete": p.complete,
                }
                for p in self.panels
            ],
        }

    @classmethod
    def load(cls, layout: BuildingLayout, stem: str, width: int, height: int) -> ViewSegmentation:
        """Read view ``stem``'s corners and mask and check both against its size (``width`` x ``height``
        px, the frontal view's)."""
        path = layout.path("segment_corners", stem=stem)

        def parse(d: dict) -> tuple:
            panels = tuple(_panel(path, i, p) for i, p in enumerate(d["panels"]))
            head = (str(d["image"]), bool(d["rectified"]), bool(d["facade_found"]), str(d.get("reason", "")))
            return panels, (int(d["width"]), int(d["height"])), head

        what = "a panel corners JSON written by segment_panels (data_layout.md, Hand-off formats)"
        panels, size, head = read_json(path, what, parse)
        if size != (width, height):
            expected = f"width x height {width}x{height} (the frontal view)"
            raise InputError(path, expected, "{}x{}".format(*size))
        mask_path = layout.path("segment_mask", stem=stem)
        mask = read_mask(mask_path)
        if mask.shape != (height, width):
            found = f"{mask.shape[1]}x{mask.shape[0]}"
            raise InputError(mask_path, f"a {width}x{height} mask (the frontal view)", found)
        return cls(head[0], width, height, head[1], head[2], head[3], panels, mask)


def _panel(path: Path, i: int, p: dict) -> SegmentedPanel:
    """Panel ``i`` of a corners JSON; corners must be 4 finite [x, y]."""
    corners = []
    for key in ("corners_px", "corners_rectified_px"):
        if key not in p and key == "corners_rectified_px":
            corners.append(None)
            continue
        c = np.asarray(p[key], dtype=np.float64)
        if c.shape != (4, 2) or not np.isfinite(c).all():
            raise InputError(path, f"panel {i} with 4 finite [x, y] {key}", f"an array of shape {c.shape}")
        corners.append(c)
    return SegmentedPanel(int(p["row"]), int(p["col"]), corners[0], corners[1], bool(p.get("complete", True)))


def panel_labels(
    rectified_quads: list[np.ndarray], rect: ViewRectification, width: int, height: int
) -> np.ndarray:
    """Panel index [H, W] of each original pixel (its centre mapped into the rectified image) among the
    quads [4, 2] in rectified pixels, -1: none."""
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    pts = rect.to_rectified(np.stack([xs.ravel(), ys.ravel()], axis=1))
    pts = np.where(np.isfinite(pts), pts, -1e9)
    return inside_quads(list(rectified_quads), pts[:, 0], pts[:, 1]).reshape(height, width)
