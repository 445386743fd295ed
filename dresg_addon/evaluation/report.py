"""``dresg report``'s writing: ``report.md``, ``report.json`` and PNG plots from what :mod:`.report_measure` measured.

The plots are drawn with matplotlib, an optional extra (``pip install .[report]``); without it the report is
written without them and says so in one line.

- ``raster_error.png``: (a), the fast rasterizer's max error against the float64 reference vs its forward time;
- ``work_precision.png``: (b), the novel-view metrics of :func:`.views.evaluate_views` against the stylization's
  wall time, for the presets and for stage counts;
- ``convergence.png``: (c), the fit's error at every fit step (the RMSE after each round of a solved colour fit,
  the Eq. 16 loss of an Adam step) and each stage's distance to its own targets before and after its fit;
- (d), the stiff and extreme cases of :mod:`.stability`, as a table.

Every measured value behind the plots goes to ``report.json``; :func:`draw_plots` redraws the PNGs from it.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from ..method.config import DEFAULT_PRESET
from ..util.machine import load_average
from .report_measure import ReportOptions, measure_report

ERROR_FLOOR = 1e-17  # errors of exactly 0 are drawn here on the log axis


# ----------------------------------------------------------------------------------------------------
# (a) Rasterizer error against run time


def plot_raster_error(ax, result: dict) -> None:
    """(a) on ``ax``: per knob, the max rgb error against the forward time, one marker per setting."""
    times = [r["seconds"] for r in result["rows"] if r["seconds"] > 0]
    if times and max(times) > 4 * min(times):
        ax.set_xscale("log")
    ax.set_yscale("log")
    families = {}
    for row in result["rows"]:
        families.setdefault(row["knob"], []).append(row)
    for i, (knob, rows) in enumerate(families.items()):
        _series(  # in the order of the knob's values: a curve along the setting
            ax,
            [r["seconds"] for r in rows],
            [max(r["rgb_error"], ERROR_FLOOR) for r in rows],
            [_knob_value_label(r["value"]) for r in rows],
            label=knob,
            marker=FIGURE_MARKERS[i % len(FIGURE_MARKERS)],
            linestyle="-" if len(rows) > 1 else "none",
        )
    zeros = any(r["rgb_error"] == 0 for r in result["rows"])
    _decorate(
        ax,
        "Rasterizer: error against the float64 reference",
        "forward time of the full image (s)",
        "max |rgb - reference| on the window",
        f"{result['camera']} image, {result['window'][2]}x{result['window'][3]} reference window"
        + (f"; exact zeros drawn at {ERROR_FLOOR:g}" if zeros else ""),
    )


def _knob_value_label(value) -> str:
    """A short label of a knob value: "" for the default, 500k, 8M, 3, float32."""
    if value is None:
        return ""
    if isinstance(value, int) and value >= 1000:
        return f"{value / 1e6:g}M" if value >= 1_000_000 else f"{value / 1e3:g}k"
    return f"{value:g}" if isinstance(value, float) else str(value)


def raster_table(result: dict) -> str:
    lines = [
        "| knob | value | max rgb error | max alpha error | samples | forward (s) |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in result["rows"]:
        value = "-" if r["value"] is None else _knob_value_label(r["value"])
        lines.append(
            f"| {r['knob']} | {value} | {r['rgb_error']:.2e} | {r['alpha_error']:.2e} | {r['pairs']:,} "
            f"| {r['seconds']:.3f} |"
        )
    return "\n".join(lines)


def _fmt(value, digits: int = 4) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


# ----------------------------------------------------------------------------------------------------
# (b) Work-precision and (c) convergence

METRIC_PANELS = (
    ("sw_colors", "Style: sliced Wasserstein, colours", "SW2 to the style", "lower is better"),
    ("sw_patches", "Style: sliced Wasserstein, 7x7 patches", "SW2 to the style", "lower is better"),
    ("ssim", "Content: SSIM to the base render", "SSIM", "higher is better"),
    ("short_rmse", "Consistency: short-term (gap 1)", "masked RMSE of the warped view", "lower is better"),
)


def plot_work_precision(axes, rows: list[dict], base: dict) -> None:
    """(b) on four ``axes``, one per metric of :data:`METRIC_PANELS`: the stage-count curve, the presets
    and the unstylized scene's level, against the stylization's wall time."""
    times = [r["seconds"] for r in rows]
    xlog = bool(times) and max(times) > 20 * max(min(times), 1e-9)
    for ax, (key, title, ylabel, note) in zip(axes, METRIC_PANELS):
        if xlog:
            ax.set_xscale("log")
        presets = [r for r in rows if r["group"] == "preset" and r[key] is not None]
        stages = sorted(
            (r for r in rows if r["group"] == "stages" and r[key] is not None), key=lambda r: r["config"]["stages"]
        )
        if stages:
            _series(
                ax,
                [r["seconds"] for r in stages],
                [r[key] for r in stages],
                [r["label"].replace("stages ", "F=") for r in stages],
                label=f"{DEFAULT_PRESET} at F stages",
                color="C0",
                marker="^",
            )
        if presets:
            _series(
                ax,
                [r["seconds"] for r in presets],
                [r[key] for r in presets],
                [r["label"] for r in presets],
                label="presets",
                color="C3",
                linestyle="none",
                marker="o",
                markersize=8,
            )
        if base.get(key) is not None and math.isfinite(base[key]):
            ax.axhline(base[key], color="0.5", linewidth=1.0, label="unstylized scene")
        _decorate(ax, title, "stylization wall time (s)", ylabel, note)


def work_precision_table(rows: list[dict], base: dict) -> str:
    lines = [
        "| run | stages x updates | fit / post steps | proposal | geometry | active views | time (s) "
        "| SW patch | ½ | ¼ | SW colour | SSIM | GS | texture kept | kept at 2x | shapes | forms | marks fine | mid "
        "| coarse | short RMSE | long RMSE |",
        "|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def metrics(r: dict) -> str:
        return (
            f"| {_fmt(r['sw_patches'])} | {_fmt(r['sw_patches_half'])} | {_fmt(r['sw_patches_quarter'])} "
            f"| {_fmt(r['sw_colors'])} | {_fmt(r['ssim'], 3)} | {_fmt(r['structure'], 3)} "
            f"| {_fmt(r['texture_kept'], 3)} | {_fmt(r.get('texture_kept_2x'), 3)} | {_fmt(r['shapes'], 3)} "
            f"| {_fmt(r.get('forms'), 3)} | {_fmt(r.get('marks_fine'), 2)} | {_fmt(r.get('marks_mid'), 2)} "
            f"| {_fmt(r.get('marks_coarse'), 2)} "
            f"| {_fmt(r['short_rmse'])} "
            f"| {_fmt(r['long_rmse'])} |"
        )

    for r in rows:
        c = r["config"]
        lines.append(
            f"| {r['label']} | {c['stages']} x {c['updates_per_stage']} | {c['fit_steps']} / {c['post_steps']} "
            f"| {c['proposal_width']}x{c['proposal_height']} | {'on' if c['optimize_geometry'] else 'off'} | {r['views']} "
            f"| {r['seconds']:.1f} " + metrics(r)
        )
    lines.append("| unstylized | | | | | | " + metrics(base))
    return "\n".join(lines)


def plot_convergence(axes, steps: list, log: list[dict]) -> None:
    """(c) on two ``axes``: the fit loss per step (``steps``: (seconds, stage, step, loss)) and per stage
    (the stylize ``log``)."""
    steps_ax, stage_ax = axes
    fit = [s for s in steps if s[1] != "post"]
    post = [s for s in steps if s[1] == "post"]
    losses = [s[3] for s in steps if math.isfinite(s[3]) and s[3] > 0]
    if losses and max(losses) > 8 * min(losses):
        steps_ax.set_yscale("log")
        stage_ax.set_yscale("log")
    ends = []
    for i, stage in enumerate(dict.fromkeys(s[1] for s in fit)):
        # One line per stage: the proposal phase between stages has no fit steps to join.
        own = [s for s in fit if s[1] == stage]
        ends.append(own[-1])
        label = "fit steps" if i == 0 else "_nolegend_"
        _series(steps_ax, [s[0] for s in own], [s[3] for s in own], label=label, color="C0")
    _series(
        steps_ax,
        [s[0] for s in ends],
        [s[3] for s in ends],
        [str(s[1]) for s in ends] if len(ends) <= 12 else None,
        label="end of stage",
        color="C1",
        linestyle="none",
        marker="o",
    )
    if post:
        _series(steps_ax, [s[0] for s in post], [s[3] for s in post], label="post stage", color="C2")
    _decorate(
        steps_ax, "Fit error of every fit step", "time since the start of stylize (s)", "RMSE over covered pixels",
        "each stage fits a new target: the error jumps at stage starts",
    )  # fmt: skip
    # Each stage's gap to its own targets before the fit and what the fit left of it (RMSE over covered pixels).
    stages = [e for e in log if e.get("target_gap") is not None]
    seconds = [e["seconds"] for e in stages]
    _series(stage_ax, seconds, [e["target_gap"] for e in stages], label="before the fit", color="C0", marker="s")
    _series(
        stage_ax,
        seconds,
        [e["fit_residual"] for e in stages],
        [str(e["stage"]) for e in stages] if len(stages) <= 12 else None,
        label="after the fit",
        color="C1",
        marker="o",
    )
    _decorate(
        stage_ax, "Distance to each stage's targets", "end of the stage (s)", "RMSE, covered pixels",
        "before the stage's fit (target gap) and after it (fit residual)",
    )  # fmt: skip


def convergence_table(log: list[dict]) -> str:
    lines = [
        "| stage | t | gamma | energy | target gap | fit residual | optimum | closed | stage (s) | elapsed (s) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for e in log:
        t = e.get("t", "")
        gamma = f"{e['gamma']:.3f}" if isinstance(e.get("gamma"), float) else ""
        energy = f"{e['energy']:.4f}" if isinstance(e.get("energy"), float) else ""
        closed = f"{100 * e['gap_closed']:.0f}%" if isinstance(e.get("gap_closed"), float) else ""
        lines.append(
            f"| {e['stage']} | {t} | {gamma} | {energy} | {_fmt(e.get('target_gap'))} | {_fmt(e.get('fit_residual'))} "
            f"| {_fmt(e.get('optimum_residual'))} | {closed} | {e.get('stage_seconds', 0.0):.2f} "
            f"| {e.get('seconds', 0.0):.2f} |"
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------
# Figures: matplotlib, an optional extra (imported only here, drawing on Agg canvases: no pyplot, no global backend)

FIGURES_NEED_MATPLOTLIB = "figures left out: they need matplotlib (pip install .[report])"
FIGURE_DPI = 100  # panel sizes below are in pixels
FIGURE_MARKERS = ("o", "s", "^", "D", "v")


def matplotlib_available() -> bool:
    """Whether the figures can be drawn; without matplotlib the report is written without them."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _series(ax, xs, ys, point_labels=None, **style) -> None:
    """Plot one series on ``ax`` (its scales already set), with each of ``point_labels`` beside its point.

    Points that cannot be drawn are left out: None, NaN or Inf, and values <= 0 on a log axis, so no
    non-finite value reaches an image and the line joins the points on either side.
    """
    xlog, ylog = ax.get_xscale() == "log", ax.get_yscale() == "log"
    labels = point_labels or [""] * len(xs)
    points = [
        (float(x), float(y), text)
        for x, y, text in zip(xs, ys, labels)
        if x is not None
        and y is not None
        and math.isfinite(x)
        and math.isfinite(y)
        and (x > 0 or not xlog)
        and (y > 0 or not ylog)
    ]
    (line,) = ax.plot([p[0] for p in points], [p[1] for p in points], **style)
    for x, y, text in points:
        if text:
            ax.annotate(text, (x, y), xytext=(5, 4), textcoords="offset points", fontsize=8, color=line.get_color())


def _decorate(ax, title: str, xlabel: str, ylabel: str, note: str) -> None:
    """Title with a small grey ``note`` under it, axis labels, grid, and a legend where it hides least."""
    ax.set_title(title, fontsize=11, pad=16)
    ax.annotate(
        note, (0.5, 1.0), xycoords="axes fraction", xytext=(0, 5), textcoords="offset points",
        ha="center", va="bottom", fontsize=8, color="0.35",
    )  # fmt: skip
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, color="0.88")
    ax.set_axisbelow(True)
    # Point labels in the right fifth go left of their point, so that they stay inside the figure.
    ax.get_xlim()  # settles the autoscaled limits that the transform below uses
    data_to_axes = ax.transScale + ax.transLimits
    for label in ax.texts:
        if label.xycoords == "data" and data_to_axes.transform(label.xy)[0] > 0.8:
            label.set_horizontalalignment("right")
            label.xyann = (-5, 4)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)


def _figure(columns: int, rows: int, panel_size: tuple[int, int]):
    """A figure of ``rows`` x ``columns`` panels of ``panel_size`` pixels each, and its axes row by row."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width, height = panel_size
    figure = Figure(figsize=(columns * width / FIGURE_DPI, rows * height / FIGURE_DPI), dpi=FIGURE_DPI)
    figure.set_layout_engine("constrained")
    FigureCanvasAgg(figure)
    return figure, list(figure.subplots(rows, columns, squeeze=False).ravel())


def _save_figure(figure, path: Path) -> None:
    """Render ``figure`` and write it as an 8-bit RGB PNG through :func:`~dresg_addon.util.imageio.write_image`:
    atomic, and a full disk raises WriteError with the old file kept. The figure belongs to no pyplot
    state, so dropping it frees it: there is nothing to close."""
    from ..util.imageio import write_image

    figure.canvas.draw()
    rgba = np.asarray(figure.canvas.buffer_rgba())
    write_image(path, rgba[..., :3].astype(np.float32) / 255.0)


def draw_plots(data: dict, out: Path) -> None:
    """The report's PNGs from its measured data (what ``report.json`` holds), into ``out``; needs matplotlib."""
    out = Path(out)
    figure, axes = _figure(1, 1, (760, 480))
    plot_raster_error(axes[0], data["raster"])
    _save_figure(figure, out / "raster_error.png")
    figure, axes = _figure(2, 2, (560, 400))
    plot_work_precision(axes, data["runs"], data["unstylized"])
    _save_figure(figure, out / "work_precision.png")
    if data.get("convergence"):
        figure, axes = _figure(2, 1, (560, 400))
        plot_convergence(axes, data["convergence"]["steps"], data["convergence"]["log"])
        _save_figure(figure, out / "convergence.png")


# ----------------------------------------------------------------------------------------------------
# The whole report

METRICS_TEXT = (
    "Metrics of `dresg_addon.evaluation.views.evaluate_views` (those of `dresg evaluate` and the quality "
    "benchmark), means over the novel views, on the pixels the base render covers: SW patch, ½, ¼: the "
    "sliced-Wasserstein distance of 7x7 patches to the painting at the cameras' size, half and a quarter (renders "
    "at twice the size area-downsampled by 2, 4 and 8, the painting resampled alike); SW colour: the same on "
    "colours; SSIM and GS (gradient structure) to the unstylized render; texture kept: the correlation of the "
    "luminance high-pass (sigma 2 px) with the unstylized render's, 4 px inside the silhouette (1: the scene's own "
    "fine texture all still there; lower: more of the painting's); kept at 2x: the same on the renders at twice the size, 8 px "
    "inside (detail finer than the fit size, a capture's sub-pixel texture); shapes: SSIM of the luminance blurred by a "
    "Gaussian of sigma 3 px (1: the same forms); forms: SSIM's structure term alone on it (1: the same forms, "
    "whatever the palette's brightness and contrast); marks fine, mid, coarse: mark contrast, the luminance "
    "band-pass (sigma 0.6/1.2, 1.2/2.4, 2.4/4.8 px) of the 2x render area-downsampled to the cameras' size, less "
    "what the unstylized render's same band explains, 4 px inside the silhouette, over the painting's own at the "
    "run's Stroke Size (1: marks as strong as the painting's; about 0: none); short and long RMSE: the stylized view i warped into view i + 1 "
    "and i + N // 2 with rendered depth and the known poses, masked RMSE."
)


def report_markdown(data: dict, figures: bool) -> str:
    """``report.md`` from :func:`~.report_measure.measure_report`'s data; ``figures``: whether the PNGs exist."""
    from .stability import format_markdown

    def figure(caption: str, name: str) -> list[str]:
        """The Markdown of one figure (the caption says what it shows), or nothing when figures are left out."""
        return [f"![{caption}]({name})", ""] if figures else []

    raster = data["raster"]
    x0, y0, wx, wy = raster["window"]
    repeats = raster["repeats"]
    lines = [
        "# DReSG: error against run time, convergence and numerical stability",
        "",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- machine: {data['machine']}",
        f"- mode: {'quick (budgets shrunk: indicative numbers only)' if data['quick'] else 'full'}",
        f"- scene: {data['scene']}; {data['cameras']}",
        f"- styles: {', '.join(data['styles'])}",
        *([] if figures else [f"- {FIGURES_NEED_MATPLOTLIB}"]),
        "",
        "## (a) Rasterizer: error against the float64 reference vs run time",
        "",
        f"The fast rasterizer renders the whole {raster['camera']} image of the scene (camera "
        f"{raster['camera_name']}); the float64 reference renderer renders the {wx}x{wy} pixel window at "
        f"({x0}, {y0}) from the {raster['subset']:,} Gaussians that can reach it "
        f"({raster['reference_seconds']:.1f} s; window coverage {raster['coverage']:.2f}). Error: max absolute "
        f"difference on that window; time: "
        + (f"the fastest of {repeats} forward renders" if repeats > 1 else "one forward render")
        + " of the full image (no gradients), after a warm-up render.",
        "",
        *figure("rasterizer error against time", "raster_error.png"),
        raster_table(raster),
        "",
        "## (b) Stylization work-precision",
        "",
        METRICS_TEXT
        + " Against the stylization's wall time (view selection to the post stage), averaged over the styles. "
        "Presets as defined in `dresg_addon.method.config`"
        + (", shrunk for the quick run (see the table)" if data["quick"] else "")
        + f"; the stage counts F run the default preset ({DEFAULT_PRESET}) with F stages and no early stop.",
        "",
        *figure("metrics against time", "work_precision.png"),
        work_precision_table(data["runs"], data["unstylized"]),
        "",
        "## (c) Convergence",
        "",
    ]
    chosen = data["convergence"]
    if chosen is not None:
        lines += [
            f'How far the fit of run "{chosen["label"]}" on {chosen["style"]} got: its error after every fit step '
            "(colour-only runs solve each fit as bounded least squares: the RMSE over all pixels after each "
            "round; Adam runs: the Eq. 16 loss), and per stage the RMSE over covered pixels between the "
            "stage's targets and the renders before its fit (target gap) and after it (fit residual), "
            "with the joint least-squares optimum of those targets and the share of the gap closed, against "
            "the time since the start of stylize (from its log and progress reports).",
            "",
            *figure("fit error against time", "convergence.png"),
            convergence_table(chosen["log"]),
            "",
        ]
    else:
        lines += ["No stylization run was requested.", ""]
    lines += ["## (d) Numerical stability", ""]
    if data["stability"] is not None:
        lines += [
            "Stiff and extreme inputs through every stage (`dresg_addon/evaluation/stability.py`, run as tests by "
            "`tests/test_stability.py`). Each row says what was checked and what came out.",
            "",
            format_markdown(data["stability"]),
            "",
        ]
    else:
        lines += ["Skipped (--no-stability).", ""]
    lines.append(
        f"Report written in {data['seconds']:.0f} s; load average at the end {load_average(1)}. Times are "
        "wall-clock: other work on the machine slows them, so compare runs of one report only."
    )
    return "\n".join(lines) + "\n"


def build_report(options: ReportOptions, say: Callable[[str], None] | None = None) -> Path:
    """Measure everything (:func:`~.report_measure.measure_report`), write ``report.md``, ``report.json`` and the
    PNG plots into ``options.out``; returns the Markdown path."""
    from ..util.fileutil import atomic_write_bytes

    say = say or (lambda message: print(message, file=sys.stderr, flush=True))
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    figures = matplotlib_available()
    if not figures:
        say(f"report: {FIGURES_NEED_MATPLOTLIB}")
    work = out / "logs"
    work.mkdir(exist_ok=True)
    data = measure_report(options, work, say)
    plotted = {key: data[key] for key in ("raster", "runs", "unstylized", "convergence")}
    atomic_write_bytes(out / "report.json", (json.dumps(plotted, indent=1, allow_nan=False) + "\n").encode("utf-8"))
    if figures:
        draw_plots(plotted, out)
    path = out / "report.md"
    atomic_write_bytes(path, report_markdown(data, figures).encode("utf-8"))
    return path
