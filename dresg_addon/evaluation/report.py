"""Error against run time, convergence and numerical stability: ``python -m dresg_addon report``.

Writes ``report.md`` and PNG plots into one folder. The plots are drawn with matplotlib, an optional extra
(``pip install .[report]``); without it the report is written without them and says so in one line.

(a) ``raster_error.png``: the fast rasterizer's max error against the float64 reference renderer
    (:mod:`dresg_addon.raster.reference`) against its forward time, one point per speed-knob setting of
    :class:`~dresg_addon.raster.RasterSettings` (:mod:`dresg_addon.raster.knobs`, the ones ``bench/raster.py`` measures
    too). The reference loops in Python, so it renders a small
    pixel window at the image centre, from the Gaussians that can reach that window (a conservative
    cull); the fast path renders the whole scene and the same window is compared.
(b) ``work_precision.png``: the weight-free metrics of :mod:`.metrics` (sliced Wasserstein style
    distances, SSIM and gradient structure to the base render, cross-view consistency) against the
    stylization's wall time, for the presets and for stage counts; its table adds the texture kept and
    the shapes (:func:`.metrics.texture_kept`, :func:`.metrics.shape_similarity`).
(c) ``convergence.png``: the fit's error at every fit step (the RMSE after each round of a solved colour
    fit, the Eq. 16 loss of an Adam step) and each stage's distance to its own targets before and after
    its fit, against time, from the stylize log and progress reports of one run.
(d) the stiff and extreme cases of :mod:`.stability`, as a table.

Every measured value behind the plots goes to ``report.json``; :func:`draw_plots` redraws the PNGs from it.

The scene is the real bonsai (``shared/data/scenes/bonsai-7k-mini.splat``, 273k Gaussians) with orbit
cameras and the shared style paintings when they are present, else the built-in demo. ``quick`` shrinks
every budget (the demo scene unless a scene is given, smaller images, fewer stages, steps and views) so
that the whole report takes a minute or two; its numbers show the machinery, not the method's quality.
"""

from __future__ import annotations

import json
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import torch

from ..method.config import DEFAULT_PRESET, PRESETS, StylizeConfig
from ..raster.knobs import SPEED_KNOBS, knob_settings, window_errors
from ..scene.camera import Camera, look_at
from ..scene.gaussians import GaussianScene
from ..util.errors import ConfigError, with_path
from ..util.machine import cpu_model, load_average, usable_cores

REPO = Path(__file__).resolve().parents[2]
SHARED_DATA = Path(os.environ.get("DRESG_SHARED_DATA", REPO.parent / "shared" / "data"))
BONSAI = "scenes/bonsai-7k-mini.splat"
DEFAULT_STYLES = ("starry_night.jpg", "the_scream.jpg")
DEMO = "demo"

# The rasterizer's speed knobs are raster/knobs.py's (the benchmark measures the same ones); --quick takes
# the default and six of them.
QUICK_RASTER_KNOBS = tuple(
    (knob, value)
    for knob, value in SPEED_KNOBS
    if value is None
    or (knob, value)
    in {
        ("tile_size", 16),
        ("max_per_pixel", 32),
        ("max_per_pixel", 8),
        ("truncation_sigma", 3.0),
        ("truncation_sigma", 2.0),
        ("dtype", "float32"),
    }
)
ERROR_FLOOR = 1e-17  # errors of exactly 0 are drawn here on the log axis


@dataclass(frozen=True)
class ReportOptions:
    """What the report measures; ``None`` fields take the quick or full default."""

    out: Path = Path("report")
    scene: str | None = None  # a scene file, "demo", or None: the bonsai when present (not quick), else the demo
    styles: tuple[str, ...] = ()  # empty: the shared paintings with a real scene, else the demo painting
    quick: bool = False
    width: int | None = None  # evaluation and stylization camera size (quick 112x80, full 224x160)
    height: int | None = None
    views: int | None = None  # orbit cameras (quick 4, full 8)
    presets: tuple[str, ...] | None = None  # default: every preset
    stage_counts: tuple[int, ...] | None = None  # stage counts of the default preset (quick 1, 2; full 1, 2, 4, 6)
    repeats: int | None = None  # timing repeats of the rasterizer knobs (quick 1, full 3)
    stability: bool = True
    seed: int = 0

    def resolved(self) -> ReportOptions:
        """The options with every default filled in for quick or full, checked."""
        quick = self.quick
        out = replace(
            self,
            width=self.width or (112 if quick else 224),
            height=self.height or (80 if quick else 160),
            views=self.views or (4 if quick else 8),
            presets=tuple(self.presets) if self.presets is not None else tuple(PRESETS),
            stage_counts=tuple(self.stage_counts)
            if self.stage_counts is not None
            else ((1, 2) if quick else (1, 2, 4, 6)),
            repeats=self.repeats or (1 if quick else 3),
        )
        if out.width < 16 or out.height < 16:
            raise ConfigError(f"report image size {out.width}x{out.height} must be at least 16x16")
        if out.views < 2:
            raise ConfigError(f"the report needs at least 2 orbit views for consistency, got {out.views}")
        unknown = [p for p in out.presets if p not in PRESETS]
        if unknown:
            raise ConfigError(f"unknown preset(s) {', '.join(unknown)} (choose from {', '.join(PRESETS)})")
        if any(s < 1 for s in out.stage_counts):
            raise ConfigError(f"stage counts must be >= 1, got {list(out.stage_counts)}")
        return out


# ----------------------------------------------------------------------------------------------------
# Inputs


@dataclass
class ReportInputs:
    scene: GaussianScene
    scene_label: str
    cameras: list[Camera]  # orbit cameras to stylize from, in path order
    eval_cameras: list[Camera]  # novel views between them (half a step further round), for the metrics
    raster_camera: Camera
    styles: list[tuple[str, np.ndarray]]  # (name, [H, W, 3] float32)


def shared_styles(count: int) -> list[Path]:
    """Up to ``count`` of the shared style paintings: the default ones first, then the rest in name order."""
    folder = SHARED_DATA / "styles"
    if not folder.is_dir():
        return []
    found = sorted(folder.glob("*.jpg"))
    preferred = [folder / name for name in DEFAULT_STYLES if (folder / name).exists()]
    ordered = preferred + [p for p in found if p not in preferred]
    return ordered[:count]


def _hint_camera(scene_path: Path, width: int, height: int) -> Camera | None:
    """The ``<stem>.camera_hint.json`` pose next to a scene (position, look-at, up), 50 degrees wide."""
    hint_path = scene_path.with_name(scene_path.name.split(".")[0] + ".camera_hint.json")
    if not hint_path.exists():
        return None
    hint = json.loads(hint_path.read_text())
    w2c = look_at(hint["initialCameraPosition"], hint["initialCameraLookAt"], hint["cameraUp"])
    fx = width / (2.0 * math.tan(math.radians(25.0)))
    return Camera(width, height, fx, fx, width / 2.0, height / 2.0, w2c, "hint")


def load_inputs(options: ReportOptions) -> ReportInputs:
    """The scene, orbit cameras, rasterizer camera (twice the evaluation size) and style images."""
    from ..scene.orbit import orbit_cameras
    from ..util.imageio import STYLE_MAX_SIDE, read_rgb

    width, height, n = options.width, options.height, options.views
    raster_size = (2 * width, 2 * height)
    scene_path = None
    if options.scene is None:
        candidate = SHARED_DATA / BONSAI
        scene_path = candidate if candidate.exists() and not options.quick else None
    elif options.scene != DEMO:
        scene_path = Path(options.scene)
    if scene_path is None:
        from ..scene.demo import demo_cameras, demo_scene, demo_style_image

        scene = demo_scene(options.seed)
        cameras = demo_cameras(scene, n=n, width=width, height=height)
        eval_cameras = demo_cameras(scene, n=n, width=width, height=height, azimuth_offset_deg=180.0 / n)
        raster_camera = demo_cameras(scene, n=1, width=raster_size[0], height=raster_size[1])[0]
        label = f"built-in demo scene ({len(scene):,} Gaussians)"
        default_styles = [("demo painting", demo_style_image(seed=options.seed))]
    else:
        from ..scene.io import read_scene

        if not scene_path.exists():
            raise ConfigError(with_path(scene_path, "scene file not found"))
        scene = read_scene(scene_path)
        cameras = orbit_cameras(scene, n, width=width, height=height)
        eval_cameras = orbit_cameras(scene, n, width=width, height=height, azimuth_offset_deg=180.0 / n)
        raster_camera = (
            _hint_camera(scene_path, *raster_size)
            or orbit_cameras(scene, 1, width=raster_size[0], height=raster_size[1])[0]
        )
        label = f"{scene_path.name} ({len(scene):,} Gaussians)"
        default_styles = [
            (p.stem, read_rgb(p, max_side=STYLE_MAX_SIDE)) for p in shared_styles(1 if options.quick else 2)
        ]
        if not default_styles:
            from ..scene.demo import demo_style_image

            default_styles = [("demo painting", demo_style_image(seed=options.seed))]
    styles = [(Path(p).stem, read_rgb(p, max_side=STYLE_MAX_SIDE)) for p in options.styles] or default_styles
    return ReportInputs(scene, label, cameras, eval_cameras, raster_camera, styles)


# ----------------------------------------------------------------------------------------------------
# Machine


def machine_description() -> str:
    """CPU model, usable cores, OS, Python and torch versions, and the load average now."""
    return (
        f"{cpu_model()}, {usable_cores()} cores usable, {platform.system()} {platform.release()}, Python "
        f"{platform.python_version()}, torch {torch.__version__} ({torch.get_num_threads()} threads), "
        f"load average {load_average(1)} (1, 5, 15 min)"
    )


# ----------------------------------------------------------------------------------------------------
# (a) Rasterizer error against run time


def window_subset(scene: GaussianScene, camera: Camera, window, near: float = 0.01) -> np.ndarray:  # -> [K] indices
    """Indices of the Gaussians that can reach pixel ``window`` (x0, y0, w, h): a conservative cull.

    A Gaussian's alpha falls below 1/255 beyond sqrt(2 ln 255) = 3.33 standard deviations of its
    projected footprint, whose deviation is at most s_max f / z times the frustum guard's Jacobian
    factor sqrt(1 + gx^2 + gy^2), plus the sqrt(0.3) low-pass; 3.5 deviations + 1 pixel are kept.
    """
    means = scene.means.astype(np.float64)
    w2c = camera.world_to_camera
    p = means @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    ok = np.isfinite(p).all(1) & (z > near)
    z_safe = np.where(ok, z, 1.0)
    u = camera.fx * p[:, 0] / z_safe + camera.cx
    v = camera.fy * p[:, 1] / z_safe + camera.cy
    gx, gy = 1.3 * camera.width / (2 * camera.fx), 1.3 * camera.height / (2 * camera.fy)
    sigma = np.exp(scene.log_scales.astype(np.float64).max(1)) * max(camera.fx, camera.fy) / z_safe
    reach = 3.5 * (sigma * math.sqrt(1.0 + gx * gx + gy * gy) + math.sqrt(0.3)) + 1.0
    x0, y0, w, h = window
    ok &= (u + reach >= x0) & (u - reach <= x0 + w) & (v + reach >= y0) & (v - reach <= y0 + h)
    return np.nonzero(ok)[0]


def _fastest_time(fn: Callable[[], object], repeats: int) -> float:
    """The fastest of ``repeats`` runs: other work on a shared machine only ever adds time."""
    times = []
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def rasterizer_error_vs_time(
    scene: GaussianScene, camera: Camera, window, knobs=SPEED_KNOBS, repeats: int = 3, say=print
) -> dict:
    """Per knob setting: max |rgb - reference| and |alpha - reference| on ``window``, and the forward time.

    Colours go in as float64, so the output is float64 too and the exact default's error shows the
    rasterizer's own arithmetic. The time is the fastest of ``repeats`` full-image forward renders (no
    gradients, the first of them the one that gives the error), after one warm-up render.
    """
    from ..raster import render
    from ..raster.reference import reference_render
    from ..raster.sh import colors_from_sh

    tensors = [_torch(a) for a in (scene.means, scene.quats, scene.log_scales, scene.opacity_logits)]
    center = torch.as_tensor(camera.center, dtype=torch.float32)
    with torch.no_grad():
        rest = None if scene.sh_rest is None else _torch(scene.sh_rest).double()
        all_colors = colors_from_sh(_torch(scene.sh_dc).double(), rest, tensors[0], center)
    subset = window_subset(scene, camera, window)
    part = scene.subset(subset)
    start = time.perf_counter()
    reference = reference_render(
        part.means,
        part.quats,
        part.log_scales,
        part.opacity_logits,
        all_colors[torch.from_numpy(subset)].numpy(),
        camera,
        window=window,
    )
    reference_seconds = time.perf_counter() - start

    def forward(settings):
        with torch.no_grad():
            return render(*tensors, all_colors, camera, settings)

    forward(knob_settings("default", None))  # warm-up: first-call allocations are not any knob's cost
    rows = []
    for knob, value in knobs:
        settings = knob_settings(knob, value)
        start = time.perf_counter()
        out = forward(settings)
        seconds = time.perf_counter() - start
        if repeats > 1:
            seconds = min(seconds, _fastest_time(lambda settings=settings: forward(settings), repeats - 1))
        rows.append(
            {
                "knob": knob,
                "value": value,
                **window_errors(out, reference, window),
                "pairs": out.n_pairs,
                "seconds": seconds,
            }
        )
        say(f"  raster {knob}={value}: error {rows[-1]['rgb_error']:.2e}, {seconds:.3f} s")
    return {
        "rows": rows,
        "window": list(window),
        "subset": int(subset.size),
        "reference_seconds": reference_seconds,
        "coverage": float(reference["alpha"].mean()),
        "camera": f"{camera.width}x{camera.height}",
    }


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


# ----------------------------------------------------------------------------------------------------
# Evaluation of a stylized scene


def _torch(array) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))


def _same_geometry(a: GaussianScene, b: GaussianScene) -> bool:
    return len(a) == len(b) and all(
        np.array_equal(getattr(a, k), getattr(b, k)) for k in ("means", "log_scales", "quats", "opacity_logits")
    )


class ViewEvaluator:
    """The report's weight-free metrics of stylized scenes against one base scene and camera path.

    The base scene's per-view contributions are cached (``ColorOnlyRenderer``), so a stylized scene
    with the base geometry (every colour-only run) renders each view with one sparse product; scenes
    whose geometry moved are rendered in full.
    """

    def __init__(self, base: GaussianScene, cameras: Sequence[Camera], settings=None):
        from ..raster import ColorOnlyRenderer, RasterSettings

        self.base = base
        self.cameras = list(cameras)
        self.settings = settings or RasterSettings()
        means, quats, log_scales, logits = (
            _torch(a) for a in (base.means, base.quats, base.log_scales, base.opacity_logits)
        )
        with torch.no_grad():
            self.fast = [ColorOnlyRenderer(means, quats, log_scales, logits, c, self.settings) for c in self.cameras]
        self.base_views = self._views(base)

    def _style(self, style: np.ndarray) -> torch.Tensor:  # [H, W, 3] -> [3, h, w]
        """The style image resized (aspect kept) so that its shorter side matches the first camera's."""
        from ..util.imageio import resize_image

        style_t = torch.from_numpy(np.ascontiguousarray(style, dtype=np.float32)).permute(2, 0, 1)
        h, w = style_t.shape[1:]
        factor = min(self.cameras[0].width, self.cameras[0].height) / min(w, h)
        return resize_image(style_t, max(1, round(w * factor)), max(1, round(h * factor)))

    def _views(self, scene: GaussianScene) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """(rgb [3, H, W] in [0, 1], alpha [H, W], depth [H, W]) per camera."""
        from ..raster import render_scene
        from ..raster.sh import colors_from_sh

        views = []
        if _same_geometry(scene, self.base):
            means = _torch(scene.means)
            for camera, fast in zip(self.cameras, self.fast):
                rest = None if scene.sh_rest is None else _torch(scene.sh_rest)
                center = torch.as_tensor(camera.center, dtype=torch.float32)
                with torch.no_grad():
                    rgb = fast(colors_from_sh(_torch(scene.sh_dc), rest, means, center))
                views.append((rgb.clamp(0, 1).permute(2, 0, 1), fast.alpha, fast.depth))
        else:
            for camera in self.cameras:
                out = render_scene(scene, camera, self.settings)
                views.append((out.rgb.clamp(0, 1).permute(2, 0, 1), out.alpha, out.depth))
        return views

    def measure(self, scene: GaussianScene, style: np.ndarray) -> dict[str, float | None]:  # style [H, W, 3]
        """Means over the views: sw_colors, sw_patches, ssim, gs, texture_kept, shapes (on the pixels the base
        render covers); consistency short and long (masked RMSE)."""
        views = self.base_views if scene is self.base else self._views(scene)
        return self._metrics(views, self._style(style))

    def _metrics(self, views, style: torch.Tensor) -> dict[str, float | None]:
        from . import metrics

        rgb = [v[0] for v in views]
        base_rgb = [v[0] for v in self.base_views]
        images = [v[0].permute(1, 2, 0) for v in views]
        alphas, depths = [v[1] for v in views], [v[2] for v in views]
        n = len(self.cameras)
        masks = [v[1] for v in self.base_views]  # the pixels the scene covers
        pairs = list(zip(rgb, base_rgb, masks))
        return {
            "sw_colors": float(metrics.sliced_wasserstein_colors(rgb, style, masks=masks).mean()),
            "sw_patches": float(metrics.sliced_wasserstein_patches(rgb, style, masks=masks).mean()),
            "ssim": float(torch.stack([metrics.ssim_per_image(a, b, mask=m) for a, b, m in pairs]).mean()),
            "gs": float(torch.stack([metrics.gradient_structure_similarity(a, b, mask=m) for a, b, m in pairs]).mean()),
            "texture_kept": float(torch.stack([metrics.texture_kept(a, b, mask=m) for a, b, m in pairs]).mean()),
            "shapes": float(torch.stack([metrics.shape_similarity(a, b, mask=m) for a, b, m in pairs]).mean()),
            "short_rmse": metrics.consistency_rmse(images, depths, alphas, self.cameras, 1).rmse,
            "long_rmse": metrics.consistency_rmse(images, depths, alphas, self.cameras, max(1, n // 2)).rmse,
        }


# ----------------------------------------------------------------------------------------------------
# (b, c) Stylization runs


@dataclass
class RunRecord:
    label: str  # e.g. "preview", "stages 5"
    group: str  # "preset" or "stages"
    style: str
    config: StylizeConfig
    seconds: float  # stylize wall time (view selection to post stage)
    metrics: dict
    log: list[dict]  # the stylize log (JSON lines, read back)
    steps: list[tuple[float, object, int, float]] = field(default_factory=list)  # (seconds, stage, step, loss)
    views: int = 0  # active views


def stylize_with_log(scene, cameras, style, config, log_path: Path) -> tuple[object, list[dict], list[tuple]]:
    """Run :func:`~dresg_addon.method.loop.stylize` with a log file; (result, log records, step timestamps)."""
    from ..method.loop import stylize

    steps = []
    start = time.perf_counter()

    def progress(p):
        if p.phase in ("fit", "post") and p.step >= 1:
            steps.append((time.perf_counter() - start, "post" if p.phase == "post" else p.stage, p.step, p.loss))

    result = stylize(scene, cameras, style, config, progress=progress, log_path=log_path)
    records = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    return result, records, steps


def quick_config(config: StylizeConfig) -> StylizeConfig:
    """A preset shrunk for ``--quick``: at most 2 stages of 2 updates, 3 fit and 3 post steps, 2 active
    views, proposals at most 112x80."""
    scale = min(1.0, 112 / config.proposal_width, 80 / config.proposal_height)
    return config.with_(
        stages=min(config.stages, 2),
        updates_per_stage=min(config.updates_per_stage, 2),
        fit_steps=min(config.fit_steps, 3),
        post_steps=min(config.post_steps, 3),
        max_views=min(config.max_views or 2, 2),
        proposal_width=max(16, round(config.proposal_width * scale)),
        proposal_height=max(16, round(config.proposal_height * scale)),
    )


def planned_runs(options: ReportOptions) -> list[tuple[str, str, StylizeConfig]]:
    """(label, group, config) of every run: the presets, then the default preset at each stage count (early
    stop off, so that every count runs in full)."""
    shrink = quick_config if options.quick else (lambda c: c)
    runs = [(name, "preset", shrink(PRESETS[name].with_(seed=options.seed))) for name in options.presets]
    for count in options.stage_counts:
        base = PRESETS[DEFAULT_PRESET].with_(seed=options.seed, early_stop=0.0)
        config = shrink(base).with_(stages=count)
        if count * config.updates_per_stage > config.ddim_steps:
            raise ConfigError(f"stage count {count} needs more than {config.ddim_steps} DDIM steps")
        runs.append((f"stages {count}", "stages", config))
    return runs


def run_stylizations(
    inputs: ReportInputs, options: ReportOptions, work: Path, say=print
) -> tuple[list[RunRecord], dict]:
    """Every planned run on every style; the records and the unstylized scene's metrics per style."""
    records, base_metrics = [], {}
    evaluator = ViewEvaluator(inputs.scene, inputs.eval_cameras)
    for style_name, style in inputs.styles:
        base_metrics[style_name] = evaluator.measure(inputs.scene, style)
        done: dict[str, RunRecord] = {}
        for label, group, config in planned_runs(options):
            key = json.dumps(config.to_dict(), sort_keys=True, default=str)
            if key in done:  # a stage count that is a preset itself: measure it once
                records.append(replace(done[key], label=label, group=group))
                continue
            safe = "".join(ch if ch.isalnum() else "_" for ch in f"{style_name}_{label}")
            result, log, steps = stylize_with_log(inputs.scene, inputs.cameras, style, config, work / f"{safe}.jsonl")
            record = RunRecord(
                label, group, style_name, config, result.seconds, evaluator.measure(result.scene, style), log, steps,
                len(result.selection.indices),
            )  # fmt: skip
            done[key] = record
            records.append(record)
            m = record.metrics
            say(
                f"  {style_name} / {label}: {record.seconds:.1f} s, SW colour {m['sw_colors']:.4f}, "
                f"SW patch {m['sw_patches']:.4f}, SSIM {m['ssim']:.3f}, short RMSE {_fmt(m['short_rmse'])}"
            )
    return records, base_metrics


def _fmt(value, digits: int = 4) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def average_runs(records: list[RunRecord]) -> list[dict]:
    """Per (label, group): time and metrics averaged over the styles (None where a style has no value)."""
    grouped: dict[tuple[str, str], list[RunRecord]] = {}
    for r in records:
        grouped.setdefault((r.label, r.group), []).append(r)
    rows = []
    for (label, group), runs in grouped.items():
        row = {"label": label, "group": group, "seconds": statistics.mean(r.seconds for r in runs)}
        row["config"] = runs[0].config.to_dict()
        row["views"] = runs[0].views
        for key in runs[0].metrics:
            values = [r.metrics[key] for r in runs if r.metrics[key] is not None]
            row[key] = statistics.mean(values) if values else None
        rows.append(row)
    return rows


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
        "| SW colour | SW patch | SSIM | GS | texture kept | shapes | short RMSE | long RMSE |",
        "|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        c = r["config"]
        lines.append(
            f"| {r['label']} | {c['stages']} x {c['updates_per_stage']} | {c['fit_steps']} / {c['post_steps']} "
            f"| {c['proposal_width']}x{c['proposal_height']} | {'on' if c['optimize_geometry'] else 'off'} | {r['views']} "
            f"| {r['seconds']:.1f} | {_fmt(r['sw_colors'])} | {_fmt(r['sw_patches'])} | {_fmt(r['ssim'], 3)} "
            f"| {_fmt(r['gs'], 3)} | {_fmt(r.get('texture_kept'), 3)} | {_fmt(r.get('shapes'), 3)} "
            f"| {_fmt(r['short_rmse'])} | {_fmt(r['long_rmse'])} |"
        )
    lines.append(
        f"| unstylized | | | | | | | {_fmt(base['sw_colors'])} | {_fmt(base['sw_patches'])} | {_fmt(base['ssim'], 3)} "
        f"| {_fmt(base['gs'], 3)} | {_fmt(base.get('texture_kept'), 3)} | {_fmt(base.get('shapes'), 3)} "
        f"| {_fmt(base['short_rmse'])} | {_fmt(base['long_rmse'])} |"
    )
    return "\n".join(lines)


def mean_metrics(per_style: dict[str, dict]) -> dict:
    keys = next(iter(per_style.values())).keys()
    out = {}
    for key in keys:
        values = [m[key] for m in per_style.values() if m[key] is not None]
        out[key] = statistics.mean(values) if values else None
    return out


def convergence_run(records: list[RunRecord]) -> RunRecord | None:
    """The run with the most fit steps in all (ties: the first), whose log the convergence plot shows."""
    if not records:
        return None
    return max(records, key=lambda r: (r.config.stages * r.config.fit_steps + r.config.post_steps, -records.index(r)))


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


def build_report(options: ReportOptions, say: Callable[[str], None] | None = None) -> Path:
    """Measure everything, write ``report.md`` and the PNG plots into ``options.out``; returns the Markdown path."""
    from ..util.fileutil import atomic_write_bytes

    say = say or (lambda message: print(message, file=sys.stderr, flush=True))
    options = options.resolved()
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    machine = machine_description()
    figures = matplotlib_available()
    if not figures:
        say(f"report: {FIGURES_NEED_MATPLOTLIB}")

    def figure(caption: str, name: str) -> list[str]:
        """The Markdown of one figure (the caption says what it shows), or nothing when figures are left out."""
        return [f"![{caption}]({name})", ""] if figures else []

    inputs = load_inputs(options)
    say(f"report: {inputs.scene_label}, {len(inputs.cameras)} views at {options.width}x{options.height}")
    lines = [
        "# DReSG: error against run time, convergence and numerical stability",
        "",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- machine: {machine}",
        f"- mode: {'quick (budgets shrunk: indicative numbers only)' if options.quick else 'full'}",
        f"- scene: {inputs.scene_label}; {len(inputs.cameras)} orbit cameras at {options.width}x{options.height} to "
        f"stylize from, {len(inputs.eval_cameras)} novel views between them to evaluate on",
        f"- styles: {', '.join(name for name, _ in inputs.styles)}",
        *([] if figures else [f"- {FIGURES_NEED_MATPLOTLIB}"]),
        "",
    ]

    # (a)
    say("(a) rasterizer error against run time")
    camera = inputs.raster_camera
    wx, wy = (16, 12) if options.quick else (32, 24)
    wx, wy = min(wx, camera.width), min(wy, camera.height)
    window = ((camera.width - wx) // 2, (camera.height - wy) // 2, wx, wy)
    knobs = QUICK_RASTER_KNOBS if options.quick else SPEED_KNOBS
    raster = rasterizer_error_vs_time(inputs.scene, camera, window, knobs, options.repeats, say)
    lines += [
        "## (a) Rasterizer: error against the float64 reference vs run time",
        "",
        f"The fast rasterizer renders the whole {raster['camera']} image of the scene (camera "
        f"{camera.name or 'hint'}); the float64 reference renderer renders the {wx}x{wy} pixel window at "
        f"({window[0]}, {window[1]}) from the {raster['subset']:,} Gaussians that can reach it "
        f"({raster['reference_seconds']:.1f} s; window coverage {raster['coverage']:.2f}). Error: max absolute "
        f"difference on that window; time: "
        + (f"the fastest of {options.repeats} forward renders" if options.repeats > 1 else "one forward render")
        + " of the full image (no gradients), after a warm-up render.",
        "",
        *figure("rasterizer error against time", "raster_error.png"),
        raster_table(raster),
        "",
    ]

    # (b) and (c)
    say("(b) stylization work-precision")
    work = out / "logs"
    work.mkdir(exist_ok=True)
    records, base_per_style = run_stylizations(inputs, options, work, say)
    rows = average_runs(records)
    base = mean_metrics(base_per_style)
    lines += [
        "## (b) Stylization work-precision",
        "",
        "Metrics of `dresg_addon.evaluation.metrics` on the novel views (never active views; pixels the scene covers) "
        "against the stylization's wall time (view selection to the post stage), averaged over the styles. "
        "Presets as defined in `dresg_addon.method.config`"
        + (", shrunk for the quick run (see the table)" if options.quick else "")
        + f"; the stage counts F run the default preset ({DEFAULT_PRESET}) with F stages and no early stop. "
        "Texture kept: the correlation of the luminance high-pass (sigma 2 px) with the unstylized render's, 4 px "
        "inside the silhouette (1: the scene's own fine texture all still there; lower: more of the painting's); "
        "shapes: SSIM of the luminance blurred by a Gaussian of sigma 3 px (1: the same forms). "
        "Consistency: the stylized view i warped into view i + gap with rendered depth and the known poses, "
        "masked RMSE.",
        "",
        *figure("metrics against time", "work_precision.png"),
        work_precision_table(rows, base),
        "",
    ]
    say("(c) convergence")
    chosen = convergence_run([r for r in records if r.style == inputs.styles[0][0]])
    convergence = None
    lines += ["## (c) Convergence", ""]
    if chosen is not None:
        convergence = {"label": chosen.label, "style": chosen.style, "steps": chosen.steps, "log": chosen.log}
        lines += [
            f'How far the fit of run "{chosen.label}" on {chosen.style} got: its error after every fit step '
            "(colour-only runs solve each fit as bounded least squares: the RMSE over all pixels after each "
            "round; Adam runs: the Eq. 16 loss), and per stage the RMSE over covered pixels between the "
            "stage's targets and the renders before its fit (target gap) and after it (fit residual), "
            "with the joint least-squares optimum of those targets and the share of the gap closed, against "
            "the time since the start of stylize (from its log and progress reports).",
            "",
            *figure("fit error against time", "convergence.png"),
            convergence_table(chosen.log),
            "",
        ]
    else:
        lines += ["No stylization run was requested.", ""]
    data = {"raster": raster, "runs": rows, "unstylized": base, "convergence": convergence}
    atomic_write_bytes(out / "report.json", (json.dumps(data, indent=1, allow_nan=False) + "\n").encode("utf-8"))
    if figures:
        draw_plots(data, out)

    # (d)
    lines += ["## (d) Numerical stability", ""]
    if options.stability:
        say("(d) numerical stability")
        from .stability import format_markdown, run_all

        lines += [
            "Stiff and extreme inputs through every stage (`dresg_addon/evaluation/stability.py`, run as tests by "
            "`tests/test_stability.py`). Each row says what was checked and what came out.",
            "",
            format_markdown(run_all()),
            "",
        ]
    else:
        lines += ["Skipped (--no-stability).", ""]
    lines.append(
        f"Report written in {time.perf_counter() - started:.0f} s; load average at the end {load_average(1)}. Times are "
        "wall-clock: other work on the machine slows them, so compare runs of one report only."
    )
    path = out / "report.md"
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"))
    return path
