"""Accuracy benchmark of train_gs: PSNR of the reflection models (``mlp``, ``sh``, ``envmap``) on the glass
pixels of held-out views, and the Gaussians' normal error on glass with and without the normal prior;
appends a section to benchmarks/RESULTS.md with the machine and the CPU budget.

    .venv/bin/python benchmarks/bench_train.py --data-root /tmp/bench [--building demo] [--iterations N]

The building is synthesized and imported under ``--data-root`` when missing (synthetic buildings only).
The normal prior and masks are the baked ones (06_bake_normals, through the stage's loader) when that stage
has completed, else the ground truth of gt/ (stated in the table). Every variant trains from the same
initialisation with the building's [train_gs] parameters (demo's carry a CPU budget: the one `make run`
trains with), overridden by the command-line options that are given.

On a GPU machine without the I/O stack (open3d, OpenEXR, pycolmap), train from a bundle made here (it holds
the exposure estimate, made here with open3d):

    .venv/bin/python benchmarks/bench_train.py --data-root /tmp/bench --save-bundle demo.npz
    python benchmarks/bench_train.py --bundle demo.npz --device cuda --iterations 3000 --patch-px 0

``--speed N`` measures instead of training to the end: milliseconds per iteration over N iterations after
``--warmup`` ones (the device synchronised around them) and the peak memory of the device, for each variant
of ``--only`` (benchmarks/gpu_check.sh runs it on a GPU).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import machine, record_results  # noqa: E402

from facade_pipeline.config import load_building_config  # noqa: E402
from facade_pipeline.evaluation.core import evaluate_views, headline, views_of  # noqa: E402
from facade_pipeline.evaluation.image_eval import INTERIOR_MARGIN_PX, LpipsSetting  # noqa: E402
from facade_pipeline.evaluation.params import EvaluateParams  # noqa: E402
from facade_pipeline.evaluation.render_views import from_trainer  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.splatting.types import LOWPASS_SIGMA_PX  # noqa: E402
from facade_pipeline.training.data import (  # noqa: E402
    InitGeometry,
    TrainData,
    TrainView,
    load_bundle,
    save_bundle,
    split_views,
)
from facade_pipeline.training.monitor import whole_view_psnr  # noqa: E402
from facade_pipeline.training.params import AlignParams, TrainParams, replace_keys  # noqa: E402
from facade_pipeline.training.render import training_rasterizer  # noqa: E402
from facade_pipeline.training.trainer import (  # noqa: E402
    TrainingDivergedError,
    build_trainer,
    resolve_device,
    train,
)

# The building's files are read with the I/O stack (open3d, OpenEXR, pycolmap), imported where they are read
# so that `--bundle` runs on a machine with torch alone.


def ensure_building(layout: BuildingLayout) -> None:
    from stages import load_stage
    from stages._runner import execute, load_params

    if layout.manifest("import_photogrammetry").is_file():  # imported already (a real building's way)
        return
    for name in ("synthesize", "import_photogrammetry"):
        stage = load_stage(name)
        if not layout.manifest(name).is_file():
            print(f"running {name} for {layout.building} ...", flush=True)
            execute(stage, layout, load_params(stage, layout.building))


def gt_data(layout: BuildingLayout, test_every: int) -> TrainData:
    """Views with the true normals and masks as prior (when bake_normals has not run)."""
    from facade_pipeline.io.images import read_image
    from facade_pipeline.io.meshes import read_points
    from facade_pipeline.scene import ImportedScene
    from facade_pipeline.synthetic.truth import SyntheticTruth

    scene = ImportedScene.load(layout)
    truth = SyntheticTruth.load(layout, scene.georef_from_local)
    views = []
    for v in scene.uav_views:
        normals, valid = truth.normal_map(v.stem)
        views.append(
            TrainView(
                v.stem,
                v.camera,
                read_image(layout.root / v.image).astype(np.float32) / 255.0,
                truth.mask("facade", v.stem),
                truth.mask("glass", v.stem),
                normals.astype(np.float32),
                valid,
            )
        )
    vertices, triangles = truth.mesh("facade_mesh")
    pcd = read_points(layout.import_coarse_points)
    init = InitGeometry(np.asarray(pcd.points), np.asarray(pcd.colors), vertices, triangles)
    train_idx, test_idx = split_views(len(views), test_every)
    return TrainData(tuple(views), train_idx, test_idx, init)


def paper_mlp(base: TrainParams) -> TrainParams:
    """``base`` with the paper's reflection model and training as published: its 8 x 512 network without
    the environment proxy, reflection gradients into the normals, one initial reflectivity for every splat,
    the high-frequency loss from the start (weight 1 -> 10), one exposure for all photos, the imported poses
    kept, 2DGS's low-pass filter; the MLP pixel cap of the old CPU budget."""
    return replace_keys(
        base,
        {
            "reflection.model": "mlp",
            "reflection.proxy.channels": 0,
            "reflection.mlp.depth": 8,
            "reflection.mlp.width": 512,
            "mlp_max_pixels": 2048 if base.patch_px else base.mlp_max_pixels,
            "reflection_normal_grad": True,
            "init_reflectivity_glass": base.init_reflectivity,
            "lambda_hf_start": 1.0,
            "lambda_hf_end": 10.0,
            "exposure_estimate": False,
            "pose_refinement": False,
            "lowpass_sigma_px": LOWPASS_SIGMA_PX,
        },
    )


def variants(base: TrainParams) -> list[tuple[str, TrainParams]]:
    return [
        ("mlp", base),
        ("sh", replace_keys(base, {"reflection.model": "sh"})),
        ("envmap", replace_keys(base, {"reflection.model": "envmap"})),
        ("mlp, no normal prior", dataclasses.replace(base, lambda_normal_prior=0.0)),
        ("mlp, as the paper", paper_mlp(base)),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-root", default="/tmp/bench_train")
    ap.add_argument("--building", default="demo")
    ap.add_argument("--iterations", type=int, default=0, help="0: the building's [train_gs] budget")
    ap.add_argument("--patch-px", type=int, default=-1, help="-1: the building's (0: whole images)")
    ap.add_argument("--mlp-width", type=int, default=0, help="0: the building's")
    ap.add_argument("--mlp-depth", type=int, default=0, help="0: the building's")
    ap.add_argument("--mlp-max-pixels", type=int, default=-1, help="-1: the building's (0: all)")
    ap.add_argument("--init-points", type=int, default=0, help="0: the building's")
    ap.add_argument("--max-gaussians", type=int, default=0, help="0: the building's")
    ap.add_argument("--supersample", type=int, default=0, help="samples per pixel side; 0: the building's")
    ap.add_argument("--lowpass-sigma-px", type=float, default=0.0, help="0: the building's")
    ap.add_argument(
        "--train-views",
        default="",
        help="comma-separated indices of the views to train on, among the split's training views "
        "(default: all of them): how well fewer views are fitted",
    )
    ap.add_argument("--only", default="", help="comma-separated variant names to run (default: all)")
    ap.add_argument("--speed", type=int, default=0, help="time this many iterations per variant (0: train)")
    ap.add_argument("--warmup", type=int, default=20, help="iterations before --speed's timing")
    ap.add_argument(
        "--profile",
        type=int,
        default=0,
        help="with --speed: this many more iterations under torch's profiler, its operators by self time "
        "printed",
    )
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--align-steps", type=int, default=-1, help="-1: the building's [evaluate.align] steps")
    ap.add_argument(
        "--lpips",
        action="store_true",
        help="also LPIPS of the held-out views (the first of [evaluate] lpips_conventions, its weights found "
        "as the evaluate stage finds them)",
    )
    ap.add_argument(
        "--save-variants",
        action="store_true",
        help="keep each trained variant under <building>/variants/<name>/: `evaluate` then measures it "
        "beside 07_train (LPIPS, frames, renders)",
    )
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument(
        "--log-every",
        type=int,
        default=0,
        help="check the training views' whole-view PSNR every this many iterations, as train_gs does with "
        "[run] log_every (a divergence it finds stops the variant, measured where it stopped); its "
        "history goes into the result line (0: no checks)",
    )
    ap.add_argument(
        "--compile",
        action="store_true",
        help="train with [run] compile on (torch.compile of a step's shading, losses and densification "
        "statistics) whatever the building's [run] says",
    )
    ap.add_argument(
        "--fp32-mlp",
        action="store_true",
        help="the reflection MLP's matrix products in float32 on CUDA too (the reference of their bfloat16 "
        "there: shading.reflection.CUDA_MATMUL_DTYPE)",
    )
    ap.add_argument("--save-bundle", default="", help="write the training data to this .npz and stop")
    ap.add_argument("--bundle", default="", help="train on this .npz (from --save-bundle) instead")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a [train_gs] key set for every variant, dotted for a nested table (lr.reflection_init=1e-3), "
        "the value read as TOML; repeatable",
    )
    a = ap.parse_args()
    cfg = load_building_config(a.building)
    base = cfg.section("train_gs", TrainParams)
    align = cfg.section("evaluate.align", AlignParams)
    if a.align_steps >= 0:
        align = dataclasses.replace(align, steps=a.align_steps)
    lpips = LpipsSetting(())
    if a.lpips:
        lp = cfg.section("evaluate", EvaluateParams).lpips
        lpips = LpipsSetting(lp.conventions[:1], lp.weights_dir)
    mlp = base.reflection.mlp
    base = replace_keys(
        base,
        {
            "iterations": a.iterations or base.iterations,
            "patch_px": base.patch_px if a.patch_px < 0 else a.patch_px,
            "mlp_max_pixels": base.mlp_max_pixels if a.mlp_max_pixels < 0 else a.mlp_max_pixels,
            "init_max_points": a.init_points or base.init_max_points,
            "init_mesh_samples": a.init_points or base.init_mesh_samples,
            "reflection.mlp.width": a.mlp_width or mlp.width,
            "reflection.mlp.depth": a.mlp_depth or mlp.depth,
            "supersample": a.supersample or base.supersample,
            "densify.max_gaussians": a.max_gaussians or base.densify.max_gaussians,
            "lowpass_sigma_px": a.lowpass_sigma_px or base.lowpass_sigma_px,
        },
    )
    if a.set:
        import tomllib

        pairs = (x.split("=", 1) for x in a.set)
        base = replace_keys(base, {k: tomllib.loads(f"v = {v}")["v"] for k, v in pairs})
    data, prior = building_data(a, base)
    if a.train_views:
        chosen = tuple(int(i) for i in a.train_views.split(","))
        if not set(chosen) <= set(data.train_idx):
            sys.exit(f"--train-views: indices among the training views {data.train_idx}, got {chosen}")
        data = dataclasses.replace(data, train_idx=chosen)
    if a.save_bundle:
        save_bundle(data, a.save_bundle)
        Path(a.save_bundle).with_suffix(".prior.txt").write_text(prior)
        print(f"wrote {a.save_bundle} ({len(data.views)} views; prior: {prior})")
        return
    device = resolve_device(a.device)
    compile = a.compile or cfg.run.compile
    if a.speed > 0:
        speed(a, base, data, cfg.run.raster_backend, device, compile)
        return
    rows = []
    for name, p in variants(base):
        if a.only and name not in a.only.split(","):
            continue
        t0 = time.perf_counter()
        # per variant: the paper's has 2DGS's low-pass sigma whatever the building's
        raster = training_rasterizer(cfg.run.raster_backend, p.lowpass_sigma_px, device)
        tr = build_trainer(p, data, raster, device, compile)
        mlp_dtype(tr, a)
        stopped = None
        try:
            train(tr, progress=lambda it, total, out, n=name: print(f"\r{n}: {it}/{total}", end=""),
                  log_every=a.log_every)  # fmt: skip
        except TrainingDivergedError as e:  # measured where it stopped, as train_gs keeps its last state
            stopped = str(e)
            print(f"\n{name}: stopped: {stopped}", flush=True)
        wall = time.perf_counter() - t0
        if a.save_variants:
            save_variant(a, name, tr)
        fit = whole_view_psnr(tr, data.train_idx)
        ev, ev_aligned = measure(tr, name, data, align, lpips)
        rows.append((name, ev, ev_aligned, wall, tr.state.model.n, fit))
        print(
            f"\n{name}: training views {fit:.2f} dB, glass PSNR {ev['psnr_glass']:.2f} dB, "
            f"facade PSNR {ev['psnr']:.2f} dB, "
            f"normal error {ev['normal_error_glass_deg']:.2f} deg, {wall:.0f} s"
            + ("" if ev_aligned is None else f"; aligned: glass PSNR {ev_aligned['psnr_glass']:.2f} dB"),
            flush=True,
        )
        # one line a script reads (benchmarks/gpu_summary.py): every figure of the variant
        checks = [[r["iteration"], r["n_gaussians"], r.get("view_psnr")] for r in tr.state.log]
        figures = {"variant": name, "iterations": p.iterations, "compiled": compile, "wall_s": round(wall, 2),
                   "iterations_run": tr.state.iteration, "stopped": stopped, "checks": checks,
                   "splats": tr.state.model.n, "training_views_psnr": round(fit, 4), "imported": ev,
                   "aligned": ev_aligned}  # fmt: skip
        print("result: " + json.dumps(figures), flush=True)
    report(a, base, align, prior, data, rows, device)


def mlp_dtype(tr, a) -> None:
    """``--fp32-mlp``: the trainer's reflection MLP computes in float32 on CUDA too."""
    if a.fp32_mlp and hasattr(tr.state.reflection, "cuda_matmul_dtype"):
        tr.state.reflection.cuda_matmul_dtype = None


def speed(a, base: TrainParams, data: TrainData, backend: str, device, compile: bool) -> None:
    """ms per iteration and the device's peak memory of each variant (``--speed``), and how many graphs
    ``torch.compile`` made while it was timed (compiled: a first run through the same iterations compiles
    every specialisation the timed one meets, the normal terms' start among them, so that the figure is a
    step's and not the compiler's)."""
    import torch
    from torch._dynamo.utils import counters

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    rows = []
    for name, p in variants(base):
        if a.only and name not in a.only.split(","):
            continue
        p = dataclasses.replace(p, iterations=a.warmup + a.speed + a.profile)
        raster = training_rasterizer(backend, p.lowpass_sigma_px, device)
        if compile:
            first = build_trainer(p, data, raster, device, compile)
            mlp_dtype(first, a)
            train(first, stop_at=a.warmup + a.speed)
            del first
        tr = build_trainer(p, data, raster, device, compile)
        mlp_dtype(tr, a)
        train(tr, stop_at=a.warmup)
        sync()
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        graphs = counters["stats"]["unique_graphs"]
        t0 = time.perf_counter()
        train(tr, stop_at=a.warmup + a.speed)
        sync()
        ms = 1000.0 * (time.perf_counter() - t0) / a.speed
        graphs = counters["stats"]["unique_graphs"] - graphs
        if a.profile > 0:
            profile(tr, name, device, sync)
        mem = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else float("nan")
        rows.append((name, ms, mem, tr.state.model.n))
        print(f"{name}: {ms:.1f} ms per iteration, peak {mem:.2f} GiB, {tr.state.model.n} splats, "
              f"{graphs} graphs compiled while timed", flush=True)  # fmt: skip
    where = machine()
    if device.type == "cuda":
        where += f" GPU: {torch.cuda.get_device_name(device)} (torch {torch.__version__})."
    v = data.views[0].camera
    lines = [
        "\n## train_gs speed\n",
        f"{where}\n",
        f"Building `{a.building}` ({v.width} x {v.height} px), {a.speed} iterations after {a.warmup}, "
        f"{base.patch_px or 'whole-image'} px windows, low-pass sigma {base.lowpass_sigma_px} px, "
        f"{base.supersample} x {base.supersample} samples per pixel, at most {base.densify.max_gaussians} "
        "splats"
        + ("; compiled (`--compile`)" if compile else "")
        + ("; the reflection MLP in float32 (`--fp32-mlp`)" if a.fp32_mlp else "")
        + (f"; set with `--set`: {', '.join(f'`{x}`' for x in a.set)}" if a.set else "")
        + ".\n",
        "| variant | ms per iteration | peak device memory GiB | splats |",
        "| --- | --- | --- | --- |",
        *(f"| {n} | {ms:.1f} | {mem:.2f} | {k} |" for n, ms, mem, k in rows),
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if not a.no_write:
        record_results(text)


def profile(tr, name: str, device, sync) -> None:
    """The rest of ``tr``'s iterations under torch's profiler: where a step's time goes, by operator."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with torch_profile(activities=activities) as prof:
        train(tr)
        sync()
    averages = prof.key_averages()
    keys = ["self_cpu_time_total"]
    if device.type == "cuda":
        keys.insert(0, "self_cuda_time_total")
    for key in keys:
        table = averages.table(sort_by=key, row_limit=25, max_name_column_width=60)
        print(f"\n{name}: operators by {key}\n{table}", flush=True)


def save_variant(a, name: str, tr) -> None:
    """``tr``'s model saved as the variant ``name`` of the building, as train_gs saves 07_train."""
    from facade_pipeline.config import to_dict
    from facade_pipeline.training.batches import exposure_gains
    from facade_pipeline.training.trained import TrainedModelFiles

    data = tr.data
    split: dict = {k: [data.views[i].stem for i in idx] for k, idx in (("train", data.train_idx),
                                                                      ("test", data.test_idx))}  # fmt: skip
    gains = exposure_gains(tr.gains, tr.data)
    if gains:
        split["exposure_gain"] = gains
    folder = "".join(c if c.isalnum() else "_" for c in name)
    layout = BuildingLayout(Path(a.data_root), a.building)
    files = TrainedModelFiles.variant(layout.path("variant_dir", variant=folder), to_dict(tr.params), name)
    strategy = tr.params.reflection_strategy(data.bounds)
    files.save(tr.state.model, tr.state.reflection, strategy, data.bounds, split)


def measure(
    tr, name: str, data: TrainData, align: AlignParams, lpips: LpipsSetting
) -> tuple[dict, dict | None]:
    """The held-out views' headline figures as imported and, when ``align`` has steps, aligned (the
    evaluation core, as train_gs and the evaluate stage measure them), with the facade's LPIPS under
    ``lpips``'s convention when it names one."""
    tm = from_trainer(tr, name)
    views = views_of(data, data.test_idx, tr.params.mask_by_facade)

    def figures(result: dict) -> dict:
        out = headline(result)
        if lpips.conventions:
            out["lpips"] = ((result["mean"].get("facade") or {}).get("lpips") or {}).get(lpips.conventions[0])
        return out

    ev = figures(evaluate_views(tm, views, lpips))
    aligned = figures(evaluate_views(tm, views, lpips, align)) if align.steps > 0 else None
    return ev, aligned


def building_data(a, base: TrainParams) -> tuple[TrainData, str]:
    """The training data (from ``--bundle``, else the building's files) and where its prior comes from."""
    if a.bundle:
        prior_file = Path(a.bundle).with_suffix(".prior.txt")
        prior = prior_file.read_text() if prior_file.is_file() else "unknown"
        return load_bundle(a.bundle), f"{prior}, from the bundle {Path(a.bundle).name}"
    layout = BuildingLayout(Path(a.data_root), a.building)
    ensure_building(layout)
    if layout.manifest("bake_normals").is_file():
        from stages.train_gs import load_train_data

        return load_train_data(layout, base), "baked (06_bake_normals)"
    data = gt_data(layout, base.test_every)
    if base.exposure_estimate:
        from facade_pipeline.training.exposure import with_exposure_estimate

        data = with_exposure_estimate(data, base.seed)
    return data, "ground truth (gt/; bake_normals not run)"


def report(a, p: TrainParams, align: AlignParams, prior: str, data: TrainData, rows, device) -> None:
    where = machine()
    if device.type == "cuda":
        import torch

        where += f" GPU: {torch.cuda.get_device_name(device)} (torch {torch.__version__}), training on it."
    mlp, proxy = p.reflection.mlp, p.reflection.proxy
    lines = [
        "\n## train_gs accuracy\n",
        f"{where}\n",
        f"Building `{a.building}`: {len(data.train_idx)} training and {len(data.test_idx)} held-out views "
        f"({data.views[0].camera.width} x {data.views[0].camera.height} px); prior and masks: {prior}.",
        f"{'GPU' if device.type == 'cuda' else 'CPU'} budget per variant: {p.iterations} iterations on "
        f"{p.patch_px or 'whole-image'} px patches, at most "
        f"{p.mlp_max_pixels or 'all'} MLP pixels per step, {p.init_max_points} + {p.init_mesh_samples} "
        f"initial splats (cap {p.densify.max_gaussians}), reflection MLP {mlp.depth} x {mlp.width}, "
        f"L = {mlp.fourier_levels}, skip {mlp.skip}, environment proxy {proxy.channels} channels at "
        f"{proxy.resolution_px} px (rate {p.lr.proxy}; the surroundings' surface model in cells of "
        f"{proxy.cell:.4f} of the facade's size), "
        f"initial reflectivity {p.init_reflectivity} "
        f"({p.init_reflectivity_glass} on glass), reflection gradient into normals "
        f"{p.reflection_normal_grad}, pose refinement {p.pose_refinement}, exposure gains estimated "
        f"{p.exposure_estimate}, high-frequency weight "
        f"{p.lambda_hf_start} -> {p.lambda_hf_end}, {p.supersample} x {p.supersample} samples per pixel, "
        f"low-pass sigma {p.lowpass_sigma_px} px. "
        + (f"Set with `--set` for every variant: {', '.join(f'`{x}`' for x in a.set)}. " if a.set else "")
        + "`mlp, as the paper` changes these to the paper's (`paper_mlp` in this file). The paper trains "
        "2 x 10^5 iterations on an A40: these are short runs. Wall time: training alone.\n",
    ]
    aligned = [r for r in rows if r[2] is not None]
    if aligned:
        lines.append(
            f"Aligned: each held-out view's pose and exposure{'' if align.exposure else ' (not)'} fitted to "
            f"the frozen model first ({align.steps} Adam steps on its whole image, rates "
            f"{align.lr_rotation} rad, {align.lr_translation} m, {align.lr_exposure}; `[evaluate.align]`, as "
            "the evaluate stage does it), then measured. The first two columns are as imported.\n"
        )
    lines += [
        "| variant | glass PSNR dB (test) | glass interior PSNR dB | glass PSNR dB, aligned | "
        "glass interior, aligned | facade PSNR dB (test) | facade, aligned | SSIM | normal error on glass "
        "deg | training views, whole-view PSNR dB | splats | wall s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, ev, ev_a, wall, n, fit in rows:
        al = ev_a or {}
        lines.append(
            f"| {name} | {ev['psnr_glass']:.2f} | {ev['psnr_glass_interior']:.2f} | "
            f"{_fmt(al.get('psnr_glass'))} | {_fmt(al.get('psnr_glass_interior'))} | {ev['psnr']:.2f} | "
            f"{_fmt(al.get('psnr'))} | {ev['ssim']:.3f} | {ev['normal_error_glass_deg']:.2f} | {fit:.2f} | "
            f"{n} | {wall:.0f} |"
        )
    by = {name: (ev, ev_a) for name, ev, ev_a, *_ in rows}
    # the accuracy targets: mlp's lead (dB) on aligned held-out glass
    targets = [(n, t) for n, t in (("sh", 5.0), ("envmap", 2.0)) if n in by]
    if "mlp" in by and targets:
        for k, label in ((0, "As imported"), (1, "Aligned")):
            if any(by[n][k] is None for n in ("mlp", *(n for n, _ in targets))):
                continue
            gaps = {n: by["mlp"][k]["psnr_glass"] - by[n][k]["psnr_glass"] for n, _ in targets}
            said = "; ".join(f"mlp - {n} on glass {gaps[n]:+.2f} dB (target >= +{t:g})" for n, t in targets)
            met = all(gaps[n] >= t for n, t in targets)
            lines.append(f"\n{label}: {said}: {'met' if met else 'NOT met'}.")
        lines.append(
            f"\nGlass interior: the glass pixels at least {INTERIOR_MARGIN_PX} px from the mask's edge "
            "(frame edges left out), beside the target's figure for where the error sits."
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if not a.no_write:
        record_results(text)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


if __name__ == "__main__":
    main()
