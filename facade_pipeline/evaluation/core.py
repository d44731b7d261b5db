"""The one evaluation of a trained model on a list of views: what train_gs reports of its held-out views,
what the evaluate stage writes into metrics.json and the report, and what the benchmarks print.

Each view is rendered whole (``render_views``; or first aligned to the frozen model, pose and exposure
gain fitted over its facade mask by ``training.corrections.align_view``, then rendered from the fitted
pose with the gain applied before the clip to [0, 1]) and measured against its photo per region
(``image_eval.REGIONS``: facade, glass, glass interior, frames) with PSNR, masked SSIM and LPIPS under the
configured conventions; where the view carries a normal prior, also the rendered normals' angle error on
glass. A row per view, and means over the views (``image_eval.mean_metrics``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from facade_pipeline.evaluation.image_eval import LpipsSetting, mean_metrics, region_masks, view_metrics
from facade_pipeline.evaluation.render_views import TrainedModel, align_trained, render_trained
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.training.data import TrainData, TrainView
from facade_pipeline.training.params import AlignParams


@dataclass(frozen=True)
class EvalView:
    """A view to measure: its camera, its photo [H, W, 3] in [0, 1], the facade and glass masks [H, W]
    bool and, optionally, the normal prior [H, W, 3] (world, unit) with its validity [H, W] bool and the
    photo's clipped pixels [H, W] bool (any channel: ``image_eval.region_masks``'s ``unclipped``)."""

    stem: str
    camera: PinholeCamera
    image: np.ndarray
    facade_mask: np.ndarray
    glass_mask: np.ndarray
    normal_prior: np.ndarray | None = None
    normal_valid: np.ndarray | None = None
    clipped: np.ndarray | None = None

    @classmethod
    def of_train_view(cls, v: TrainView, mask_by_facade: bool = True) -> EvalView:
        """A training data view, measured over its facade mask (over the whole image when training did not
        mask by the facade, as it then learnt the whole image); its clipped channels (None: none) as
        clipped pixels."""
        facade = v.facade_mask if mask_by_facade else np.ones_like(v.facade_mask, dtype=bool)
        clipped = np.zeros_like(facade) if v.clipped is None else np.asarray(v.clipped).any(axis=-1)
        return cls(v.stem, v.camera, v.image, facade, v.glass_mask, v.normal_prior, v.normal_valid, clipped)


def views_of(data: TrainData, indices: Sequence[int], mask_by_facade: bool = True) -> list[EvalView]:
    """The views ``indices`` of ``data`` (``EvalView.of_train_view``)."""
    return [EvalView.of_train_view(data.views[i], mask_by_facade) for i in indices]


@dataclass(frozen=True)
class MeasuredView:
    """One measured view: its row (``view``, ``metrics`` per region, ``normal_error_glass_deg`` where the
    view has a prior, ``alignment`` when aligned) and the render [H, W, 3] in [0, 1] that was measured."""

    row: dict[str, Any]
    rgb: np.ndarray


def normal_error_glass_deg(normal: np.ndarray, view: EvalView) -> float | None:
    """Mean angle (deg) between the rendered normals [H, W, 3] (normalised here) and the view's normal
    prior over its glass region where the prior is valid; None where no such pixel is."""
    assert view.normal_prior is not None and view.normal_valid is not None
    n = torch.nn.functional.normalize(torch.as_tensor(normal), dim=-1)
    cos = (n * torch.as_tensor(view.normal_prior, dtype=n.dtype)).sum(-1).clamp(-1, 1)
    ok = torch.as_tensor(view.facade_mask & view.glass_mask & view.normal_valid)
    if not bool(ok.any()):
        return None
    return float(torch.rad2deg(torch.arccos(cos[ok])).mean())


def measure_view(
    tm: TrainedModel, view: EvalView, setting: LpipsSetting, align: AlignParams | None = None
) -> MeasuredView:
    """Render ``view`` with ``tm`` (aligned first when ``align`` has steps) and measure it."""
    if align is not None and align.steps > 0:
        a = align_trained(tm, view.camera, view.image, view.facade_mask, align)
        render, alignment = a.render, a.alignment.summary()
    else:
        render, alignment = render_trained(tm, view.camera, view.facade_mask), None
    masks = region_masks(view.facade_mask, view.glass_mask, view.clipped)
    row: dict[str, Any] = {"view": view.stem, "metrics": view_metrics(render.rgb, view.image, masks, setting)}
    if view.normal_prior is not None:
        row["normal_error_glass_deg"] = normal_error_glass_deg(render.normal, view)
    if alignment is not None:
        row["alignment"] = alignment
    return MeasuredView(row, render.rgb)


def evaluate_views(
    tm: TrainedModel,
    views: Sequence[EvalView],
    setting: LpipsSetting,
    align: AlignParams | None = None,
    on_view: Callable[[EvalView, MeasuredView], None] | None = None,
) -> dict[str, Any]:
    """``{"views": [row per view], "mean": means over them}`` (``measure_view``); ``on_view`` is called
    with each view and its measurement as it is made (to write its render, to advance a progress bar)."""
    rows = []
    for view in views:
        m = measure_view(tm, view, setting, align)
        rows.append(m.row)
        if on_view is not None:
            on_view(view, m)
    return {"views": rows, "mean": mean_metrics(rows, setting.conventions)}


def headline(result: dict[str, Any]) -> dict[str, Any]:
    """The figures quoted beside a training run: mean PSNR and SSIM over the facade, PSNR on glass, on
    its interior and on the facade's unclipped pixels, and the normal error on glass (None where no view
    had the region or a prior)."""
    mean = result["mean"]

    def get(region: str, key: str) -> Any:
        return (mean.get(region) or {}).get(key)

    return {
        "psnr": get("facade", "psnr"),
        "ssim": get("facade", "ssim"),
        "psnr_glass": get("glass", "psnr"),
        "psnr_glass_interior": get("glass_interior", "psnr"),
        "psnr_unclipped": get("unclipped", "psnr"),
        "normal_error_glass_deg": mean.get("normal_error_glass_deg"),
    }
