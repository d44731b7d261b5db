"""What accuracy costs in time: train_gs swept one factor at a time around a base configuration.

Factors: training iterations, image resolution (training views downscaled; held-out views are always
measured at full resolution), number of Gaussians (initial points and the densification cap), reflection
variant (sh / envmap / mlp) and the reflection MLP's L, depth, width and skip. Each run trains in its own
process (so its peak RSS is its own) on the building's upstream outputs (06_bake_normals and before, made
first if missing) and is measured on the held-out views (every ``test_every``-th) over the facade mask:
PSNR, SSIM, LPIPS (VGG, [0, 1], the 3DGS convention; "unavailable" without weights). Writes a Markdown
table, a Pareto plot (held-out PSNR against training wall time, SVG) and the per-stage times of the whole
DAG read from the manifests of the buildings given with ``--dag``; ``--append`` adds them, with the machine,
to benchmarks/RESULTS.md.

    python benchmarks/accuracy_vs_time.py --quick --append          # a few minutes on 2 cores (synthetic64)
    python benchmarks/accuracy_vs_time.py --building demo --append  # the full sweep (hours on 2 cores)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import machine, record_results  # noqa: E402

from facade_pipeline.config import load_building_config, to_dict  # noqa: E402
from facade_pipeline.evaluation.core import evaluate_views, views_of  # noqa: E402
from facade_pipeline.evaluation.image_eval import LpipsSetting  # noqa: E402
from facade_pipeline.evaluation.render_views import from_trainer  # noqa: E402
from facade_pipeline.evaluation.report import pareto_front, svg_scatter  # noqa: E402
from facade_pipeline.geometry.camera import PinholeCamera  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.training.data import TrainView  # noqa: E402
from facade_pipeline.training.params import TrainParams, replace_keys  # noqa: E402
from facade_pipeline.training.render import training_rasterizer  # noqa: E402
from facade_pipeline.training.trained import TrainedModelFiles  # noqa: E402
from facade_pipeline.training.trainer import build_trainer, resolve_device, train  # noqa: E402
from stages import PIPELINE, load_stage  # noqa: E402
from stages._runner import execute, load_params  # noqa: E402

LPIPS_CONVENTION = "vgg_3dgs"
UPSTREAM = [s for s in PIPELINE if PIPELINE.index(s) < PIPELINE.index("train_gs")]


# ------------------------------------------------------------------------------------------ the sweep


def sweep(quick: bool) -> list[tuple[str, dict[str, Any]]]:
    """(label, changes) pairs, one factor at a time around the base. ``changes`` holds train_gs keys, dotted
    for its tables (``densify.max_gaussians``, ``reflection.mlp.depth``), and ``scale`` (training-image
    resolution factor)."""
    if quick:
        iters = [20, 80]
        gaussians = [(500, 1000), (2000, 6000)]
        arch = [
            {"mlp.fourier_levels": 4},
            {"mlp.depth": 2},
            {"mlp.width": 32},
            {"mlp.skip": False},
            {"proxy.channels": 0},
        ]
        scales = [0.5]
    else:
        iters = [1000, 3000, 10000]
        gaussians = [(20000, 50000), (100000, 300000), (100000, 1000000)]
        arch = [
            {"mlp.fourier_levels": 10},
            {"mlp.fourier_levels": 14},
            {"mlp.fourier_levels": 16},
            {"mlp.depth": 6},
            {"mlp.width": 256},
            {"mlp.skip": False},
            {"proxy.channels": 0},
        ]
        scales = [0.25, 0.5]
    runs: list[tuple[str, dict[str, Any]]] = [(f"iterations={n}", {"iterations": n}) for n in iters]
    runs += [(f"resolution x{s}", {"scale": s}) for s in scales]
    runs += [
        (f"gaussians<={cap}", {"init_max_points": n, "init_mesh_samples": n, "densify.max_gaussians": cap})
        for n, cap in gaussians
    ]
    runs += [(f"reflection={m}", {"reflection.model": m}) for m in ("sh", "envmap")]
    runs += [
        ("mlp " + ", ".join(f"{k}={v}" for k, v in a.items()), {f"reflection.{k}": v for k, v in a.items()})
        for a in arch
    ]
    return runs


def base_params(building: str, quick: bool) -> TrainParams:
    """The building's train_gs parameters; the quick sweep shortens the run (middle of its iterations)."""
    p = load_building_config(building).section("train_gs", TrainParams)
    return dataclasses.replace(p, iterations=40) if quick else p


def apply(p: TrainParams, changes: dict[str, Any]) -> TrainParams:
    return replace_keys(p, {k: v for k, v in changes.items() if k != "scale"})


# ------------------------------------------------------------------------------------------ one run


def downscale(view: TrainView, scale: float) -> TrainView:
    """The view at ``scale`` x its resolution: area-averaged image, nearest masks and normals, scaled K."""
    if scale == 1.0:
        return view
    cam = view.camera
    w, h = max(1, round(cam.width * scale)), max(1, round(cam.height * scale))
    sx, sy = w / cam.width, h / cam.height
    K = np.diag([sx, sy, 1.0]) @ cam.K
    K[0, 2], K[1, 2] = (cam.K[0, 2] + 0.5) * sx - 0.5, (cam.K[1, 2] + 0.5) * sy - 0.5
    near = cv2.INTER_NEAREST

    def rs(a: np.ndarray, interp: int) -> np.ndarray:
        return cv2.resize(a, (w, h), interpolation=interp)

    return TrainView(
        view.stem,
        PinholeCamera(K, cam.cam_from_world, w, h),
        rs(view.image, cv2.INTER_AREA),
        rs(view.facade_mask.astype(np.uint8), near) > 0,
        rs(view.glass_mask.astype(np.uint8), near) > 0,
        rs(view.normal_prior, near),
        rs(view.normal_valid.astype(np.uint8), near) > 0,
    )


def slug(label: str) -> str:
    """A folder name for a run label (``mlp mlp.depth=4`` -> ``mlp_mlp.depth-4``)."""
    return "".join(c if c.isalnum() or c in "._" else ("-" if c == "=" else "_") for c in label).strip("_")


def child(
    building: str, data_root: str, quick: bool, label: str, changes: dict[str, Any], save: bool = False
) -> dict[str, Any]:
    """Train one configuration and measure it on the held-out views (full resolution); ``save`` keeps the
    model under ``variants/<label>/`` for the evaluate stage."""
    train_stage = load_stage("train_gs")
    layout = BuildingLayout.for_building(building, data_root)
    p = apply(base_params(building, quick), changes)
    full = train_stage.load_train_data(layout, p)
    scale = float(changes.get("scale", 1.0))
    data = dataclasses.replace(full, views=tuple(downscale(v, scale) for v in full.views))
    run = load_building_config(building).run
    device = resolve_device(run.device)
    t0 = time.perf_counter()
    raster = training_rasterizer(run.raster_backend, p.lowpass_sigma_px, device)
    tr = build_trainer(p, data, raster, device, run.compile)
    train(tr)
    t_train = time.perf_counter() - t0
    tm = from_trainer(tr, label, run.raster_backend)
    t0 = time.perf_counter()
    mean = evaluate_views(tm, views_of(full, full.test_idx), LpipsSetting((LPIPS_CONVENTION,)))["mean"]
    t_eval = time.perf_counter() - t0
    if save:
        split = {
            k: [full.views[i].stem for i in idx]
            for k, idx in (("train", full.train_idx), ("test", full.test_idx))
        }
        files = TrainedModelFiles.variant(layout.path("variant_dir", variant=slug(label)), to_dict(p))
        strategy = p.reflection_strategy(data.bounds)
        files.save(tr.state.model, tr.state.reflection, strategy, data.bounds, split)
    return {
        "label": label,
        "changes": changes,
        "train_s": round(t_train, 2),
        "eval_s": round(t_eval, 2),
        "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "n_gaussians": tr.state.model.n,
        "test_views": len(full.test_idx),
        "mean": mean,
        "params": to_dict(p),
    }


def run_child(args: argparse.Namespace, label: str, changes: dict[str, Any]) -> dict[str, Any]:
    cmd = (
        [
            sys.executable,
            __file__,
            "--building",
            args.building,
            "--data-root",
            args.data_root,
            "--child",
            json.dumps([label, changes]),
        ]
        + (["--quick"] if args.quick else [])
        + (["--save-variants"] if args.save_variants else [])
    )
    env = {**os.environ, "TQDM_DISABLE": "1"}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    if out.returncode != 0:
        raise RuntimeError(f"run {label!r} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def prepare(building: str, data_root: str) -> None:
    """Run the stages before train_gs that have no manifest yet (the whole upstream DAG once)."""
    layout = BuildingLayout.for_building(building, data_root)
    synthetic = load_building_config(building).building.kind == "synthetic"
    for name in UPSTREAM:
        if (name == "synthesize" and not synthetic) or layout.manifest(name).is_file():
            continue
        stage = load_stage(name)
        execute(stage, layout, load_params(stage, building))


# ------------------------------------------------------------------------------------------ output


def _cell(x: Any, digits: int) -> str:
    return "-" if x is None else (x if isinstance(x, str) else f"{x:.{digits}f}")


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| run | train s | eval s | peak MB | Gaussians | PSNR facade | PSNR glass | PSNR frames | SSIM | "
        f"LPIPS ({LPIPS_CONVENTION}) |"
    )
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        f, g, fr = (r["mean"].get(k) or {} for k in ("facade", "glass", "frames"))
        lines.append(
            f"| {r['label']} | {r['train_s']:.1f} | {r['eval_s']:.1f} | {r['peak_mb']:.0f} | "
            f"{r['n_gaussians']} | {_cell(f.get('psnr'), 2)} | {_cell(g.get('psnr'), 2)} | "
            f"{_cell(fr.get('psnr'), 2)} | {_cell(f.get('ssim'), 4)} | "
            f"{_cell((f.get('lpips') or {}).get(LPIPS_CONVENTION), 4)} |"
        )
    return "\n".join(lines)


def pareto(rows: list[dict[str, Any]]) -> tuple[str, list[str]]:
    """The SVG plot (PSNR against training time) and the labels of the Pareto-optimal runs."""
    ok = [r for r in rows if isinstance((r["mean"].get("facade") or {}).get("psnr"), float)]
    pts = [(r["train_s"], r["mean"]["facade"]["psnr"]) for r in ok]
    front = pareto_front(pts)
    svg = svg_scatter(
        pts,
        [r["label"] for r in ok],
        "Held-out facade PSNR vs training time (red: Pareto front)",
        "training wall time (s)",
        "PSNR (dB)",
        front,
    )
    return svg, [ok[i]["label"] for i in front]


def dag_times(data_root: str, building: str) -> str | None:
    """Per-stage wall time and peak memory of the whole DAG, from the manifests of ``building``."""
    layout = BuildingLayout.for_building(building, data_root)
    rows, total = [], 0.0
    for name in PIPELINE:
        path = layout.manifest(name)
        if not path.is_file():
            continue
        m = json.loads(path.read_text())
        total += m["wall_time_s"]
        rows.append(f"| {name} | {m['wall_time_s']:.1f} | {m['peak_memory_mb']:.0f} |")
    if not rows:
        return None
    return "\n".join(
        [
            f"DAG of `{building}` ({data_root}), from the manifests:",
            "",
            "| stage | wall s | peak MB |",
            "|---|---|---|",
            *rows,
            f"| total | {total:.1f} | |",
        ]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--quick", action="store_true", help="synthetic64-sized short runs: a few minutes on 2 cores"
    )
    ap.add_argument("--building", default=None, help="default: synthetic64 with --quick, else demo")
    ap.add_argument("--data-root", default=str(REPO / "data"))
    ap.add_argument(
        "--dag",
        nargs="*",
        default=["synthetic64", "demo"],
        help="buildings whose per-stage DAG times are reported (from their manifests)",
    )
    ap.add_argument(
        "--out",
        default=str(REPO / "benchmarks" / "accuracy_vs_time"),
        help="prefix of the written .md, .svg and .json",
    )
    ap.add_argument("--append", action="store_true", help="append the results to benchmarks/RESULTS.md")
    ap.add_argument(
        "--save-variants",
        action="store_true",
        help="keep each trained model under <building>/variants/<run>/: `evaluate` then compares them",
    )
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    a.building = a.building or ("synthetic64" if a.quick else "demo")
    if a.child:
        torch.set_num_threads(max(1, os.cpu_count() or 1))
        label, changes = json.loads(a.child)
        print(json.dumps(child(a.building, a.data_root, a.quick, label, changes, a.save_variants)))
        return
    t_all = time.perf_counter()
    prepare(a.building, a.data_root)
    rows = []
    for label, changes in [("base", {}), *sweep(a.quick)]:
        rows.append(run_child(a, label, changes))
        print(
            f"{label}: train {rows[-1]['train_s']:.1f} s, PSNR {rows[-1]['mean']['facade']}", file=sys.stderr
        )
    svg, front = pareto(rows)
    base = base_params(a.building, a.quick)
    mlp = base.reflection.mlp
    dags = [d for d in (dag_times(a.data_root, b) for b in a.dag) if d]
    sweep_s = time.perf_counter() - t_all
    text = "\n".join(
        [
            f"## Accuracy vs time ({'quick' if a.quick else 'full'} sweep, {a.building})",
            "",
            machine(),
            "",
            f"One factor at a time around the base: {base.iterations} iterations, reflection "
            f"`{base.reflection.model}` (L={mlp.fourier_levels}, depth {mlp.depth}, width "
            f"{mlp.width}, skip {mlp.skip}, environment proxy {base.reflection.proxy.channels} channels), "
            f"at most {base.densify.max_gaussians} Gaussians. "
            f"Metrics on the {rows[0]['test_views']} held-out views "
            f"(full resolution) over the facade mask; train s = training wall time of the run, peak MB = its "
            f"process's peak RSS. Whole sweep: {sweep_s / 60:.1f} min.",
            "",
            table(rows),
            "",
            f"Pareto-optimal (PSNR vs training time): {', '.join(front)}. Plot: "
            f"`benchmarks/{Path(a.out).name}.svg`.",
            "",
            *[d + "\n" for d in dags],
        ]
    )
    Path(a.out + ".md").write_text(text + "\n")
    Path(a.out + ".svg").write_text(svg + "\n")
    Path(a.out + ".json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)
    if a.append:
        record_results(text)


if __name__ == "__main__":
    main()
