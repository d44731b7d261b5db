"""The parameters of the ``evaluate`` stage (``[evaluate]``) and the LPIPS setting they select, apart from
the evaluation that uses them (torch, OpenCV, open3d), so that reading them costs no heavy import: doit
reads every stage's parameters to build its task list."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

from facade_pipeline.config import Fraction, PosInt, Positive
from facade_pipeline.errors import ConfigError
from facade_pipeline.evaluation.errors import MetricInputError
from facade_pipeline.evaluation.video import VideoParams
from facade_pipeline.training.params import AlignParams

LpipsConvention = Literal["alex_official", "vgg_3dgs", "vgg_official"]


def check_convention(convention: str) -> None:
    """``MetricInputError`` naming the valid LPIPS conventions when ``convention`` is none of them."""
    names = get_args(LpipsConvention)
    if convention not in names:
        raise MetricInputError(f"an LPIPS convention in {sorted(names)}", repr(convention))


@dataclass(frozen=True)
class LpipsSetting:
    """Which LPIPS figures to compute and where the weights are (None: the documented search order)."""

    conventions: tuple[LpipsConvention, ...]
    weights_dir: str | Path | None = None


@dataclass(frozen=True)
class EvaluateParams:
    """``[evaluate]``: what is rendered and measured, and how the report shows it."""

    render_training_views: bool
    """also render and measure the training views"""
    include_saved_variants: bool
    """evaluate the variants saved under variants/<name>/ beside 07_train"""
    lpips_conventions: tuple[LpipsConvention, ...]
    """LPIPS figures to compute; the first is the one the tables show"""
    lpips_weights_dir: str
    """folder or file of the LPIPS weights; "" searches $FACADE_LPIPS_DIR, then ../shared/lpips"""
    heatmap_max_error: Positive
    """absolute error (0-1, mean over RGB) at the top of the heat-map colour ramp"""
    align: AlignParams
    """``[evaluate.align]``: each measured view is also measured after its pose and exposure are fitted
    against the frozen model (``<split>_aligned`` in metrics.json); steps = 0 turns it off"""
    video: VideoParams
    """``[evaluate.video]``: the fly-through of each model (frames = 0: none)"""
    geometry_samples: PosInt | None = None
    """points sampled by area on each mesh for the geometry metrics against gt/. This and the next two:
    synthetic buildings only (configs/synthetic.toml); None: no truth to measure against"""
    geometry_max_match_m: Positive | None = None
    """samples farther than this (m) from both true glass and frames are left out"""
    gaussian_min_opacity: Fraction | None = None
    """Gaussians less opaque than this are left out of the geometry metrics"""

    def __post_init__(self) -> None:
        if not self.lpips_conventions:
            raise ConfigError(None, "at least one convention in evaluate.lpips_conventions", "none")
        for c in self.lpips_conventions:
            check_convention(c)

    @property
    def splits(self) -> tuple[str, ...]:
        """The splits measured: the held-out views, and the training views when asked."""
        return ("test", "train") if self.render_training_views else ("test",)

    @property
    def lpips(self) -> LpipsSetting:
        return LpipsSetting(self.lpips_conventions, self.lpips_weights_dir or None)
