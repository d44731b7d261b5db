"""The summary table of benchmarks/gpu_check.sh, from the logs it wrote into OUT:

    python benchmarks/gpu_summary.py OUT GSPLAT_BUILD_S ACCURACY_ITERS WALL_S

Targets: mlp at most 12 ms and sh at most 8 ms per whole-image iteration of demo on one H100 or H200.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine  # noqa: E402

TARGET_MS = {"mlp": 12.0, "sh": 8.0}
SPEED = re.compile(r"^(\w[\w ,]*): ([\d.]+) ms per iteration, peak ([\d.na]+) GiB, (\d+) splats", re.M)
ACCURACY = re.compile(
    r"^(\w[\w ,]*): glass PSNR ([\d.]+) dB, facade PSNR ([\d.]+) dB, normal error ([\d.]+) deg, (\d+) s"
    r"(?:; aligned: glass PSNR ([\d.]+) dB)?",
    re.M,
)


def read(out: Path, name: str) -> str:
    f = out / name
    return f.read_text() if f.is_file() else ""


def summary(out: Path, build_s: str, accuracy_iters: str, wall_s: str) -> str:
    counts = re.compile(r"\d+ (passed|failed|skipped)")
    tests = [ln for ln in read(out, "tests.log").splitlines() if counts.search(ln)]
    rows = [
        ("gsplat built from its wheel", f"{build_s} s"),
        ("CUDA tests", tests[-1].strip("= ") if tests else "no result (tests.log)"),
    ]
    for name, ms, mem, n in SPEED.findall(read(out, "speed.log")):
        target = TARGET_MS.get(name)
        verdict = "met" if target is not None and float(ms) <= target else "NOT met"
        met = "" if target is None else f" (target <= {target:g}: {verdict})"
        rows.append((f"{name}, gsplat: ms per iteration", f"{float(ms):.1f}{met}"))
        rows.append((f"{name}, gsplat: peak GPU memory GiB, splats", f"{mem}, {n}"))
    for name, glass, facade, normal, wall, aligned in ACCURACY.findall(read(out, "accuracy.log")):
        rows.append(
            (
                f"{name}, {accuracy_iters} whole-image iterations: held-out glass PSNR dB as imported / "
                "aligned, facade PSNR dB, normal error on glass deg, wall s",
                f"{glass} / {aligned or '-'}, {facade}, {normal}, {wall}",
            )
        )
    rows.append(("the whole check, wall s", wall_s))
    try:
        import torch

        gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU"
        where = f"{machine()} GPU: {gpu} (torch {torch.__version__})."
    except Exception as e:  # the summary still prints what the logs hold
        where = f"{machine()} (torch not readable: {e})"
    lines = ["## GPU check (benchmarks/gpu_check.sh)", "", where, "", "| what | figure |", "| --- | --- |"]
    lines += [f"| {a} | {b} |" for a, b in rows]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(summary(Path(sys.argv[1]), *sys.argv[2:5]))
