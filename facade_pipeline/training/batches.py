"""What one training step looks at: the window of a view (the whole image or a random patch on the
facade, ``random_window``), its data on the device (``view_tensors`` -> ``ViewTensors``), the view's camera
as training sees it (``camera``: with its pose correction) and its exposure gain (estimated from the photos
before training and carried by the data, ``training.exposure``; applied through ``exposure_gain``). Here
apart from the loop so that a step reads as draw, render, compare, update; each function takes the parts of
the trainer it reads, and every random draw comes from the trainer's one generator, in the order the step
makes them."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from facade_pipeline.training.corrections import ViewCorrections
from facade_pipeline.training.data import TrainData, TrainView
from facade_pipeline.training.render import Camera, Window


def random_int(gen: torch.Generator, high: int) -> int:
    """A uniform integer in [0, ``high``) from ``gen``."""
    return int(torch.randint(high, (1,), generator=gen))


def random_window(
    cam: Camera, facade_mask: np.ndarray | None, patch_px: int, gen: torch.Generator
) -> Window:
    """The whole image, or a random patch of ``patch_px`` centred on a random pixel of ``facade_mask``
    (patches off the facade would teach nothing when the loss is masked by it; None: anywhere)."""
    p = patch_px
    if p <= 0 or (p >= cam.width and p >= cam.height):
        return (0, 0, cam.width, cam.height)
    pw, ph = min(p, cam.width), min(p, cam.height)
    ys, xs = np.nonzero(facade_mask) if facade_mask is not None else (np.zeros(0), np.zeros(0))
    if len(xs) == 0:
        return (
            random_int(gen, cam.width - pw + 1),
            random_int(gen, cam.height - ph + 1),
            pw,
            ph,
        )
    k = random_int(gen, len(xs))
    x0 = int(np.clip(xs[k] - pw // 2, 0, cam.width - pw))
    y0 = int(np.clip(ys[k] - ph // 2, 0, cam.height - ph))
    return (x0, y0, pw, ph)


@dataclass
class ViewTensors:
    """A window of a view's data on the device."""

    image: Tensor  # [H, W, 3]
    mask: Tensor  # [H, W] bool: facade mask (all True when not masking)
    glass: Tensor  # [H, W] bool
    facade: Tensor  # [H, W] bool: facade mask (also when not masking)
    prior: Tensor  # [H, W, 3]
    prior_valid: Tensor  # [H, W] bool
    clipped: Tensor | None = None  # [H, W, 3] bool: channels the photo clipped; None: none


def views_on_device(
    views: tuple[TrainView, ...], mask_by_facade: bool, device: torch.device
) -> tuple[ViewTensors, ...]:
    """Every view's whole photo, masks and normal prior on ``device``, moved there once before training so
    that a step slices its window there instead of copying it from the host (on the CPU the tensors share
    the arrays' memory)."""

    def t(a: np.ndarray, dtype=torch.float32) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

    def on_device(v: TrainView) -> ViewTensors:
        facade = t(v.facade_mask, torch.bool)
        return ViewTensors(
            t(v.image),
            facade if mask_by_facade else torch.ones_like(facade),  # one facade mask on the device
            t(v.glass_mask, torch.bool),
            facade,
            t(v.normal_prior),
            t(v.normal_valid, torch.bool),
            None if v.clipped is None else t(v.clipped, torch.bool),
        )

    return tuple(on_device(v) for v in views)


def view_tensors(view: ViewTensors, window: Window, clipped: np.ndarray | None) -> ViewTensors:
    """``view``'s data (``views_on_device``) inside ``window`` (x0, y0, w, h). ``clipped`` is the view's
    ``TrainView.clipped`` on the host: a window in which the photo clipped no channel gets None there, for
    which the camera's clipping (``losses.recorded``) is the render itself, so that the loss and the step's
    figures skip its operations on the window (a step's few dozen operations on its window each cost
    a wait for the CPU's threads; read on the host, the check makes a GPU wait for nothing)."""
    x0, y0, w, h = window
    sl = (slice(y0, y0 + h), slice(x0, x0 + w))
    out = ViewTensors(
        *(None if (x := getattr(view, f.name)) is None else x[sl] for f in dataclasses.fields(ViewTensors))
    )
    if out.clipped is not None and (clipped is None or not clipped[sl].any()):
        out = dataclasses.replace(out, clipped=None)
    return out


def camera(cam: Camera, corrections: ViewCorrections | None, index: int) -> Camera:
    """View ``index``'s camera ``cam`` as training sees it: with its pose correction when poses are
    refined (``corrections``)."""
    if corrections is None:
        return cam
    return Camera(cam.K, corrections.cam_from_world(index, cam.cam_from_world), cam.width, cam.height)


def exposure_gain(gains: Tensor | None, train_idx: tuple[int, ...], index: int) -> Tensor | None:
    """View ``index``'s exposure gain per colour channel [3] of ``gains`` [V, 3], as estimated before
    training (``exposure_estimate``), relative to the training views' geometric mean so that the splats
    keep the mean exposure; None for held-out views and without the estimate (``gains`` None)."""
    if index not in train_idx or gains is None:
        return None
    return gains[index]


@torch.no_grad()
def exposure_gains(gains: Tensor | None, data: TrainData) -> dict[str, list[float]]:
    """Each training view's exposure gain per colour channel as trained (stem -> [r, g, b]); empty when
    training assumed one exposure for all views."""
    out = {}
    for i in data.train_idx:
        gain = exposure_gain(gains, data.train_idx, i)
        if gain is not None:
            out[data.views[i].stem] = [round(float(x), 5) for x in gain]
    return out
