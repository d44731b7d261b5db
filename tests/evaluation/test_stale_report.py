"""An earlier run's report must not pass for a new run's: evaluate removes its report before anything else,
so a run that stops (bad input, a crash, Ctrl-C) leaves no report of other figures behind."""

from __future__ import annotations

import pytest

from facade_pipeline.config import default_params, default_run_settings
from facade_pipeline.errors import PipelineError
from stages import evaluate


def test_the_old_report_is_gone_before_evaluate_reads_anything(layout):
    params = default_params("evaluate", evaluate.Params)
    old = evaluate.targets(layout, params)
    assert layout.path("eval_report_html") in old
    for path in old:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("figures of an earlier run")
    with pytest.raises(PipelineError):
        evaluate.run(layout, params, default_run_settings())  # no imported scene: it stops at its first read
    assert not any(p.exists() for p in old)
