"""What every benchmark shares: a description of the machine and appending a section to RESULTS.md.

Benchmarks run as scripts (`python benchmarks/bench_x.py`), so this module is imported from the
script's own folder.
"""

from __future__ import annotations

import os
import platform
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
        "figures)."
    )


def append_results(text: str) -> None:
    """Append a section (Markdown) to benchmarks/RESULTS.md, starting on a new line."""
    with RESULTS.open("a") as fh:
        fh.write(text if text.startswith("\n") else "\n" + text)
        if not text.endswith("\n"):
            fh.write("\n")
