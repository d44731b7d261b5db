"""What one training step looks at: the window of a view (the whole image or a random patch on the
facade, ``random_window``), its data on the device (``view_tensors`` -> ``ViewTensors``), the view's camera
as training sees it (``camera``: with its pose correction) and its exposure gain (estimated from the photos
before training, ``estimate_view_exposures``; applied through ``exposure_gain``). Here apart from the loop
so that a step reads as draw, render, compare, update; every random draw comes from the trainer's one
generator, in the order the step makes them."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from facade_pipeline.training.data import TrainData, TrainView
from facade_pipeline.training.exposure import ExposureEstimate, ExposureParams, estimate_exposures
from facade_pipeline.training.params import TrainParams
from facade_pipeline.training.render import Camera, Window

if TYPE_CHECKING:
    from facade_pipeline.training.trainer import Trainer

log = logging.getLogger(__name__)
#: How the per-view exposure gains are estimated before training (``training.exposure``): its defaults.
EXPOSURE_ESTIMATE = ExposureParams()


def random_int(gen: torch.Generator, high: int) -> int:
    """A uniform integer in [0, ``high``) from ``gen``."""
    return int(torch.randint(high, (1,), generator=gen))


def random_window(tr: Trainer, index: int) -> Window:
    """The whole image, or a random patch of ``patch_px`` centred on a random facade pixel (patches off the
    facade would teach nothing when the loss is masked by it)."""
    cam, p = tr.cameras[index], tr.params.patch_px
    if p <= 0 or (p >= cam.width and p >= cam.height):
        return (0, 0, cam.width, cam.height)
    pw, ph = min(p, cam.width), min(p, cam.height)
    mask = tr.data.views[index].facade_mask
    ys, xs = np.nonzero(mask) if tr.params.mask_by_facade else (np.zeros(0), np.zeros(0))
    if len(xs) == 0:
        return (
            random_int(tr.generator, cam.width - pw + 1),
            random_int(tr.generator, cam.height - ph + 1),
            pw,
            ph,
        )
    k = random_int(tr.generator, len(xs))
    x0 = int(np.clip(xs[k] - pw // 2, 0, cam.width - pw))
    y0 = int(np.clip(ys[k] - ph // 2, 0, cam.height - ph))
    return (x0, y0, pw, ph)


@dataclass
class ViewTensors:
    """A window of a view's data on the device."""

    image: Tensor  # [H, W, 3]
    mask: Tensor  # [H, W] bool: facade mask (all True when not masking)
    glass: Tensor  # [H, W] bool
    prior: Tensor  # [H, W, 3]
    prior_valid: Tensor  # [H, W] bool
    clipped: Tensor | None = None  # [H, W, 3] bool: channels the photo clipped; None: none


def view_tensors(view: TrainView, window: Window, mask_by_facade: bool, device: torch.device) -> ViewTensors:
    """``view``'s photo, masks and normal prior inside ``window`` (x0, y0, w, h) on ``device``."""
    x0, y0, w, h = window
    sl = (slice(y0, y0 + h), slice(x0, x0 + w))

    def t(a: np.ndarray, dtype=torch.float32) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(a[sl]), dtype=dtype, device=device)

    mask = (
        t(view.facade_mask, torch.bool)
        if mask_by_facade
        else torch.ones(h, w, dtype=torch.bool, device=device)
    )
    return ViewTensors(
        t(view.image),
        mask,
        t(view.glass_mask, torch.bool),
        t(view.normal_prior),
        t(view.normal_valid, torch.bool),
        None if view.clipped is None else t(view.clipped, torch.bool),
    )


def camera(tr: Trainer, index: int) -> Camera:
    """View ``index``'s camera as training sees it: with its pose correction when poses are refined."""
    cam = tr.cameras[index]
    if tr.corrections is None:
        return cam
    return Camera(cam.K, tr.corrections.cam_from_world(index, cam.cam_from_world), cam.width, cam.height)


def estimate_view_exposures(p: TrainParams, data: TrainData) -> ExposureEstimate | None:
    """The training views' exposure gains estimated from the photos (``exposure_estimate``), else None; a
    warning names the views with too few samples to estimate (their gain stays 1)."""
    if not p.exposure_estimate:
        return None
    m = data.init
    est = estimate_exposures(
        data.views, m.mesh_vertices, m.mesh_triangles, m.mesh_glass, data.train_idx, EXPOSURE_ESTIMATE, p.seed
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
    return est


def exposure_gain(tr: Trainer, index: int) -> Tensor | None:
    """View ``index``'s exposure gain per colour channel [3] as estimated before training
    (``exposure_estimate``), relative to the training views' geometric mean so that the splats keep the
    mean exposure; None for held-out views and without the estimate."""
    if index not in tr.data.train_idx or tr.exposure is None:
        return None
    return torch.as_tensor(tr.exposure.log_gain[index], device=tr.device).exp()


@torch.no_grad()
def exposure_gains(tr: Trainer) -> dict[str, list[float]]:
    """Each training view's exposure gain per colour channel as trained (stem -> [r, g, b]); empty when
    training assumed one exposure for all views."""
    out = {}
    for i in tr.data.train_idx:
        gain = exposure_gain(tr, i)
        if gain is not None:
            out[tr.data.views[i].stem] = [round(float(x), 5) for x in gain]
    return out
