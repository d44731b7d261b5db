"""The summary table of benchmarks/gpu_check.sh, from the logs it wrote into OUT, and the plot of accuracy
against time (OUT/accuracy_vs_time.svg):

    python benchmarks/gpu_summary.py OUT GSPLAT_BUILD_S WALL_S

Targets: mlp at most 12 ms and sh at most 8 ms per whole-image iteration of demo on one H100 or H200.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine  # noqa: E402

from facade_pipeline.evaluation.report import svg_scatter  # noqa: E402

TARGET_MS = {"mlp": 12.0, "sh": 8.0}
SPEED = re.compile(r"^(\w[\w ,]*): ([\d.]+) ms per iteration, peak ([\d.na]+) GiB, (\d+) splats", re.M)
#: the speed logs, by what they time: the GPU budget, with the reflection MLP in float32 (``--fp32-mlp``),
#: again compiled (``--compile``), the CPU budget
SPEED_LOGS = {
    "gpu": "gpu budget",
    "gpu_fp32": "gpu budget, float32 MLP",
    "gpu_compiled": "gpu budget compiled",
    "cpu": "cpu budget",
}


def read(out: Path, name: str) -> str:
    f = out / name
    return f.read_text() if f.is_file() else ""


def results(out: Path) -> list[dict]:
    """The accuracy points (``result:`` lines of accuracy_<N>.log), by iterations."""
    rows = []
    for f in out.glob("accuracy_*.log"):
        lines = f.read_text().splitlines()
        rows += [json.loads(ln.removeprefix("result: ")) for ln in lines if ln.startswith("result: ")]
    return sorted(rows, key=lambda r: r["iterations"])


def _f(x, fmt: str) -> str:
    return format(x, fmt) if isinstance(x, (int, float)) else "-"


def summary(out: Path, build_s: str, wall_s: str) -> str:
    counts = re.compile(r"\d+ (passed|failed|skipped)")
    tests = [ln for ln in read(out, "tests.log").splitlines() if counts.search(ln)]
    rows = [
        ("gsplat built from its wheel", f"{build_s} s"),
        ("CUDA tests", tests[-1].strip("= ") if tests else "no result (tests.log)"),
    ]
    for log, budget in SPEED_LOGS.items():
        found = SPEED.findall(read(out, f"speed_{log}.log"))
        if not found:
            rows.append((f"speed, {budget}", f"no result (speed_{log}.log)"))
        for name, ms, mem, n in found:
            target = TARGET_MS.get(name)
            verdict = "met" if target is not None and float(ms) <= target else "NOT met"
            met = "" if target is None else f" (target <= {target:g}: {verdict})"
            rows.append((f"{name}, {budget}: ms per iteration", f"{float(ms):.1f}{met}"))
            rows.append((f"{name}, {budget}: peak GPU memory GiB, splats", f"{mem}, {n}"))
    for r in results(out):
        im, al = r["imported"], r["aligned"] or {}
        rows.append(
            (
                f"{r['variant']}{' compiled' if r.get('compiled') else ''}, {r['iterations']} whole-image "
                "iterations: held-out glass PSNR dB as "
                "imported / aligned, facade PSNR dB as imported / aligned, SSIM, LPIPS (aligned), normal "
                "error on glass deg, splats, training wall s",
                f"{_f(im['psnr_glass'], '.2f')} / {_f(al.get('psnr_glass'), '.2f')}, "
                f"{_f(im['psnr'], '.2f')} / {_f(al.get('psnr'), '.2f')}, "
                f"{_f(al.get('ssim', im['ssim']), '.3f')}, "
                f"{_f(al.get('lpips', im.get('lpips')), '.3f')}, {_f(im['normal_error_glass_deg'], '.2f')}, "
                f"{r['splats']}, {r['wall_s']:.0f}",
            )
        )
        checks = [c for c in r.get("checks") or [] if c[2] is not None]
        if checks:  # the run's whole-view PSNR of its training views, as train_gs checks it ([run] log_every)
            best = max(checks, key=lambda c: c[2])
            rows.append(
                (
                    f"{r['variant']}, {r['iterations']} iterations: training views' whole-view PSNR dB "
                    "(splats) at the first check, the best, the last",
                    " / ".join(f"{c[2]:.2f} ({c[1]}) at {c[0]}" for c in (checks[0], best, checks[-1])),
                )
            )
        if r.get("stopped"):
            rows.append((f"{r['variant']}, {r['iterations']} iterations: stopped", r["stopped"]))
    for ln in read(out, "skipped.log").splitlines():
        rows.append(("accuracy point not run", ln.removeprefix("skipped: ")))
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


def plot(out: Path) -> str | None:
    """Held-out facade and glass PSNR, aligned, against training wall time (SVG); None without points."""
    pts, labels = [], []
    for r in results(out):
        al = r["aligned"] or r["imported"]
        for region, key in (("facade", "psnr"), ("glass", "psnr_glass")):
            if isinstance(al.get(key), (int, float)):
                pts.append((r["wall_s"], al[key]))
                labels.append(f"{region}, {r['iterations']} iterations")
    if not pts:
        return None
    return svg_scatter(pts, labels, "demo on the GPU: held-out PSNR (aligned) against training time",
                       "training wall time (s)", "PSNR (dB)")  # fmt: skip


if __name__ == "__main__":
    folder = Path(sys.argv[1])
    print(summary(folder, *sys.argv[2:4]))
    svg = plot(folder)
    if svg is not None:
        (folder / "accuracy_vs_time.svg").write_text(svg)
