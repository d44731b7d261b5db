"""The evaluation report: Markdown and a self-contained HTML page built from ``metrics.json`` (the dict the
evaluate stage writes) and the comparison images it names.

Tables follow the paper: Table 1 puts the trained variants side by side (PSNR, SSIM, LPIPS over the facade
mask of the held-out views, plus glass, its interior and frames separately); Table 3 compares reflection-MLP
architectures and appears only when two or more MLP variants of different architecture were evaluated.
LPIPS prints as "unavailable" when there were no weights, never as a number. Plots are inline SVG written
here (no plotting dependency); images are embedded in the HTML as base64 PNG.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from facade_pipeline.evaluation.image_eval import INTERIOR_MARGIN_PX
from facade_pipeline.evaluation.lpips import CONVENTIONS

#: the reflection MLP's architecture (Table 3 varies these)
ARCHITECTURE_KEYS = (
    "fourier_levels",
    "mlp_depth",
    "mlp_width",
    "mlp_skip",
    "mlp_proxy_channels",
    "mlp_proxy_surroundings",
    "mlp_self_hits",
)
_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")


# ------------------------------------------------------------------------------------------ formatting


def fmt(x: Any, digits: int) -> str:
    """A table cell: numbers with ``digits`` decimals, None as a dash, strings as they are."""
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    return f"{x:.{digits}f}"


def primary_convention(metrics: dict[str, Any]) -> str:
    """The LPIPS convention the tables show: the first configured one."""
    return metrics["lpips"]["conventions"][0]


def architecture_label(arch: dict[str, Any]) -> str:
    """Table 3's wording: "L = 12, 8 layers, 512 hidden dim, w/ skip connection", and the environment
    proxy (the room or the surroundings) and the self hits when there are (a model saved before they
    existed has neither)."""
    skip = "w/" if arch["mlp_skip"] else "w/o"
    proxy = int(arch.get("mlp_proxy_channels") or 0)
    surroundings = ", surroundings" if arch.get("mlp_proxy_surroundings") else ""
    return (
        f"L = {arch['fourier_levels']}, {arch['mlp_depth']} layers, {arch['mlp_width']} hidden dim, "
        f"{skip} skip connection"
        + (f", environment proxy ({proxy} channels{surroundings})" if proxy else "")
        + (", facade self hits" if arch.get("mlp_self_hits") else "")
    )


def _region(variant: dict[str, Any], split: str, region: str) -> dict[str, Any]:
    return ((variant.get(split) or {}).get("mean") or {}).get(region) or {}


def table1_rows(metrics: dict[str, Any], split: str = "test") -> list[list[str]]:
    """Rows of Table 1: variant, model, PSNR, SSIM, LPIPS (facade), PSNR and SSIM on glass, PSNR on the
    glass interior, PSNR and SSIM on frames, PSNR on the facade's unclipped pixels."""
    conv = primary_convention(metrics)
    rows = []
    for name, v in metrics["variants"].items():
        f, g, gi, fr, un = (
            _region(v, split, r) for r in ("facade", "glass", "glass_interior", "frames", "unclipped")
        )
        rows.append(
            [
                name,
                v["reflection_model"],
                fmt(f.get("psnr"), 2),
                fmt(f.get("ssim"), 4),
                fmt((f.get("lpips") or {}).get(conv), 4),
                fmt(g.get("psnr"), 2),
                fmt(g.get("ssim"), 4),
                fmt(gi.get("psnr"), 2),
                fmt(fr.get("psnr"), 2),
                fmt(fr.get("ssim"), 4),
                fmt(un.get("psnr"), 2),
            ]
        )
    return rows


TABLE1_HEADER = [
    "Variant",
    "Reflection",
    "PSNR↑",
    "SSIM↑",
    "LPIPS↓",
    "PSNR glass↑",
    "SSIM glass↑",
    "PSNR glass interior↑",
    "PSNR frames↑",
    "SSIM frames↑",
    "PSNR unclipped↑",
]


def ablation_variants(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """The MLP variants of the largest ablation: same ``ablation_group`` (every training parameter but the
    architecture equal), one per architecture (the first found), sorted by architecture; [] when no group
    holds two architectures (no ablation was run)."""
    groups: dict[str, dict[str, dict[str, Any]]] = {}
    for v in metrics["variants"].values():
        if v["reflection_model"] == "mlp" and v.get("architecture"):
            arch = architecture_label(v["architecture"])
            groups.setdefault(v.get("ablation_group", ""), {}).setdefault(arch, v)
    best = max(groups.values(), key=len, default={})
    return [best[a] for a in sorted(best)] if len(best) >= 2 else []


def table3_rows(metrics: dict[str, Any]) -> list[list[str]]:
    """Rows of Table 3 (case, architecture, PSNR, SSIM, LPIPS) of ``ablation_variants``, or []."""
    conv = primary_convention(metrics)
    rows = []
    for case, v in enumerate(ablation_variants(metrics), 1):
        f = _region(v, "test", "facade")
        rows.append(
            [
                str(case),
                architecture_label(v["architecture"]),
                fmt(f.get("psnr"), 2),
                fmt(f.get("ssim"), 4),
                fmt((f.get("lpips") or {}).get(conv), 4),
            ]
        )
    return rows


TABLE3_HEADER = ["Case", "Architecture", "PSNR↑", "SSIM↑", "LPIPS↓"]

GEOMETRY_KEYS = [
    ("glass_distance_mean_m", "glass dist. mean (cm)", 100.0),
    ("glass_distance_p95_m", "glass dist. p95 (cm)", 100.0),
    ("frame_distance_mean_m", "frame dist. mean (cm)", 100.0),
    ("glass_normal_error_mean_deg", "glass normal err. mean (deg)", 1.0),
    ("glass_normal_error_p95_deg", "glass normal err. p95 (deg)", 1.0),
]


GEOMETRY_HEADER = ["Surface"] + [h for _, h, _ in GEOMETRY_KEYS] + ["measured"]


def geometry_rows(metrics: dict[str, Any]) -> list[list[str]]:
    """One row per surface (coarse mesh, corrected mesh, each variant's Gaussians) against gt/."""
    geo = metrics.get("geometry")
    if not geo:
        return []
    surfaces = [("coarse mesh", geo.get("coarse_mesh")), ("corrected mesh", geo.get("corrected_mesh"))]
    surfaces += [(f"Gaussians: {n}", v.get("geometry")) for n, v in metrics["variants"].items()]
    rows = []
    for label, g in surfaces:
        if g:
            measured = (
                f"{g['gaussians_measured']} of {g['gaussians']} splats"
                if "gaussians" in g
                else f"{g.get('samples_unmatched', 0)} samples unmatched"
            )
            rows.append(
                [label]
                + [fmt(None if g.get(k) is None else g[k] * s, 2) for k, _, s in GEOMETRY_KEYS]
                + [measured]
            )
    return rows


# ------------------------------------------------------------------------------------------ markdown


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def _lpips_lines(metrics: dict[str, Any]) -> list[str]:
    out = []
    for conv in metrics["lpips"]["conventions"]:
        status = metrics["lpips"]["status"][conv]
        out.append(f"- `{conv}`: {CONVENTIONS[conv].label}: {status}")
    return out


def _corner_line(metrics: dict[str, Any]) -> str | None:
    c = (metrics.get("geometry") or {}).get("panel_corners")
    if not c:
        return None
    return (
        f"Panel corners ({c['panels']} panels found, {c['true_panels']} true): mean "
        f"{fmt(c['corner_error_mean_m'], 3)} m, max {fmt(c['corner_error_max_m'], 3)} m; in the UAV views "
        f"mean {fmt(c['corner_error_mean_px'], 2)} px, max {fmt(c['corner_error_max_px'], 2)} px."
    )


ALIGNED_NOTE = (
    "aligned to the model: each view's pose and exposure fitted to the frozen model before it is measured "
    "(the table above measures them as imported)"
)


def _more_tables(metrics: dict[str, Any]) -> list[tuple[str, str]]:
    """(split key, title) of the Table 1 variants present beside the held-out views as imported."""
    titles = {
        "test_aligned": f"Held-out views, {ALIGNED_NOTE}",
        "train": "Training views",
        "train_aligned": f"Training views, {ALIGNED_NOTE}",
    }
    return [(k, t) for k, t in titles.items() if any(v.get(k) for v in metrics["variants"].values())]


def build_markdown(metrics: dict[str, Any], images: Sequence[tuple[str, str]] = ()) -> str:
    """The report as Markdown; ``images`` are (caption, path relative to the report) pairs."""
    conv = primary_convention(metrics)
    md = [
        f"# Evaluation: {metrics['building']}",
        "",
        f"Held-out views: every {metrics['test_every']}-th view. Metrics over the facade mask "
        "(baked from the corrected mesh); glass, its interior (glass pixels at least "
        f"{INTERIOR_MARGIN_PX} px from the glass edge: frame edges left out) and frames (facade minus glass) "
        "separately. SSIM: 11x11 Gaussian window, sigma 1.5, statistics renormalised over the mask. PSNR in "
        "dB, averaged over views.",
        "",
        *[f"**Note: {n}.**\n" for n in metrics.get("notes", [])],
        "LPIPS conventions (the tables show the first):",
        *_lpips_lines(metrics),
        "",
        "## Table 1: variants side by side (held-out views)",
        "",
        markdown_table(TABLE1_HEADER, table1_rows(metrics)),
        "",
        f"LPIPS column: `{conv}`.",
    ]
    for split, title in _more_tables(metrics):
        md += ["", f"### {title}", "", markdown_table(TABLE1_HEADER, table1_rows(metrics, split))]
    t3 = table3_rows(metrics)
    if t3:
        md += ["", "## Table 3: reflection MLP architectures", "", markdown_table(TABLE3_HEADER, t3)]
    geo = geometry_rows(metrics)
    if geo:
        md += [
            "",
            "## Geometry against the truth (synthetic building)",
            "",
            markdown_table(GEOMETRY_HEADER, geo),
        ]
        line = _corner_line(metrics)
        md += ["", line] if line else []
    video = metrics.get("video")
    if video:
        md += ["", "## Fly-through", "", f"![fly-through]({video['clip']})", "", _video_line(video)]
    if images:
        md += [
            "",
            "## Renders",
            "",
            "Ground truth | render | absolute error (black 0, yellow >= "
            f"{metrics['heatmap_max_error']}; grey outside the facade mask)",
            "",
        ]
        md += [f"![{c}]({p})  \n{c}" for c, p in images]
    return "\n".join(md) + "\n"


# ------------------------------------------------------------------------------------------ SVG plots


def svg_bar_chart(
    groups: Sequence[str],
    series: dict[str, Sequence[float | None]],
    title: str,
    y_label: str,
    width: int = 640,
    height: int = 300,
) -> str:
    """Grouped bars: one group per entry of ``groups``, one bar per series (None: no bar). Inline SVG."""
    vals = [v for s in series.values() for v in s if v is not None]
    top = max(vals) * 1.1 if vals and max(vals) > 0 else 1.0
    ml, mb, mt = 50, 40, 30
    pw, ph = width - ml - 10, height - mb - mt
    gw = pw / max(len(groups), 1)
    bw = gw * 0.8 / max(len(series), 1)
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-size="11">',
        f'<text x="{width / 2}" y="16" text-anchor="middle" font-size="13">{html.escape(title)}</text>',
        f'<line x1="{ml}" y1="{mt + ph}" x2="{ml + pw}" y2="{mt + ph}" stroke="black"/>',
        f'<line x1="{ml}" y1="{mt}" x2="{ml}" y2="{mt + ph}" stroke="black"/>',
        f'<text x="12" y="{mt + ph / 2}" transform="rotate(-90 12 {mt + ph / 2})" text-anchor="middle">'
        f"{html.escape(y_label)}</text>",
    ]
    for t in range(5):
        y = mt + ph - ph * t / 4
        out.append(f'<text x="{ml - 4}" y="{y + 4}" text-anchor="end">{top * t / 4:.3g}</text>')
    for gi, g in enumerate(groups):
        out.append(
            f'<text x="{ml + gw * (gi + 0.5)}" y="{mt + ph + 14}" '
            f'text-anchor="middle">{html.escape(g)}</text>'
        )
        for si, (name, s) in enumerate(series.items()):
            v = s[gi]
            if v is None:
                continue
            h = ph * v / top
            x = ml + gw * gi + gw * 0.1 + bw * si
            out.append(
                f'<rect x="{x:.1f}" y="{mt + ph - h:.1f}" width="{bw:.1f}" height="{h:.1f}" '
                f'fill="{_COLOURS[si % len(_COLOURS)]}"><title>{html.escape(name)}: {v:.4g}</title></rect>'
            )
    for si, name in enumerate(series):
        x = ml + 10 + 110 * si
        out.append(
            f'<rect x="{x}" y="{height - 14}" width="10" height="10" fill="{_COLOURS[si % len(_COLOURS)]}"/>'
            f'<text x="{x + 14}" y="{height - 5}">{html.escape(name)}</text>'
        )
    return "\n".join(out + ["</svg>"])


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points (time, accuracy) that no other point beats: none both faster-or-equal and
    more-or-equally accurate with one strictly better. Sorted by time."""
    idx = []
    for i, (t, a) in enumerate(points):
        if not any(
            (t2 <= t and a2 >= a) and (t2 < t or a2 > a) for j, (t2, a2) in enumerate(points) if j != i
        ):
            idx.append(i)
    return sorted(idx, key=lambda i: points[i][0])


def svg_scatter(
    points: Sequence[tuple[float, float]],
    labels: Sequence[str],
    title: str,
    x_label: str,
    y_label: str,
    front: Sequence[int] = (),
    width: int = 640,
    height: int = 360,
) -> str:
    """Scatter plot of (x, y) points with hover labels; ``front`` indices are joined by a line (Pareto)."""
    xs, ys = [p[0] for p in points], [p[1] for p in points]
    x0, x1 = (min(xs), max(xs)) if xs else (0.0, 1.0)
    y0, y1 = (min(ys), max(ys)) if ys else (0.0, 1.0)
    x1, y1 = (x1 if x1 > x0 else x0 + 1), (y1 if y1 > y0 else y0 + 1)
    ml, mb, mt, mr = 60, 40, 30, 20
    pw, ph = width - ml - mr, height - mb - mt

    def sx(x: float) -> float:
        return ml + pw * (x - x0) / (x1 - x0)

    def sy(y: float) -> float:
        return mt + ph - ph * (y - y0) / (y1 - y0)

    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-size="11">',
        f'<text x="{width / 2}" y="16" text-anchor="middle" font-size="13">{html.escape(title)}</text>',
        f'<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" fill="none" stroke="black"/>',
        f'<text x="{ml + pw / 2}" y="{height - 6}" text-anchor="middle">{html.escape(x_label)}</text>',
        f'<text x="14" y="{mt + ph / 2}" transform="rotate(-90 14 {mt + ph / 2})" text-anchor="middle">'
        f"{html.escape(y_label)}</text>",
    ]
    for t in range(5):
        xv, yv = x0 + (x1 - x0) * t / 4, y0 + (y1 - y0) * t / 4
        out.append(f'<text x="{sx(xv):.1f}" y="{mt + ph + 14}" text-anchor="middle">{xv:.3g}</text>')
        out.append(f'<text x="{ml - 4}" y="{sy(yv) + 4:.1f}" text-anchor="end">{yv:.3g}</text>')
    if len(front) > 1:
        path = " ".join(f"{sx(points[i][0]):.1f},{sy(points[i][1]):.1f}" for i in front)
        out.append(f'<polyline points="{path}" fill="none" stroke="#d62728" stroke-width="1.5"/>')
    for i, ((x, y), lab) in enumerate(zip(points, labels, strict=True)):
        colour = "#d62728" if i in front else "#1f77b4"
        out.append(
            f'<circle cx="{sx(x):.1f}" cy="{sy(y):.1f}" r="4" fill="{colour}">'
            f"<title>{html.escape(lab)}: {x:.4g}, {y:.4g}</title></circle>"
        )
    return "\n".join(out + ["</svg>"])


# ------------------------------------------------------------------------------------------ HTML


def _html_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


def embed_png(path: str | Path) -> str:
    """A ``data:`` URI of a PNG file (the page then needs nothing beside it)."""
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def psnr_chart(metrics: dict[str, Any]) -> str:
    """Bars of held-out PSNR per variant on the facade, glass and frames."""
    names = list(metrics["variants"])
    series = {}
    for region in ("facade", "glass", "frames"):
        vals = [_region(metrics["variants"][n], "test", region).get("psnr") for n in names]
        series[region] = [v if isinstance(v, int | float) else None for v in vals]
    return svg_bar_chart(names, series, "Held-out PSNR per region", "PSNR (dB)")


_CSS = (
    "body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}"
    "table{border-collapse:collapse;margin:.5em 0}"
    "td,th{border:1px solid #999;padding:3px 8px;text-align:right}"
    "td:first-child,th:first-child{text-align:left}figure{display:inline-block;margin:.5em}"
    "figure img{image-rendering:pixelated;min-width:384px}"
)


def _video_line(video: dict[str, Any]) -> str:
    w, h = video["size_px"]
    names = ", ".join(video["variants"])
    path = video.get("path", "orbit")
    route = (
        "an orbit through the training cameras' range"
        if path == "orbit"
        else f"a path through the views {', '.join(path)}"
    )
    return (
        f"[{video['file']}]({video['file']}): {video['frames']} frames of {w} x {h} px at "
        f"{video['fps']} fps, {route}; left to right: {names}."
    )


def build_html(
    metrics: dict[str, Any], images: Sequence[tuple[str, Path]] = (), clip: Path | None = None
) -> str:
    """The report as one self-contained HTML page; ``images`` are (caption, PNG path) pairs, embedded, and
    ``clip`` the fly-through's looping clip (animated WebP), embedded too."""
    e = html.escape
    conv = primary_convention(metrics)
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>Evaluation: {e(metrics['building'])}"
        f"</title><style>{_CSS}</style></head><body>",
        f"<h1>Evaluation: {e(metrics['building'])}</h1>",
        f"<p>Held-out views: every {metrics['test_every']}-th view. Metrics over the facade mask; glass, its "
        f"interior ({INTERIOR_MARGIN_PX} px from the glass edge) and frames separately. SSIM: 11x11 "
        "Gaussian window, sigma 1.5. PSNR in dB, averaged over views.</p>",
        *[f"<p><strong>Note: {e(n)}.</strong></p>" for n in metrics.get("notes", [])],
        "<ul>" + "".join(f"<li>{e(line[2:])}</li>" for line in _lpips_lines(metrics)) + "</ul>",
        "<h2>Table 1: variants side by side (held-out views)</h2>",
        _html_table(TABLE1_HEADER, table1_rows(metrics)),
        f"<p>LPIPS column: {e(conv)}.</p>",
    ]
    for split, title in _more_tables(metrics):
        parts += [f"<h3>{e(title)}</h3>", _html_table(TABLE1_HEADER, table1_rows(metrics, split))]
    t3 = table3_rows(metrics)
    if t3:
        parts += ["<h2>Table 3: reflection MLP architectures</h2>", _html_table(TABLE3_HEADER, t3)]
    parts.append(psnr_chart(metrics))
    geo = geometry_rows(metrics)
    if geo:
        parts += [
            "<h2>Geometry against the truth (synthetic building)</h2>",
            _html_table(GEOMETRY_HEADER, geo),
        ]
        line = _corner_line(metrics)
        parts += [f"<p>{e(line)}</p>"] if line else []
    video = metrics.get("video")
    if video and clip is not None and Path(clip).is_file():
        data = base64.b64encode(Path(clip).read_bytes()).decode("ascii")
        line = e(_video_line(video)).replace(
            e(f"[{video['file']}]({video['file']})"), f"<a href='{e(video['file'])}'>{e(video['file'])}</a>"
        )
        parts += [
            "<h2>Fly-through</h2>",
            f"<figure><img src='data:image/webp;base64,{data}' alt='fly-through'><figcaption>{line}"
            "</figcaption></figure>",
        ]
    if images:
        parts += [
            "<h2>Renders</h2>",
            f"<p>Ground truth | render | absolute error (black 0, yellow &ge; "
            f"{metrics['heatmap_max_error']}; grey outside the facade mask)</p>",
        ]
        parts += [
            f"<figure><img src='{embed_png(p)}' alt='{e(c)}'><figcaption>{e(c)}</figcaption></figure>"
            for c, p in images
        ]
    return "\n".join(parts + ["</body></html>"]) + "\n"
