"""Per-view exposure gains estimated from the photos before training, from the facade's opaque parts.

UAV cameras expose each photo on their own (and may set its white balance on their own): the same frame
bar is brighter in one photo than in the next. Trained as if all photos were exposed alike, a model takes
these changes for view-dependent colour, which on glass is indistinguishable from a reflection, and the
held-out views pay for it. Learning a gain per view with the splats instead was poorly
determined early in a short run, when the gains absorb the model's own colour errors.

The opaque parts of the facade (frames, walls) are diffuse: a point on them has one radiance, whichever
view sees it. So, for a view i and a surface point p seen by it, ``log I_i(p) = g_i + log L(p)`` per colour
channel, and the gains follow from the photos and the corrected mesh alone:

- points are drawn on the corrected mesh's non-glass triangles (all triangles when the labels are
  unknown);
- a point counts in a view where it projects inside the view's facade mask and outside its glass mask,
  both eroded by ``erode_px`` (no mixed pixels at a frame's edge), and where the view sees it (the mesh
  does not occlude it);
- channels near black or white are left out (the log of noise; clipping);
- ``g`` and ``log L`` are solved by alternating medians, robust to the points that an unmodelled object
  occludes or that sit on a mis-labelled triangle; the gains are then shifted to a geometric mean of 1 over
  the reference (training) views.

A view with fewer than ``min_samples`` usable samples keeps a gain of 1 and is reported.

The estimate casts rays with open3d, so it is made where the training data is built
(``with_exposure_estimate``: the stage, the benchmarks) and travels with it (``TrainData.exposure``, a
bundle); training reads it there and needs torch alone.
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from facade_pipeline.config import Count, NonNeg, PosInt
from facade_pipeline.training.data import ExposureEstimate, TrainData, TrainView
from facade_pipeline.training.init import sample_mesh

if TYPE_CHECKING:  # open3d is imported where rays are cast (``estimate_exposures``)
    from facade_pipeline.geometry.raycast import MeshRaycaster

log = logging.getLogger(__name__)

#: Channel values outside this range are left out: the log of sensor noise, and clipping.
_VALID = (0.02, 0.98)


@dataclass(frozen=True)
class ExposureParams:
    """How the per-view gains are estimated before training. The defaults are what training uses: the
    estimate's internal counts and tolerances, fixed rather than configured because they set how many
    samples the robust solve sees and how it keeps mixed and hidden pixels out, not what it estimates."""

    samples: PosInt = 20000
    """points drawn on the corrected mesh's opaque triangles (-)"""
    erode_px: Count = 1
    """facade and glass masks eroded by this before a point counts in a view (px): no mixed pixels"""
    occlusion_tolerance: NonNeg = 0.005
    """a point is seen where the mesh's first hit along the ray is within this fraction of its distance (-)"""
    min_samples: Count = 30
    """fewer usable samples than this in a view: its gain stays 1 (-)"""
    iterations: PosInt = 10
    """alternating-median rounds (-)"""


#: How the per-view exposure gains are estimated before training: its defaults.
EXPOSURE_ESTIMATE = ExposureParams()


def usable_mask(view: TrainView, erode_px: int) -> np.ndarray:
    """[H, W] bool: the facade's opaque pixels of ``view`` at least ``erode_px`` from glass and from the
    facade mask's edge."""
    it = max(0, int(erode_px))
    facade, glass = view.facade_mask, view.glass_mask
    if it:
        facade = ndimage.binary_erosion(facade, iterations=it, border_value=0)
        glass = ndimage.binary_dilation(glass, iterations=it)
    return facade & ~glass


def observe(
    views: Sequence[TrainView], points: np.ndarray, caster: MeshRaycaster, params: ExposureParams
) -> np.ndarray:
    """[V, P, 3] colour of each point in each view (NaN where it does not count there)."""
    obs = np.full((len(views), len(points), 3), np.nan, np.float32)
    for i, v in enumerate(views):
        cam = v.camera
        uv, z = cam.project(points)
        with np.errstate(invalid="ignore"):
            x, y = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & np.isfinite(uv).all(1) & (x >= 0) & (y >= 0) & (x < cam.width) & (y < cam.height)
        idx = np.flatnonzero(inside)
        idx = idx[usable_mask(v, params.erode_px)[y[idx], x[idx]]]
        if len(idx) == 0:
            continue
        c = cam.center
        d = points[idx] - c
        dist = np.linalg.norm(d, axis=1)
        hits = caster.cast(np.broadcast_to(c, d.shape), d / dist[:, None])
        seen = hits.t >= dist * (1.0 - params.occlusion_tolerance)
        idx = idx[seen]
        obs[i, idx] = v.image[y[idx], x[idx]]
    return obs


def solve_log_gains(
    obs: np.ndarray, reference: Sequence[int], iterations: int, min_samples: int
) -> ExposureEstimate:
    """Alternating medians on ``log obs = g_view + log L_point`` per channel; ``obs`` [V, P, 3] with NaN
    where unobserved. Points seen by fewer than two views carry no information and are left out."""
    lo, hi = _VALID
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(obs) & (obs > lo) & (obs < hi)
        logs = np.where(ok, np.log(np.where(ok, obs, 1.0)), np.nan)
    shared = ok.sum(axis=0) >= 2  # [P, 3]
    logs = np.where(shared[None], logs, np.nan)
    counts = np.isfinite(logs).any(axis=2).sum(axis=1)  # [V] points usable per view
    g = np.zeros((obs.shape[0], 3))
    has = np.isfinite(logs)
    for _ in range(max(1, iterations)):
        with warnings.catch_warnings():  # all-NaN rows (unobserved points, unseen views) are expected
            warnings.simplefilter("ignore", RuntimeWarning)
            radiance = np.nanmedian(np.where(has, logs - g[:, None, :], np.nan), axis=0)  # [P, 3]
            resid = np.where(has, logs - radiance[None], np.nan)
            g_new = np.nanmedian(resid, axis=1)  # [V, 3]
        g = np.where(np.isfinite(g_new) & (counts >= min_samples)[:, None], g_new, 0.0)
    known = [i for i in reference if counts[i] >= min_samples]
    if known:
        g = g - g[known].mean(axis=0)
    g[counts < min_samples] = 0.0
    return ExposureEstimate(g.astype(np.float32), counts)


def estimate_exposures(
    views: Sequence[TrainView],
    vertices: np.ndarray,
    triangles: np.ndarray,
    glass_triangles: np.ndarray | None,
    reference: Sequence[int],
    params: ExposureParams,
    seed: int,
) -> ExposureEstimate:
    """Each view's log gain per channel from the colours of the corrected mesh's opaque parts."""
    from facade_pipeline.geometry.raycast import MeshRaycaster

    tris = np.asarray(triangles, np.int64).reshape(-1, 3)
    opaque = tris if glass_triangles is None else tris[~np.asarray(glass_triangles, bool)]
    verts = np.asarray(vertices, np.float64)
    pts, _, _ = sample_mesh(verts, opaque, params.samples, np.random.default_rng(seed))
    obs = observe(views, pts, MeshRaycaster(verts, tris), params)
    return solve_log_gains(obs, reference, params.iterations, params.min_samples)


def with_exposure_estimate(data: TrainData, seed: int) -> TrainData:
    """``data`` with its training views' exposure gains estimated from the photos (``EXPOSURE_ESTIMATE``;
    ``seed`` draws the mesh samples); a warning names the views with too few samples to estimate (their
    gain stays 1)."""
    m = data.init
    est = estimate_exposures(
        data.views, m.mesh_vertices, m.mesh_triangles, m.mesh_glass, data.train_idx, EXPOSURE_ESTIMATE, seed
    )
    few = [data.views[i].stem for i in data.train_idx if est.samples[i] < EXPOSURE_ESTIMATE.min_samples]
    if few:
        shown = ", ".join(few[:5]) + (f" and {len(few) - 5} more" if len(few) > 5 else "")
        log.warning(
            "exposure estimate: %d of %d training views have fewer than %d usable samples of the facade's "
            "opaque parts (non-glass points of the corrected mesh inside their facade mask) (%s); their gain "
            "stays 1. Expected where the mesh covers little of a view",
            len(few), len(data.train_idx), EXPOSURE_ESTIMATE.min_samples, shown,
        )  # fmt: skip
    return dataclasses.replace(data, exposure=est)
