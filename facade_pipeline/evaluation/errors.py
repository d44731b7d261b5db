"""Typed errors of the evaluation library. Both are ``ValueError`` too, so callers that only know the
standard library can still catch them."""

from __future__ import annotations

from facade_pipeline.errors import InputError, PipelineError


class MetricInputError(PipelineError, ValueError):
    """Arrays handed to a metric have the wrong shape, dtype or values (in memory: no file is named)."""

    def __init__(self, expected: str, found: str):
        super().__init__(None, expected, found)


class EmptyMaskError(MetricInputError):
    """A metric was asked to average over no pixel (or no point): the result would be NaN, so we raise."""


class LpipsWeightsError(InputError):
    """An LPIPS weights file that was asked for explicitly is missing, or a file found is not a valid one."""
