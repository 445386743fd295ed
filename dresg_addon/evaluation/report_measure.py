"""What ``dresg report`` measures, as data: :func:`measure_report` returns it and :mod:`.report` writes it.

On the user's scene, paintings and cameras (the built-in demo scene and painting when none are given):

(a) the fast rasterizer's max error against the float64 reference renderer (:mod:`dresg_addon.raster.reference`)
    and its forward time, one point per speed-knob setting of :class:`~dresg_addon.raster.RasterSettings`
    (:mod:`dresg_addon.raster.knobs`, the ones ``bench/raster.py`` measures too). The reference loops in Python,
    so it renders a small pixel window at the image centre, from the Gaussians that can reach that window (a
    conservative cull); the fast path renders the whole scene and the same window is compared;
(b) the novel-view metrics of :func:`.views.evaluate_views` (those of ``dresg evaluate`` and the quality bench)
    against the stylization's wall time, for the presets and for stage counts;
(c) the fit's error at every fit step and each stage's distance to its own targets, from the stylize log and
    progress reports of one run;
(d) the stiff and extreme cases of :mod:`.stability`.

Cameras: with a camera file, its cameras in path order, the 1st, 3rd, ... to stylize from and the 2nd, 4th,
... held out as the novel views to measure on; else an orbit ring to stylize from and the ring half a step
further round to measure on. ``quick`` shrinks every budget (smaller images, fewer stages, steps and views) so
that the whole report takes a minute or two; its numbers show the machinery, not the method's quality.
"""

from __future__ import annotations

import json
import math
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ..method.config import DEFAULT_PRESET, PRESETS, Plan, StylizeConfig
from ..method.schedule import DDIM_STEPS
from ..raster.knobs import SPEED_KNOBS, knob_settings, window_errors
from ..scene.camera import Camera, look_at
from ..scene.gaussians import GaussianScene
from ..util.errors import ConfigError, with_path
from ..util.machine import cpu_model, load_average, usable_cores

DEMO = "demo"

# The rasterizer's speed knobs are raster/knobs.py's (the benchmark measures the same ones); --quick takes
# the default and three of them.
QUICK_RASTER_KNOBS = tuple(
    (knob, value)
    for knob, value in SPEED_KNOBS
    if value is None
    or (knob, value)
    in {
        ("truncation_sigma", 3.0),
        ("truncation_sigma", 2.0),
        ("dtype", "float32"),
    }
)


@dataclass(frozen=True)
class ReportOptions:
    """What the report measures; ``None`` fields take the quick or full default."""

    out: Path = Path("report")
    scene: str | None = None  # a scene file; None or "demo": the built-in demo scene
    styles: tuple[str, ...] = ()  # painting files; empty: the demo painting
    cameras: str | None = None  # a camera file: 1st, 3rd, ... to stylize from, 2nd, 4th, ... held out; None: orbit
    up: tuple[float, float, float] = (0.0, -1.0, 0.0)  # orbit cameras: the world direction shown up
    quick: bool = False
    width: int | None = None  # image width (quick 112, full 224)
    height: int | None = None  # image height (quick 80, full 160; a camera file keeps its aspect without it)
    views: int | None = None  # orbit cameras (quick 4, full 8)
    presets: tuple[str, ...] | None = None  # default: every preset
    stage_counts: tuple[int, ...] | None = None  # stage counts of the default preset (quick 1, 2; full 1, 2, 4, 6)
    repeats: int | None = None  # timing repeats of the rasterizer knobs (quick 1, full 3)
    stability: bool = True
    seed: int = 0

    def resolved(self) -> ReportOptions:
        """The options with every default filled in for quick or full, checked."""
        quick = self.quick
        keeps_aspect = self.cameras is not None and self.height is None
        out = replace(
            self,
            width=self.width or (112 if quick else 224),
            height=self.height or (None if keeps_aspect else 80 if quick else 160),
            views=self.views or (4 if quick else 8),
            presets=tuple(self.presets) if self.presets is not None else tuple(PRESETS),
            stage_counts=tuple(self.stage_counts)
            if self.stage_counts is not None
            else ((1, 2) if quick else (1, 2, 4, 6)),
            repeats=self.repeats or (1 if quick else 3),
        )
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
    cameras: list[Camera]  # cameras to stylize from, in path order
    eval_cameras: list[Camera]  # novel views between them, in path order, for the metrics
    raster_camera: Camera
    styles: list[tuple[str, np.ndarray]]  # (name, [H, W, 3] float32)


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
    """The scene, cameras to stylize from and to measure on, rasterizer camera (twice the size) and paintings."""
    from ..util.imageio import STYLE_MAX_SIDE, read_rgb
    from .views import check_camera_sizes

    width, height, n = options.width, options.height, options.views
    if options.scene in (None, DEMO):
        from ..scene.demo import demo_cameras, demo_scene, demo_style_image

        scene = demo_scene(options.seed)
        label = f"built-in demo scene ({len(scene):,} Gaussians)"
        hint = None
        default_style = ("demo painting", demo_style_image(seed=options.seed))
        if options.cameras is None:
            cameras = demo_cameras(scene, n=n, width=width, height=height)
            eval_cameras = demo_cameras(scene, n=n, width=width, height=height, azimuth_offset_deg=180.0 / n)
    else:
        from ..scene.demo import demo_style_image
        from ..scene.io import read_scene
        from ..scene.orbit import orbit_cameras

        scene_path = Path(options.scene)
        if not scene_path.exists():
            raise ConfigError(with_path(scene_path, "scene file not found"))
        scene = read_scene(scene_path)
        label = f"{scene_path.name} ({len(scene):,} Gaussians)"
        hint = None if options.cameras else _hint_camera(scene_path, 2 * width, 2 * height)
        default_style = ("demo painting", demo_style_image(seed=options.seed))
        if options.cameras is None:
            size = {"width": width, "height": height, "up": options.up}
            cameras = orbit_cameras(scene, n, **size)
            eval_cameras = orbit_cameras(scene, n, azimuth_offset_deg=180.0 / n, **size)
    if options.cameras is not None:
        from ..scene.camera_io import load_cameras

        path = load_cameras(options.cameras, width=width, height=height)
        if len(path) < 4:
            raise ConfigError(
                with_path(options.cameras, f"the report needs at least 4 cameras (2 held out), got {len(path)}")
            )
        cameras, eval_cameras = path[0::2], path[1::2]
    check_camera_sizes([*cameras, *eval_cameras])
    raster_camera = hint or cameras[0].resized(2 * cameras[0].width, 2 * cameras[0].height)
    styles = [(Path(p).stem, read_rgb(p, max_side=STYLE_MAX_SIDE)) for p in options.styles] or [default_style]
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


def _torch(array) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))


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


# ----------------------------------------------------------------------------------------------------
# (b, c) Stylization runs


@dataclass
class RunRecord:
    label: str  # e.g. "preview", "stages 5"
    group: str  # "preset" or "stages"
    style: str
    config: StylizeConfig
    plan: Plan
    seconds: float  # stylize wall time (view selection to post stage)
    metrics: dict
    log: list[dict]  # the stylize log (JSON lines, read back)
    steps: list[tuple[float, object, int, float]] = field(default_factory=list)  # (seconds, stage, step, loss)
    views: int = 0  # active views


def stylize_with_log(
    scene, cameras, style, config, log_path: Path, plan: Plan | None = None
) -> tuple[object, list[dict], list[tuple]]:
    """Run :func:`~dresg_addon.method.loop.stylize` with a log file; (result, log records, step timestamps)."""
    from ..method.loop import stylize

    steps = []
    start = time.perf_counter()

    def progress(p):
        if p.phase in ("fit", "post") and p.step >= 1 and math.isfinite(p.loss):  # NaN: a report between rounds
            steps.append((time.perf_counter() - start, "post" if p.phase == "post" else p.stage, p.step, p.loss))

    result = stylize(scene, cameras, style, config, progress=progress, log_path=log_path, plan=plan)
    records = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    return result, records, steps


def quick_config(config: StylizeConfig, plan: Plan) -> tuple[StylizeConfig, Plan]:
    """A preset shrunk for ``--quick``: at most 2 stages of 2 updates, 3 fit and 3 post steps, 2 active
    views, proposals at most 112x80."""
    scale = min(1.0, 112 / config.proposal_width, 80 / config.proposal_height)
    small = config.with_(
        stages=min(config.stages, 2),
        max_views=min(config.max_views or 2, 2),
        proposal_width=max(16, round(config.proposal_width * scale)),
        proposal_height=max(16, round(config.proposal_height * scale)),
    )
    return small, plan.with_(
        updates_per_stage=min(plan.updates_per_stage, 2),
        fit_steps=min(plan.fit_steps, 3),
        post_steps=min(plan.post_steps, 3),
    )


def planned_runs(options: ReportOptions) -> list[tuple[str, str, StylizeConfig, Plan]]:
    """(label, group, config, plan) of every run: the presets, then the default preset at each stage count (early
    stop off, so that every count runs in full)."""
    shrink = quick_config if options.quick else (lambda c, p: (c, p))
    runs = []
    for name in options.presets:
        config = PRESETS[name].with_(seed=options.seed)
        runs.append((name, "preset", *shrink(config, config.plan())))
    for count in options.stage_counts:
        base = PRESETS[DEFAULT_PRESET].with_(seed=options.seed)
        config, plan = shrink(base, base.plan().with_(early_stop=0.0))
        config = config.with_(stages=count)
        if count * plan.updates_per_stage > DDIM_STEPS:
            raise ConfigError(f"stage count {count} needs more than {DDIM_STEPS} DDIM steps")
        runs.append((f"stages {count}", "stages", config, plan))
    return runs


def run_stylizations(
    inputs: ReportInputs, options: ReportOptions, work: Path, say=print
) -> tuple[list[RunRecord], dict]:
    """Every planned run on every style; the records and the unstylized scene's metrics per style."""
    from .views import base_views, evaluate_views

    records, base_metrics = [], {}
    base = base_views(inputs.scene, inputs.eval_cameras)
    for style_name, style in inputs.styles:
        base_metrics[style_name] = evaluate_views(inputs.scene, base, style).mean
        done: dict[str, RunRecord] = {}
        for label, group, config, plan in planned_runs(options):
            key = json.dumps([config.to_dict(), asdict(plan)], sort_keys=True, default=str)
            if key in done:  # a stage count that is a preset itself: measure it once
                records.append(replace(done[key], label=label, group=group))
                continue
            safe = "".join(ch if ch.isalnum() else "_" for ch in f"{style_name}_{label}")
            log_path = work / f"{safe}.jsonl"
            result, log, steps = stylize_with_log(inputs.scene, inputs.cameras, style, config, log_path, plan)
            measured = evaluate_views(result.scene, base, style, stroke_size=config.stroke_size).mean
            record = RunRecord(
                label,
                group,
                style_name,
                config,
                plan,
                result.seconds,
                measured,
                log,
                steps,
                len(result.selection.indices),
            )
            done[key] = record
            records.append(record)
            say(
                f"  {style_name} / {label}: {record.seconds:.1f} s, SW patch {measured['sw_patches']:.4f}, "
                f"SW colour {measured['sw_colors']:.4f}, SSIM {measured['ssim']:.3f}"
            )
    return records, base_metrics


def average_runs(records: list[RunRecord]) -> list[dict]:
    """Per (label, group): time and metrics averaged over the styles (None where a style has no value)."""
    grouped: dict[tuple[str, str], list[RunRecord]] = {}
    for r in records:
        grouped.setdefault((r.label, r.group), []).append(r)
    rows = []
    for (label, group), runs in grouped.items():
        row = {"label": label, "group": group, "seconds": statistics.mean(r.seconds for r in runs)}
        row["config"] = {**asdict(runs[0].plan), **runs[0].config.to_dict()}  # the table shows both
        row["views"] = runs[0].views
        for key in runs[0].metrics:
            values = [r.metrics[key] for r in runs if r.metrics[key] is not None]
            row[key] = statistics.mean(values) if values else None
        rows.append(row)
    return rows


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
    return max(
        records,
        key=lambda r: (r.config.stages * r.plan.fit_steps + r.plan.post_steps, -records.index(r)),
    )


def _window(camera: Camera, quick: bool) -> tuple[int, int, int, int]:
    """The reference window (x0, y0, w, h) at the image centre: 16x12 pixels quick, 32x24 full."""
    wx, wy = (16, 12) if quick else (32, 24)
    wx, wy = min(wx, camera.width), min(wy, camera.height)
    return ((camera.width - wx) // 2, (camera.height - wy) // 2, wx, wy)


def measure_report(options: ReportOptions, work: Path, say: Callable[[str], None] = print) -> dict:
    """Everything the report shows, as JSON-ready data (the stability cases as CaseResult under "stability");
    the stylize logs go to ``work``."""
    options = options.resolved()
    started = time.perf_counter()
    inputs = load_inputs(options)
    first, novel = inputs.cameras[0], inputs.eval_cameras[0]
    say(f"report: {inputs.scene_label}, {len(inputs.cameras)} views at {first.width}x{first.height}")
    data = {
        "machine": machine_description(),
        "quick": options.quick,
        "scene": inputs.scene_label,
        "cameras": f"{len(inputs.cameras)} {'file' if options.cameras else 'orbit'} cameras at "
        f"{first.width}x{first.height} to stylize from, {len(inputs.eval_cameras)} novel views "
        + ("held out between them" if options.cameras else "between them")
        + f" ({novel.width}x{novel.height}) to evaluate on",
        "styles": [name for name, _ in inputs.styles],
    }
    say("(a) rasterizer error against run time")
    camera = inputs.raster_camera
    knobs = QUICK_RASTER_KNOBS if options.quick else SPEED_KNOBS
    data["raster"] = rasterizer_error_vs_time(
        inputs.scene, camera, _window(camera, options.quick), knobs, options.repeats, say
    )
    data["raster"].update(camera_name=camera.name or "hint", repeats=options.repeats)
    say("(b) stylization work-precision")
    records, base_per_style = run_stylizations(inputs, options, work, say)
    data["runs"] = average_runs(records)
    data["unstylized"] = mean_metrics(base_per_style)
    say("(c) convergence")
    chosen = convergence_run([r for r in records if r.style == inputs.styles[0][0]])
    data["convergence"] = None
    if chosen is not None:
        data["convergence"] = {"label": chosen.label, "style": chosen.style, "steps": chosen.steps, "log": chosen.log}
    data["stability"] = None
    if options.stability:
        say("(d) numerical stability")
        from .stability import run_all

        data["stability"] = run_all()
    data["seconds"] = time.perf_counter() - started
    return data
