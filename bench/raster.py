# SPDX-License-Identifier: GPL-3.0-or-later
"""Rasterizer benchmark (issue 2, section 5). Not a test: it prints tables.

    .venv/bin/python bench/raster.py [--quick] [--markdown out.md] [--repeats 3] [--sizes 10000,100000] [--loaded]
    .venv/bin/python bench/raster.py --against REV [--repeats 3] [--quiet 0.3]

Two tables:

1. Speed and memory at 448x320 for random scenes of N Gaussians and the real bonsai (273k splats,
   ../shared/data, seen from its camera hint; skipped when absent): forward (no gradients),
   forward+backward with gradients on means, quaternions, log-scales and colours, the colour-only
   path (one-time build of the cached contributions, then one forward+backward step), pairs
   (samples composited) and the peak resident memory of the whole process.
2. Error against run time for each speed knob of ``RasterSettings``: the max abs error against the
   float64 reference renderer (``raster.reference``, on a pixel window, since it loops in Python)
   and the run time of that setting on the full image.

Every case runs in a fresh subprocess, so its peak memory (``ru_maxrss``) is its own; it includes
the interpreter and torch (the "baseline" line). Times are "median (best)" of ``--repeats`` runs
after warm-up runs (fewer when one run is slow), with torch's default thread count unless
``--threads``. The load average is printed: on a shared machine the best run is the better guide to
what the code can do, and one thread (``--threads 1``) is steadier than two that wait on each other.

``--against REV`` runs only an A/B comparison: ``dresg render`` of the bonsai from ``AB_VIEWS`` orbit cameras
at 448x320, with this checkout's engine and with REV's (checked out into a temporary git worktree, removed
after), alternating A B B A ... for ``--repeats`` rounds (default 3); per-view median, best and worst of each,
the ratio, and the load before each run; ``--quiet CORES`` waits before each run until other processes use at
most CORES cores (a shared machine). Target on 2 cores: at most ``TARGET_VIEW_S`` a view.

``--loaded`` adds a third table: the bonsai again while another process takes a core (a pure-Python
busy loop) and while another torch job runs (its threads spin between ops), against quiet; target:
at most 2x slower with one core taken.

Targets on a 2-core CPU: bonsai forward+backward with geometry <= 0.5 s; colour-only step <= 30 ms;
1M Gaussians within 8 GB. ``--quick`` is a smoke run (96x64, tiny scenes, one repeat, no bonsai).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import harness  # bench/, beside this script

from dresg_addon.util.machine import load_average
from dresg_addon.util.threads import ADAPT_INTERVAL_S

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DRESG_SHARED_DATA", REPO.parent / "shared" / "data"))
BONSAI = SHARED / "scenes" / "bonsai-7k-mini.splat"
BONSAI_HINT = SHARED / "scenes" / "bonsai-7k-mini.camera_hint.json"

FULL_SIZE = (448, 320)
QUICK_SIZE = (96, 64)
FOV_X_DEG = 50.0
PAIRS_PER_PIXEL = 30.0  # what random scenes aim at before early termination (real scenes: ~10-50)
TARGET_FWD_BWD_S = 0.5
TARGET_COLOUR_STEP_S = 0.030
TARGET_MEMORY_GB = 8.0
FULL_SIZES = (10_000, 100_000, 300_000, 1_000_000)
QUICK_SIZES = (1_000, 4_000)
QUICK_KNOB_N = 1_000
WINDOW_SIZE = (32, 24)  # reference window, at the image centre
TIME_BUDGET_S = 40.0  # per measurement: fewer repeats when one run is slower than budget / repeats
WARMUP = 8  # untimed runs before the timed ones (see timed())
AB_VIEWS = 9  # orbit cameras of the --against comparison
TARGET_VIEW_S = 0.2  # a bonsai view through `dresg render` on 2 cores
QUIET_WAIT_S = 120.0  # --quiet: the longest wait for a quiet moment before a run (then it runs anyway)


def centre_window(width: int, height: int) -> tuple[int, int, int, int]:
    w, h = min(WINDOW_SIZE[0], width), min(WINDOW_SIZE[1], height)
    return (width - w) // 2, (height - h) // 2, w, h


# ----------------------------------------------------------------------------------------------------
# Worker side (one subprocess per case): imports torch and the engine.


def bench_camera(width: int, height: int, world_to_camera=None):
    import numpy as np

    from dresg_addon.scene.camera import Camera

    f = width / (2.0 * math.tan(math.radians(FOV_X_DEG) / 2.0))
    w2c = np.eye(4) if world_to_camera is None else world_to_camera
    return Camera(width, height, f, f, width / 2.0, height / 2.0, w2c)


def random_scene(n: int, width: int, height: int, seed: int = 0):
    """(arrays, camera): ``n`` Gaussians in the frustum of a camera at the origin looking down +z.

    Depths 2-8, centres spread over the image (plus a 5% margin), random rotations, opacity logits
    N(0, 2), per-axis log-scales spread by N(0, 0.4) around a size chosen so that the splats' 1/255
    footprints add up to about ``PAIRS_PER_PIXEL`` per pixel: a few pixels wide at 1M, tens at 10k.
    """
    import numpy as np

    rng = np.random.default_rng(seed)
    camera = bench_camera(width, height)
    z = rng.uniform(2.0, 8.0, n)
    u = rng.uniform(-0.05 * width, 1.05 * width, n)
    v = rng.uniform(-0.05 * height, 1.05 * height, n)
    means = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], 1)
    logits = rng.normal(0.0, 2.0, n)
    opacity = 1.0 / (1.0 + np.exp(-logits))
    reach = np.maximum(np.log(255.0 * opacity), 0.0).mean()  # footprint area = 2 pi sigma^2 ln(255 o)
    sigma2 = max(PAIRS_PER_PIXEL * width * height / (n * 2.0 * math.pi * reach) - 0.3, 0.05)  # minus low-pass
    log_scales = np.log(math.sqrt(sigma2) * z / camera.fx)[:, None] + rng.normal(0.0, 0.4, (n, 3))
    arrays = {
        "means": means,
        "quats": rng.normal(size=(n, 4)),
        "log_scales": log_scales,
        "opacity_logits": logits,
        "colors": rng.uniform(0.0, 1.0, (n, 3)),
    }
    return {k: v.astype(np.float32) for k, v in arrays.items()}, camera


def bonsai_scene(width: int, height: int):
    """(arrays, camera): the bonsai from look_at(initialCameraPosition, initialCameraLookAt, cameraUp)."""
    import numpy as np

    from dresg_addon.scene.camera import look_at
    from dresg_addon.scene.io import read_scene

    scene = read_scene(BONSAI)
    hint = json.loads(BONSAI_HINT.read_text())
    w2c = look_at(hint["initialCameraPosition"], hint["initialCameraLookAt"], hint["cameraUp"])
    arrays = {
        "means": scene.means,
        "quats": scene.quats,
        "log_scales": scene.log_scales,
        "opacity_logits": scene.opacity_logits,
        "colors": np.maximum(0.5 + 0.28209479177387814 * scene.sh_dc, 0.0).astype(np.float32),
    }
    return arrays, bench_camera(width, height, w2c)


def load_case(spec: dict):
    if spec["scene"] == "bonsai":
        return bonsai_scene(spec["width"], spec["height"])
    return random_scene(spec["n"], spec["width"], spec["height"])


def timed(fn, repeats: int) -> list[float]:
    """Seconds of each run of ``fn`` after warm-ups; fewer runs when one is slower than the budget.

    The first renders of a process page-fault while the allocator's heap grows (~85k faults, +0.15 s
    per bonsai render, for about seven renders); an optimisation loop renders hundreds of times, so
    the steady state is what counts: warm up for up to ``WARMUP`` runs or a quarter of the budget.
    """
    harness.THREADS.adapt()  # torch threads for the load now (measured every 2 s), outside the timed runs
    start = time.perf_counter()
    fn()
    warm = time.perf_counter() - start
    for _ in range(min(WARMUP - 1, int(TIME_BUDGET_S / 4 / max(warm, 1e-9)))):
        harness.THREADS.adapt()
        fn()
    runs = max(1, min(repeats, int(TIME_BUDGET_S / max(warm, 1e-9))))
    times = []
    for _ in range(runs):
        harness.THREADS.adapt()
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def _tensors(arrays, grad: bool):
    import torch

    out = {k: torch.from_numpy(v) for k, v in arrays.items()}
    if grad:
        for key in ("means", "quats", "log_scales", "colors"):
            out[key] = out[key].clone().requires_grad_(True)
    return out


def _render(arrays, camera, settings, grad: bool):
    from dresg_addon.raster import render

    t = _tensors(arrays, grad)
    return render(t["means"], t["quats"], t["log_scales"], t["opacity_logits"], t["colors"], camera, settings)


def _loss_weights(camera):
    import torch

    generator = torch.Generator().manual_seed(1)
    return torch.rand(camera.height, camera.width, 3, generator=generator)


def _forward(arrays, camera, settings) -> None:
    import torch

    with torch.no_grad():
        _render(arrays, camera, settings, grad=False)


def _forward_backward(arrays, camera, settings, weights) -> None:
    out = _render(arrays, camera, settings, grad=True)
    (out.rgb * weights).sum().backward()


def run_case(spec: dict) -> dict:
    """Speed and memory of one scene: forward, forward+backward, colour-only build and step."""
    import torch

    from dresg_addon.raster import ColorOnlyRenderer, RasterSettings

    arrays, camera = load_case(spec)
    settings = RasterSettings()
    repeats = spec["repeats"]
    weights = _loss_weights(camera)
    with torch.no_grad():
        out = _render(arrays, camera, settings, grad=False)
    result = {"n": len(arrays["means"]), "pairs": out.n_pairs, "threads": torch.get_num_threads()}
    result["forward_s"] = timed(lambda: _forward(arrays, camera, settings), repeats)
    result["fwd_bwd_s"] = timed(lambda: _forward_backward(arrays, camera, settings, weights), repeats)
    t = _tensors(arrays, grad=False)
    start = time.perf_counter()
    colour_only = ColorOnlyRenderer(t["means"], t["quats"], t["log_scales"], t["opacity_logits"], camera, settings)
    result["colour_build_s"] = time.perf_counter() - start
    colors = t["colors"].clone().requires_grad_(True)

    def colour_step():
        colors.grad = None
        (colour_only(colors) * weights).sum().backward()

    result["colour_step_s"] = timed(colour_step, max(repeats, 10))
    result["peak_rss"] = harness.peak_rss_bytes()
    return result


def run_reference(spec: dict) -> dict:
    """The float64 reference on ``spec['window']`` of the knob scene, saved to ``spec['path']`` (.npz)."""
    import numpy as np

    from dresg_addon.raster.reference import reference_render

    arrays, camera = load_case(spec)
    start = time.perf_counter()
    ref = reference_render(
        arrays["means"], arrays["quats"], arrays["log_scales"], arrays["opacity_logits"], arrays["colors"],
        camera, window=tuple(spec["window"]),
    )  # fmt: skip
    np.savez(spec["path"], rgb=ref["rgb"], alpha=ref["alpha"])
    return {"seconds": time.perf_counter() - start}


def run_knobs(spec: dict) -> dict:
    """Error on the reference window, full-image difference to the default and full-image times,
    for each (knob, value) in ``spec['knobs']``."""
    import numpy as np
    import torch

    from dresg_addon.raster.knobs import knob_settings, window_errors

    arrays, camera = load_case(spec)
    ref = np.load(spec["reference"])
    weights = _loss_weights(camera)
    with torch.no_grad():
        exact = _render(arrays, camera, knob_settings("default", None), grad=False).rgb
    rows = []
    for knob, value in spec["knobs"]:
        settings = knob_settings(knob, value)
        with torch.no_grad():
            out = _render(arrays, camera, settings, grad=False)
        rows.append(
            {
                "knob": knob,
                "value": value,
                **window_errors(out, ref, spec["window"]),
                # The window may miss what a knob changes elsewhere: compare the whole image to the default.
                "full_diff": float((out.rgb - exact).abs().max()),
                "pairs": out.n_pairs,
                "forward_s": timed(lambda s=settings: _forward(arrays, camera, s), spec["repeats"]),
                "fwd_bwd_s": timed(lambda s=settings: _forward_backward(arrays, camera, s, weights), spec["repeats"]),
            }
        )
    return {"rows": rows, "peak_rss": harness.peak_rss_bytes()}


def run_baseline(spec: dict) -> dict:
    """Resident memory of the interpreter with torch and the engine imported, nothing rendered."""
    import torch

    import dresg_addon.raster  # noqa: F401

    return {"peak_rss": harness.peak_rss_bytes(), "threads": torch.get_num_threads(), "torch": torch.__version__}


WORKERS = {"case": run_case, "reference": run_reference, "knobs": run_knobs, "baseline": run_baseline}


# ----------------------------------------------------------------------------------------------------
# Driver side: runs the workers, formats the tables. Does not import torch.


def call_worker(spec: dict) -> dict:
    return harness.call_worker(__file__, spec)


def gb(n_bytes: float) -> str:
    return f"{n_bytes / 1e9:.2f}"


def secs(value: float) -> str:
    return f"{value:.3f}" if value < 10 else f"{value:.1f}"


def timing(times: list[float], scale: float = 1.0, digits: int | None = None) -> str:
    """'median (best)' of ``times`` times ``scale``."""

    def fmt(value):
        return f"{value:.{digits}f}" if digits is not None else secs(value)

    return f"{fmt(statistics.median(times) * scale)} ({fmt(min(times) * scale)})"


def mark(ok: bool) -> str:
    return "met" if ok else "NOT met"


def machine_lines(baseline: dict) -> list[str]:
    return [
        harness.machine_line(baseline, with_os=True),
        f"- load average (1, 5, 15 min) at start: {load_average()}",
        f"- baseline resident memory (interpreter + torch + engine, nothing rendered): "
        f"{gb(baseline.get('peak_rss', 0))} GB, included in every peak below",
        "- times: median (best) of the repeats, seconds unless marked ms",
    ]


def case_table(cases: list[tuple[str, dict]], pixels: int) -> list[str]:
    lines = [
        "| scene | N | pairs | pairs/px | forward (s) | fwd+bwd geometry (s) | colour-only build (s) "
        "| colour-only step (ms) | peak RSS (GB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, r in cases:
        if "error" in r:
            lines.append(f"| {label} | | | | {r['error']} | | | | |")
            continue
        lines.append(
            f"| {label} | {r['n']:,} | {r['pairs']:,} | {r['pairs'] / pixels:.1f} | {timing(r['forward_s'])} "
            f"| {timing(r['fwd_bwd_s'])} | {secs(r['colour_build_s'])} | {timing(r['colour_step_s'], 1e3, 1)} "
            f"| {gb(r['peak_rss'])} |"
        )
    return lines


def target_lines(cases: dict[str, dict]) -> list[str]:
    def verdict(times, target):
        median, best = statistics.median(times), min(times)
        if median <= target:
            return "met"
        return "met by the best run only" if best <= target else "NOT met"

    lines = ["", "Targets (2-core CPU):", ""]
    bonsai = cases.get("bonsai")
    if bonsai and "error" not in bonsai:
        lines.append(
            f"- bonsai forward+backward with geometry <= {TARGET_FWD_BWD_S} s: {timing(bonsai['fwd_bwd_s'])} s, "
            f"{verdict(bonsai['fwd_bwd_s'], TARGET_FWD_BWD_S)}"
        )
        lines.append(
            f"- colour-only step <= {TARGET_COLOUR_STEP_S * 1e3:.0f} ms (bonsai): "
            f"{timing(bonsai['colour_step_s'], 1e3, 1)} ms, {verdict(bonsai['colour_step_s'], TARGET_COLOUR_STEP_S)}"
        )
    else:
        lines.append("- bonsai targets: not measured (bonsai skipped)")
    big = cases.get("1M")
    if big and "error" not in big:
        peak = big["peak_rss"] / 1e9
        lines.append(
            f"- 1M Gaussians within {TARGET_MEMORY_GB:.0f} GB: peak {peak:.2f} GB, {mark(peak <= TARGET_MEMORY_GB)}"
        )
    elif big:
        lines.append(f"- 1M Gaussians within {TARGET_MEMORY_GB:.0f} GB: {big['error']}")
    else:
        lines.append("- 1M Gaussians: not measured in this run")
    return lines


def knob_table(rows: list[dict], per_process_memory: bool) -> list[str]:
    lines = [
        "| knob | value | window: max abs error RGB | window: max abs error alpha | full image: max abs RGB diff to default "
        "| pairs | forward (s) | fwd+bwd (s) | peak RSS (GB) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        value = "" if r["value"] is None else r["value"]
        if isinstance(value, int) and value >= 100_000:
            value = f"{value / 1e6:g}M"
        if "error" in r:
            lines.append(f"| {r['knob']} | {value} | {r['error']} | | | | | | |")
            continue
        memory = gb(r["peak_rss"]) if per_process_memory else "-"
        lines.append(
            f"| {r['knob']} | {value} | {r['rgb_error']:.1e} | {r['alpha_error']:.1e} | {r['full_diff']:.1e} | {r['pairs']:,} "
            f"| {timing(r['forward_s'])} | {timing(r['fwd_bwd_s'])} | {memory} |"
        )
    return lines


def knob_section(knob_case: dict, name: str, repeats: int, quick: bool) -> list[str]:
    """The error-against-run-time table: one reference run, then the knobs (one process each unless quick)."""
    from dresg_addon.raster.knobs import SPEED_KNOBS

    width, height = knob_case["width"], knob_case["height"]
    window = centre_window(width, height)
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "reference.npz")
        print("  running the float64 reference ...", file=sys.stderr, flush=True)
        ref = call_worker({"kind": "reference", **knob_case, "window": window, "path": path})
        rows = []
        if "error" in ref:
            rows.append({"knob": "reference", "value": None, "error": ref["error"]})
        # Full runs: one process per knob, so that each peak (band_pairs!) is its own.
        for group in [] if "error" in ref else ([list(SPEED_KNOBS)] if quick else [[k] for k in SPEED_KNOBS]):
            print(f"  running knobs {', '.join(f'{k}={v}' for k, v in group)} ...", file=sys.stderr, flush=True)
            spec = {"kind": "knobs", **knob_case, "window": window, "reference": path, "repeats": repeats}
            result = call_worker({**spec, "knobs": group})
            if "error" in result:
                rows += [{"knob": k, "value": v, "error": result["error"]} for k, v in group]
                continue
            rows += [{**row, "peak_rss": result["peak_rss"]} for row in result["rows"]]
    x0, y0, w, h = window
    return [
        "",
        f"Error against run time ({name}, {width}x{height}): max abs error against the float64 reference "
        f"(raster.reference) on the {w}x{h} pixel window at ({x0}, {y0})"
        + (f", which took {ref['seconds']:.0f} s" if "seconds" in ref else "")
        + "; the largest difference anywhere in the image to the default; times on the full image. Each row "
        "changes one knob of the default (exact spans, no cap, no truncation, per-sample arithmetic in the "
        "colours' dtype (float32 here) with float64 scans, 400k candidate samples per band).",
        "",
        *knob_table(rows, per_process_memory=not quick),
    ]


# `dresg render` prints a line per view: "orbit_000.png: 448x320, 1,234,567 pairs, 0.21 s"
VIEW_LINE = re.compile(r": \d+x\d+, ([\d,]+) pairs, ([\d.]+) s$")


@contextmanager
def checkout(rev: str):
    """``rev`` of this repository in a temporary git worktree (removed afterwards)."""
    folder = Path(tempfile.mkdtemp(prefix="dresg-against-"))
    tree = folder / "tree"
    try:
        subprocess.run(
            ["git", "-C", str(REPO), "worktree", "add", "--detach", "--quiet", str(tree), rev],
            check=True,
            capture_output=True,
            text=True,
        )
        yield tree
    finally:
        if tree.exists():
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


def render_views(tree: Path, out: Path) -> tuple[list[float], list[int]]:
    """Seconds and pairs of each view of `dresg render` of the bonsai's orbit, run with ``tree``'s engine."""
    command = [sys.executable, "-m", "dresg_addon", "render", str(BONSAI), "--orbit", str(AB_VIEWS)]
    command += ["--width", str(FULL_SIZE[0]), "--height", str(FULL_SIZE[1]), "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(tree)}  # that tree's engine, whichever one is installed
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
        raise RuntimeError(f"dresg render with the engine of {tree} failed: {tail}")
    found = [m for m in map(VIEW_LINE.search, done.stdout.splitlines()) if m]
    return [float(m.group(2)) for m in found], [int(m.group(1).replace(",", "")) for m in found]


def wait_for_quiet(cores: float | None, monitor, max_wait_s: float = QUIET_WAIT_S) -> str:
    """Wait until other processes used at most ``cores`` cores over 2 s (at most ``max_wait_s``); what was seen."""
    if cores is None:
        return f"load {load_average()}"
    start = time.monotonic()
    monitor.others_busy(min_interval_s=0.0)  # a fresh window: the last one held our own previous run
    while True:
        time.sleep(ADAPT_INTERVAL_S)
        others = monitor.others_busy()
        if others is None or others <= cores or time.monotonic() - start > max_wait_s:
            break
    seen = "unknown" if others is None else f"{others:.2f}"
    return f"other processes {seen} cores, waited {time.monotonic() - start:.0f} s, load {load_average()}"


def against_section(rev: str, rounds: int, quiet: float | None = None) -> list[str]:
    """This checkout against ``rev``: the same renders alternating, A B B A ..., each after a quiet moment."""
    from dresg_addon.util.threads import CoreMonitor

    when = "" if quiet is None else f", each run once other processes used at most {quiet:g} cores over 2 s"
    lines = [
        "",
        f"A/B: `dresg render` of the bonsai, {AB_VIEWS} orbit views at {FULL_SIZE[0]}x{FULL_SIZE[1]}, this "
        f"checkout against {rev}, {rounds} alternating rounds{when}; seconds a view, median (best-worst) over "
        "every view",
        "",
    ]
    monitor = CoreMonitor()
    sides = {"this checkout": REPO, rev: None}
    times: dict[str, list[float]] = {name: [] for name in sides}
    pairs: dict[str, set[int]] = {name: set() for name in sides}
    runs: list[str] = []
    with checkout(rev) as tree, tempfile.TemporaryDirectory(prefix="dresg-against-out-") as out:
        sides[rev] = tree
        for round_ in range(rounds):
            for name in list(sides) if round_ % 2 == 0 else list(sides)[::-1]:
                before = wait_for_quiet(quiet, monitor)
                seconds, counts = render_views(sides[name], Path(out))
                times[name] += seconds
                pairs[name].add(sum(counts))
                line = f"round {round_ + 1}, {name}: median {statistics.median(seconds):.3f} s a view ({before})"
                runs.append(f"- {line}")
                print(f"  {line}", file=sys.stderr, flush=True)
    lines += ["| engine | s a view | views |", "|---|---:|---:|"]
    for name, values in times.items():
        lines.append(
            f"| {name} | {statistics.median(values):.3f} ({min(values):.3f}-{max(values):.3f}) | {len(values)} |"
        )
    this, other = (statistics.median(times[name]) for name in sides)
    lines.append(f"- this checkout / {rev}: {this / other:.2f}x")
    lines.append(f"- this checkout: target <= {TARGET_VIEW_S:g} s a view on 2 cores: {mark(this <= TARGET_VIEW_S)}")
    if len(set.union(*pairs.values())) > 1:
        lines.append(f"- the two draw different pairs ({pairs}): they do not render the same views")
    return lines + ["", "Runs, in order:", *runs]


LOADED_TARGET = 2.0  # slowdown against quiet with one core taken


def loaded_section(quiet_cases: dict, common: dict, repeats: int, bonsai: bool) -> list[str]:
    """The same case quiet and next to each of harness.LOADS: times and slowdowns."""
    name, spec = ("bonsai", {"scene": "bonsai"}) if bonsai else ("random 100k", {"scene": "random", "n": 100_000})
    quiet = quiet_cases.get("bonsai" if bonsai else "100k") or call_worker(
        {"kind": "case", "repeats": repeats, **spec, **common}
    )
    rows = [("quiet", quiet)]
    for kind in harness.LOADS:
        print(f"  running {name} next to a {kind} load ...", file=sys.stderr, flush=True)
        with harness.background_load(kind):
            rows.append((kind, call_worker({"kind": "case", "repeats": repeats, **spec, **common})))
    lines = [
        "",
        f"Under load: {name}, quiet and while one other process runs (started and stopped here): `python`, a",
        "pure-Python busy loop (one core taken); `torch`, another torch job doing small ops with torch's default",
        "threads, which spin between ops. Median of the timed runs; slowdown against quiet.",
        "",
        "| machine | forward | fwd+bwd with geometry | colour-only step | slowdown (fwd / fwd+bwd / colour) |",
        "|---|---:|---:|---:|---:|",
    ]
    keys = ("forward_s", "fwd_bwd_s", "colour_step_s")
    for label, result in rows:
        if "error" in result:
            lines.append(f"| {label} | {result['error']} | | | |")
            continue
        medians = [statistics.median(result[key]) for key in keys]
        base = [statistics.median(quiet[key]) for key in keys]
        slow = " / ".join(f"{m / b:.2f}x" for m, b in zip(medians, base))
        lines.append(f"| {label} | {medians[0]:.3f} s | {medians[1]:.3f} s | {1000 * medians[2]:.1f} ms | {slow} |")
    python = rows[1][1]
    if "error" not in python:
        worst = max(statistics.median(python[key]) / statistics.median(quiet[key]) for key in keys)
        lines.append(
            f"- one core taken: worst slowdown {worst:.2f}x, target <= {LOADED_TARGET:g}x: {mark(worst <= LOADED_TARGET)}"
        )
    lines.append(f"- load average after: {load_average()}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: 96x64, tiny scenes, one repeat, no bonsai")
    parser.add_argument("--markdown", metavar="FILE", help="also write the tables to FILE (markdown)")
    parser.add_argument(
        "--repeats", type=int, help="timed runs per measurement after the warm-ups (default 3, quick 1)"
    )
    parser.add_argument("--sizes", help="comma-separated random scene sizes (default 10000,100000,300000,1000000)")
    parser.add_argument("--no-knobs", action="store_true", help="skip the error-against-run-time table")
    parser.add_argument(
        "--threads", type=int, help="torch threads in every case (default: torch's own choice, the core count)"
    )
    parser.add_argument(
        "--loaded",
        action="store_true",
        help="also measure the bonsai (random 100k without it) while another process takes a core",
    )
    parser.add_argument(
        "--against",
        metavar="REV",
        help="only compare `dresg render` of the bonsai with this checkout's engine and REV's (a git commit), "
        "alternating",
    )
    parser.add_argument(
        "--quiet",
        type=float,
        metavar="CORES",
        help=f"with --against: before each run wait (at most {QUIET_WAIT_S:g} s) until other processes used at most "
        "CORES cores over 2 s",
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.worker:
        return harness.run_worker(args.worker, WORKERS)
    if args.against:
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # killed: the temporary worktree still goes
        if not BONSAI.is_file():
            print(f"error: --against renders the bonsai, and {BONSAI} is absent", file=sys.stderr)
            return 2
        try:
            section = against_section(args.against, max(1, args.repeats or 3), args.quiet)
        except (RuntimeError, subprocess.CalledProcessError) as error:
            print(f"error: {getattr(error, 'stderr', '') or error}".strip(), file=sys.stderr)
            return 2
        baseline = call_worker({"kind": "baseline", "width": FULL_SIZE[0], "height": FULL_SIZE[1]})
        out = ["## Rasterizer A/B", "", harness.machine_line(baseline, with_os=True), *section]
        out.append(f"- load average at the end: {load_average()}")
        print("\n".join(out))
        if args.markdown:
            Path(args.markdown).write_text("\n".join(out) + "\n", encoding="utf-8")
        return 0

    repeats = max(1, args.repeats or (1 if args.quick else 3))
    sizes = [int(s) for s in args.sizes.split(",")] if args.sizes else list(QUICK_SIZES if args.quick else FULL_SIZES)
    width, height = QUICK_SIZE if args.quick else FULL_SIZE
    have_bonsai = BONSAI.is_file() and BONSAI_HINT.is_file()
    started = time.perf_counter()

    common = {"width": width, "height": height, "threads": args.threads}  # every worker gets these
    baseline = call_worker({"kind": "baseline", **common})
    out = [f"## Rasterizer benchmark ({width}x{height}{', quick smoke run' if args.quick else ''})", ""]
    out += machine_lines(baseline)
    print("\n".join(out), flush=True)

    cases: list[tuple[str, dict]] = []
    for n in sizes:
        label = f"{n / 1e6:g}M" if n >= 1_000_000 else f"{n / 1e3:g}k"
        print(f"  running random {label} ...", file=sys.stderr, flush=True)
        cases.append((label, call_worker({"kind": "case", "scene": "random", "n": n, "repeats": repeats, **common})))
    if have_bonsai and not args.quick:
        print("  running bonsai ...", file=sys.stderr, flush=True)
        cases.append(("bonsai", call_worker({"kind": "case", "scene": "bonsai", "repeats": repeats, **common})))
    elif not args.quick:
        print(f"note: bonsai skipped ({BONSAI} or its camera hint is absent)", file=sys.stderr)
    table = [
        "",
        f"Random scenes: N Gaussians in view, sized for ~{PAIRS_PER_PIXEL:g} pairs per pixel before early "
        "termination; bonsai: bonsai-7k-mini.splat from its camera hint, 50 degree horizontal field of view.",
        "",
        *case_table([(label if label == "bonsai" else f"random {label}", r) for label, r in cases], width * height),
        *target_lines(dict(cases)),
    ]
    print("\n".join(table), flush=True)
    out += table

    if args.loaded:
        section = loaded_section(dict(cases), common, repeats, have_bonsai and not args.quick)
        print("\n".join(section), flush=True)
        out += section

    if not args.no_knobs:
        if have_bonsai and not args.quick:
            knob_case, name = {"scene": "bonsai", **common}, "bonsai"
        else:
            knob_case, name = {"scene": "random", "n": QUICK_KNOB_N, **common}, f"random {QUICK_KNOB_N:,}"
        section = knob_section(knob_case, name, repeats, args.quick)
        print("\n".join(section), flush=True)
        out += section

    footer = ["", f"Total {time.perf_counter() - started:.0f} s; load average at the end: {load_average()}."]
    print("\n".join(footer))
    out += footer
    if args.markdown:
        Path(args.markdown).write_text("\n".join(out) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
