"""The benchmarks keep one current section per heading on the results page."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

COMMON = Path(__file__).resolve().parents[1] / "benchmarks" / "_common.py"


@pytest.fixture
def common(tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("bench_common", COMMON)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr(module, "RESULTS", tmp_path / "RESULTS.md")
    page = "# Results\n\nintro\n\n## A\n\nold a\n\n### A, detail\n\nold detail\n\n## B\n\nb\n"
    module.RESULTS.write_text(page)
    return module


def test_a_section_with_the_same_heading_is_replaced_with_its_subsections(common):
    common.record_results("\n## A\n\nnew a\n")
    text = common.RESULTS.read_text()
    assert "new a" in text and "old a" not in text and "old detail" not in text
    assert text.index("## A") < text.index("## B") and text.count("## A") == 1
    assert text.startswith("# Results\n\nintro\n")


def test_a_new_heading_goes_at_the_end_and_the_last_section_can_be_replaced(common):
    common.record_results("## C\n\nc")
    common.record_results("## B\n\nnew b\n")
    text = common.RESULTS.read_text()
    assert text.endswith("## C\n\nc\n") and "new b" in text and "\nb\n" not in text


def test_a_section_without_a_heading_is_refused(common):
    with pytest.raises(ValueError, match="heading"):
        common.record_results("no heading\n")
