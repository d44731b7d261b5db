"""Accuracy of a segmentation against real photos with truth (the layout of ``shared/real/gcw_dev``:
``masks/{img}.png`` with glass = 255 and ``panes.json`` with each visible pane's pixel outline). Tests and
benchmarks only: no stage reads the truth.

Per photo:
- whole panes: the truth outlines with 4 corners, none on the image border; one is found when a complete
  predicted panel overlaps its quad with IoU >= ``found_iou``;
- corner error of the found whole panes: each true corner against the nearest corner of the matching
  panel (photo pixels, the truth's own convention: pixel indices, so 0.5 is added to its corners);
- glass-mask IoU: ``03_segment/masks`` against the truth mask;
- complete panels less than half glass: the fraction of each complete panel's pixels that the truth mask
  calls glass.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from facade_pipeline.scene import ImportedScene
from facade_pipeline.segmentation.quads import inside_quads
from facade_pipeline.segmentation.result import ViewSegmentation


def quad_mask(corners: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H, W] bool: pixel centres inside the polygon ``corners`` [K, 2] (pixel centres at +0.5)."""
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    return inside_quads([np.asarray(corners, float)], xs, ys) >= 0


def whole_panes(outlines: list, width: int, height: int, border_px: float = 1.0) -> list[np.ndarray]:
    """True whole panes [4, 2] (pixel centres at +0.5): four corners, none within ``border_px`` of the
    border."""
    out = []
    for o in outlines:
        c = np.asarray(o, float) + 0.5
        if len(c) == 4 and (c.min(axis=0) > border_px).all() and (c[:, 0] < width - border_px).all() \
                and (c[:, 1] < height - border_px).all():
            out.append(c)
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def evaluate_photo(seg: ViewSegmentation, truth_mask: np.ndarray, outlines: list,
                   found_iou: float = 0.7) -> dict:
    """Every figure of one photo (module docstring)."""
    H, W = truth_mask.shape
    truth = truth_mask > 127
    panels = seg.panels
    complete = [p.corners_px for p in panels if p.complete]
    masks = [quad_mask(c, W, H) for c in complete]
    found, errors = 0, []
    whole = whole_panes(outlines, W, H)
    for pane in whole:
        tm = quad_mask(pane, W, H)
        scores = [iou(tm, m) for m in masks]
        if scores and max(scores) >= found_iou:
            found += 1
            c = complete[int(np.argmax(scores))]
            errors += [float(np.min(np.linalg.norm(c - q, axis=1))) for q in pane]
    glass_frac = [float(truth[m].mean()) if m.any() else 0.0 for m in masks]
    return {"n_whole": len(whole), "n_found": found, "corner_errors_px": errors,
            "mask_iou": iou(seg.mask, truth), "glass_fraction_complete": glass_frac,
            "n_panels": len(panels), "n_complete": len(complete)}


def evaluate_building(layout, truth_dir: Path) -> dict[str, dict]:
    """``evaluate_photo`` for every frontal view of ``layout`` whose stem has truth in ``truth_dir``."""
    panes = json.loads((truth_dir / "panes.json").read_text())
    out = {}
    for v in ImportedScene.load(layout).frontal_views:
        tm = cv2.imread(str(truth_dir / "masks" / f"{v.stem}.png"), cv2.IMREAD_GRAYSCALE)
        if tm is None or v.stem not in panes:
            continue
        seg = ViewSegmentation.load(layout, v.stem, v.camera.width, v.camera.height)
        out[v.stem] = evaluate_photo(seg, tm, panes[v.stem])
    return out


def summary(per_photo: dict[str, dict]) -> dict:
    """The targets' figures over all photos."""
    whole = sum(r["n_whole"] for r in per_photo.values())
    found = sum(r["n_found"] for r in per_photo.values())
    err = np.concatenate([r["corner_errors_px"] for r in per_photo.values()] + [np.zeros(0)])
    ious = np.array([r["mask_iou"] for r in per_photo.values()])
    frac = np.concatenate([r["glass_fraction_complete"] for r in per_photo.values()] + [np.zeros(0)])
    return {"photos": len(per_photo), "whole_panes": whole, "found": found,
            "found_fraction": found / whole if whole else float("nan"),
            "mask_iou_median": float(np.median(ious)), "mask_iou_min": float(ious.min()),
            "corner_error_median_px": float(np.median(err)) if len(err) else float("nan"),
            "complete_panels": len(frac), "complete_less_than_half_glass": int((frac < 0.5).sum())}


def grid_corner_errors_m(wall_points: np.ndarray, pitch_m: tuple[float, float],
                         glass_m: tuple[float, float]) -> np.ndarray:
    """Distances [N] (m) of 3D corners in the wall frame ([N, 3]: x along rows, y down, z into the wall,
    the glass plane at z = 0) to the nearest nominal glass corner: the glass of pane k spans
    [k p - g, k p] along each axis (the gcw wall frame's origin is a glass corner, the glass on its negative
    side in both axes, as its corners back-projected with the poses show)."""
    out = []
    for axis, (p, g) in enumerate(zip(pitch_m, glass_m, strict=True)):
        v = wall_points[:, axis]
        i = np.round(v / p)
        cands = np.stack([(i + k) * p + o for k in (-1, 0, 1) for o in (0.0, -g)], axis=1)
        out.append(np.min(np.abs(cands - v[:, None]), axis=1))
    return np.sqrt(out[0] ** 2 + out[1] ** 2 + wall_points[:, 2] ** 2)


#: exposure (EV) and white balance (gain per channel of linear light, R G B) a camera may have chosen for the
#: same photos
EXPOSURES = {"-1 EV": (0.5,) * 3, "-0.5 EV": (2 ** -0.5,) * 3, "+0.5 EV": (2 ** 0.5,) * 3,
             "+1 EV": (2.0,) * 3, "white balance off by 20 %": (1.2, 1.0, 0.8)}


def _srgb_to_linear(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(v: np.ndarray) -> np.ndarray:
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def exposed_copy(src: Path, dst: Path, gains_rgb: tuple[float, float, float]) -> None:
    """The truth folder ``src`` copied to ``dst`` with every photo taken at another exposure and white
    balance: each channel's linear light (sRGB decoded) times its gain, then clipped and encoded, as a
    camera would have recorded it (JPEG, quality 95); the truth as it is."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("images"))
    (dst / "images").mkdir()
    for p in sorted((src / "images").glob("*.jpg")):
        bgr = cv2.imread(str(p)).astype(np.float64) / 255.0
        linear = _srgb_to_linear(bgr) * np.array(gains_rgb[::-1])
        out = np.rint(_linear_to_srgb(linear) * 255.0).astype(np.uint8)
        cv2.imwrite(str(dst / "images" / p.name), out, [cv2.IMWRITE_JPEG_QUALITY, 95])


def _profile_edge(mask: np.ndarray, points: np.ndarray, inward: np.ndarray, reach_px: float,
                  step_px: float = 0.25) -> np.ndarray:
    """Where ``mask`` [H, W] begins along each profile through ``points`` [N, 2] (continuous pixel
    coordinates) in the direction ``inward`` [2], from -``reach_px`` to +``reach_px``: the offset e [N] such
    that the mask holds over (e, reach] (its share of the profile, counted back from the inner end)."""
    s = np.arange(-reach_px, reach_px, step_px) + step_px / 2
    q = points[:, None, :] + s[None, :, None] * inward[None, None, :]
    H, W = mask.shape
    xi = np.clip(np.floor(q[..., 0]).astype(int), 0, W - 1)
    yi = np.clip(np.floor(q[..., 1]).astype(int), 0, H - 1)
    return reach_px - mask[yi, xi].sum(axis=1) * step_px


def side_offsets(pred: np.ndarray, truth: np.ndarray, pane: np.ndarray, reach_px: float,
                 samples: int = 15) -> np.ndarray:
    """Offset [4] (px) of the predicted mask's edge from the truth mask's edge along each side of a whole
    pane ``pane`` [4, 2] (pixel centres at +0.5), the median of ``samples`` profiles across the side's
    middle 70 % (clear of the corners): > 0 where the prediction reaches beyond the truth (over the bar),
    < 0 where it stops short of it."""
    centre = pane.mean(axis=0)
    out = []
    for i in range(4):
        a, b = pane[i], pane[(i + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([-d[1], d[0]])
        mid = 0.5 * (a + b)
        if n @ (centre - mid) < 0:
            n = -n
        t = np.linspace(0.15, 0.85, samples)[:, None]
        pts = a + t * (b - a)
        out.append(float(np.median(_profile_edge(truth, pts, n, reach_px)
                                    - _profile_edge(pred, pts, n, reach_px))))
    return np.array(out)


#: the classes of ``mask_losses``, each a share of the pixels the prediction gets wrong
LOSS_CLASSES = ("missed whole pane", "missed cut pane", "short of the edge", "glass inside a found pane",
                "false panel", "over the edge", "false elsewhere")


def mask_losses(pred: np.ndarray, truth: np.ndarray, outlines: list, panels: list[np.ndarray] | None = None,
                image: np.ndarray | None = None, band_px: float = 3.0, found_share: float = 0.5) -> dict:
    """What a glass mask ``pred`` [H, W] bool loses against ``truth`` [H, W] bool, one photo, with the truth's
    pane outlines (``panes.json``'s, pixel indices).

    Each wrong pixel is put in one class (``LOSS_CLASSES``): missed glass (truth, not predicted) in a pane
    whose glass is predicted over less than ``found_share`` ("missed whole pane" for a whole pane,
    ``whole_panes``, "missed cut pane" for the rest, cut by the border), else within ``band_px`` of the
    truth's outline ("short of the edge") or deeper ("glass inside a found pane"); false glass (predicted,
    not truth) in a predicted panel (``panels``' quads [4, 2] in photo pixels; where None or outside every
    quad, the mask's 4-connected region) that is less than half truth glass ("false panel": an empty unit,
    a panel over frames), else within ``band_px`` of the truth's glass ("over the edge") or further ("false
    elsewhere"). ``gain`` per class: the IoU the photo would have with that class right.
    ``clipped``: the wrong pixels whose brightest channel in ``image`` (8-bit) is at 250 or more. Whole panes:
    ``offsets_px``, each side's offset of the predicted edge from the truth's (``side_offsets``, of the
    panes found), and ``cut_panes`` [found, all]: the panes cut by the border predicted over at least
    ``found_share`` of their glass."""
    H, W = truth.shape
    pred, truth = pred.astype(bool), truth.astype(bool)
    inter, union = int((pred & truth).sum()), int((pred | truth).sum())
    fn, fp = truth & ~pred, pred & ~truth
    whole = whole_panes(outlines, W, H)
    whole_keys = {tuple(np.round(p.ravel(), 3)) for p in whole}
    missed_whole, missed_cut = np.zeros_like(truth), np.zeros_like(truth)
    offsets, cut_found, cut_all = [], 0, 0
    for o in outlines:
        c = np.asarray(o, float) + 0.5
        # the outline runs through the centres of its outermost pixels: grown by one pixel, it holds them
        region = quad_mask(c, W, H) if len(c) == 4 else _polygon_mask(c, W, H)
        region = cv2.dilate(region.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & truth
        if not region.any():
            continue
        share = float(pred[region].mean())
        is_whole = tuple(np.round(c.ravel(), 3)) in whole_keys
        if share < found_share:
            (missed_whole if is_whole else missed_cut)[region] = True
        elif is_whole:
            reach = 0.25 * float(min(np.ptp(c[:, 0]), np.ptp(c[:, 1])))
            offsets.append(side_offsets(pred, truth, c, min(reach, 12.0)))
        if not is_whole:
            cut_all += 1
            cut_found += share >= found_share
    inside = cv2.distanceTransform(truth.astype(np.uint8), cv2.DIST_L2, 3)
    outside = cv2.distanceTransform((~truth).astype(np.uint8), cv2.DIST_L2, 3)
    classes = {}
    classes["missed whole pane"] = fn & missed_whole
    classes["missed cut pane"] = fn & missed_cut & ~missed_whole
    rest = fn & ~missed_whole & ~missed_cut
    classes["short of the edge"] = rest & (inside <= band_px)
    classes["glass inside a found pane"] = rest & (inside > band_px)
    n, labels = cv2.connectedComponents(pred.astype(np.uint8), connectivity=4)
    if panels:
        ys, xs = np.mgrid[0:H, 0:W] + 0.5
        quad = inside_quads([np.asarray(q, float) for q in panels], xs, ys)
        labels = np.where(quad >= 0, n + quad, labels)
        n += len(panels)
    labels = np.where(pred, labels, 0)
    share = np.bincount(labels[truth], minlength=n) / np.maximum(np.bincount(labels.ravel(), minlength=n), 1)
    false_region = (share < 0.5)[labels] & pred
    classes["false panel"] = fp & false_region
    classes["over the edge"] = fp & ~false_region & (outside <= band_px)
    classes["false elsewhere"] = fp & ~false_region & (outside > band_px)
    iou_now = inter / union if union else 1.0
    gain, count = {}, {}
    for name, m in classes.items():
        k = int(m.sum())
        count[name] = k
        if name in ("missed whole pane", "missed cut pane", "short of the edge", "glass inside a found pane"):
            gain[name] = (inter + k) / union - iou_now if union else 0.0
        else:
            gain[name] = inter / (union - k) - iou_now if union > k else 0.0
    clipped = 0
    if image is not None:
        clipped = int(((fn | fp) & (image.max(axis=2) >= 250)).sum())
    return {"iou": iou_now, "union_px": union, "wrong_px": int((fn | fp).sum()), "count_px": count,
            "gain": gain, "clipped_px": clipped,
            "offsets_px": np.array(offsets).reshape(-1, 4), "cut_panes": (cut_found, cut_all)}


def _polygon_mask(corners: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H, W] bool: pixels whose centre lies inside the (possibly non-convex) polygon ``corners`` [K, 2]
    (pixel centres at +0.5)."""
    from skimage.measure import points_in_poly

    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    return points_in_poly(np.stack([xs.ravel(), ys.ravel()], axis=1), corners).reshape(height, width)
