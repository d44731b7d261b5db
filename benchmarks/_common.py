"""What every benchmark shares: a description of the machine and the commit, and putting its section on the
results page (benchmarks/RESULTS.md).

Benchmarks run as scripts (`python benchmarks/bench_x.py`), so this module is imported from the
script's own folder.
"""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, or what `platform` knows where that is missing."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def machine() -> str:
    """One line: CPU, cores, Python, torch and its threads (when imported), OS and the load average now.

    The load average goes with every figure: on a shared 2-core machine other work slows wall-clock times.
    """
    import sys

    parts = [f"{cpu_model()}, {os.cpu_count()} cores", f"Python {platform.python_version()}"]
    torch = sys.modules.get("torch")
    if torch is not None:
        parts.append(f"torch {torch.__version__} ({torch.get_num_threads()} threads)")
    parts.append(platform.system())
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (
        f"Machine: {', '.join(parts)}; load average {load} (other work on the machine slows wall-clock "
        f"figures). Commit {commit()}."
    )


def commit() -> str:
    """The checkout's commit (``-dirty`` when it has uncommitted changes): what a figure was measured on."""
    out = subprocess.run(
        ["git", "-C", str(RESULTS.parent), "describe", "--always", "--dirty"], capture_output=True, text=True
    )
    return out.stdout.strip() or "unknown"


def record_results(text: str) -> None:
    """Put a benchmark's section (Markdown starting with its ``## `` heading) on the results page: the
    section with the same heading is replaced, up to the next heading of its level or above, so the page
    holds the current table of each benchmark and the history stays in git; a new heading goes at the end."""
    text = text.strip("\n") + "\n"
    heading = text.splitlines()[0]
    level = len(heading) - len(heading.lstrip("#"))
    if level == 0:
        raise ValueError(f"a results section starts with a Markdown heading, found {heading!r}")
    lines = RESULTS.read_text().splitlines(keepends=True) if RESULTS.is_file() else []
    start = next((i for i, line in enumerate(lines) if line.rstrip("\n") == heading), None)
    if start is None:
        body = "".join(lines).rstrip("\n")
        RESULTS.write_text((body + "\n\n" if body else "") + text)
        return
    end = start + 1
    while end < len(lines):
        hashes = len(lines[end]) - len(lines[end].lstrip("#"))
        if 0 < hashes <= level and lines[end][hashes : hashes + 1] == " ":
            break
        end += 1
    tail = "".join(lines[end:])
    RESULTS.write_text("".join(lines[:start]) + text + ("\n" + tail if tail else ""))
