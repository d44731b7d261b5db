"""An earlier run's report must not pass for a new run's: evaluate's report goes before its manifest,
before anything else, so a run that stops (bad input, a crash, Ctrl-C, a kill in its first seconds) leaves
no report of other figures behind, and never a report without its manifest."""

from __future__ import annotations

import pytest

from facade_pipeline.config import default_params
from facade_pipeline.errors import PipelineError
from stages import evaluate
from stages._runner import execute


def _earlier_run(layout, params):
    files = [*evaluate.targets(layout, params), layout.manifest("evaluate")]
    assert layout.path("eval_report_html") in files and layout.path("eval_metrics") in files
    for path in files:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("figures of an earlier run")
    return files


def test_the_old_report_is_gone_before_evaluate_reads_anything(layout):
    params = default_params("evaluate", evaluate.Params)
    old = _earlier_run(layout, params)
    with pytest.raises(PipelineError):
        execute(evaluate, layout, params)  # no imported scene: it stops at its first read
    assert not any(p.exists() for p in old)


def test_a_kill_in_evaluates_first_seconds_leaves_no_report(layout, monkeypatch):
    """Interrupted while it lists its inputs (the seconds its imports take), before its own code runs."""
    params = default_params("evaluate", evaluate.Params)
    old = _earlier_run(layout, params)

    def killed(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluate, "inputs", killed)
    with pytest.raises(KeyboardInterrupt):
        execute(evaluate, layout, params)
    assert not any(p.exists() for p in old)
