# SPDX-License-Identifier: GPL-3.0-or-later
"""Benchmark of the whole DReSG loop (issue 3, section 8). Not a test: it prints a table.

    .venv/bin/python bench/pipeline.py [--quick] [--markdown out.md] [--threads N] [--loaded]

The presets run with the default weight-free ``synth`` backend on the real bonsai (bonsai-7k-mini.splat,
273k Gaussians, ../shared/data) with 16 orbit cameras at 448x320 and Van Gogh's Starry Night as the
style. Each preset runs in a fresh subprocess, so its peak memory (``ru_maxrss``) is its own (it
includes the interpreter and torch). Times are split into view selection, setup (renderers, base
renders, features, first encodes), proposals (the latent updates), fitting (fit steps plus the
targets and feedback encodes between them) and the post stage.

- ``preview``, ``standard`` (the default) and ``cpu`` (the paper's schedule with colour-only fitting) run in
  full.
- ``paper`` optimises geometry offsets, so every fit step re-renders every active view: far too slow
  for a CPU run in full. One stage with the paper's per-stage work (10 updates, 30 fit steps) is run
  and timed, and the whole run is extrapolated: selection + setup + 20 x stage + the 50 post steps
  at the measured fit-step cost. Its peak memory is the one stage's (memory does not grow with stages).
- ``sd15``: seconds per latent update measured on a tiny random model of SD1.5's block layout at
  448x320, and the estimate for the real model from its measured pass costs on this CPU
  (``backends.SD15Costs``, ``estimate_cpu_seconds``).

Targets on a 2-core CPU: paper <= 10 min and <= 8 GB; preview <= 60 s; standard <= 5 min and <= 8 GB. ``--quick`` is a smoke run (a
twentieth of the bonsai, or the demo scene without shared data; 4 cameras at 112x80; tiny schedules):
its figures say nothing about the targets.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import harness  # bench/, beside this script

from dresg_addon.util.machine import load_average

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DRESG_SHARED_DATA", REPO.parent / "shared" / "data"))
BONSAI = SHARED / "scenes" / "bonsai-7k-mini.splat"
STYLE = SHARED / "styles" / "starry_night.jpg"

TARGET_PAPER_S = 600.0
TARGET_PAPER_GB = 8.0
TARGET_PREVIEW_S = 60.0
TARGET_STANDARD_S = 300.0
FULL = {"views": 16, "width": 448, "height": 320, "subsample": 1}
QUICK = {"views": 4, "width": 112, "height": 80, "subsample": 20}
# Quick runs keep each preset's character (geometry, render scale, view cap) with a tiny schedule.
QUICK_OVERRIDES = {
    "updates_per_stage": 2,
    "fit_steps": 3,
    "post_steps": 3,
    "proposal_width": 64,
    "proposal_height": 48,
}
SD15_SIZE = (448, 320)


# --- worker side (one subprocess per case): imports torch and the engine -----------------------------------


def load_inputs(spec: dict):
    """(scene, cameras, style, scene label) for a case."""
    from dresg_addon.scene.demo import demo_scene, demo_style_image
    from dresg_addon.scene.io import read_scene
    from dresg_addon.scene.orbit import orbit_cameras
    from dresg_addon.util.imageio import read_rgb

    if BONSAI.is_file():
        scene, label = read_scene(BONSAI), "bonsai-7k-mini"
    else:
        scene, label = demo_scene(), "demo scene"
    if spec["subsample"] > 1:
        scene = scene.subset(slice(None, None, spec["subsample"]))
        label += f" (every {spec['subsample']}th splat)"
    cameras = orbit_cameras(scene, spec["views"], width=spec["width"], height=spec["height"])
    style = read_rgb(STYLE) if STYLE.is_file() else demo_style_image()
    return scene, cameras, style, label


def run_preset(spec: dict) -> dict:
    """One stylize run of ``spec['preset']`` with ``spec['overrides']``, timed phase by phase."""
    from dresg_addon.method import views
    from dresg_addon.method.config import preset_run
    from dresg_addon.method.loop import stylize

    started = time.perf_counter()
    scene, cameras, style, label = load_inputs(spec)
    load_s = time.perf_counter() - started
    config, plan = preset_run(spec["preset"], **spec["overrides"])
    spent = {"selection": 0.0}
    marks: dict[str, float] = {}

    def timed(name, fn):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.perf_counter() - start

        return wrapper

    # stylize looks it up at call time, so the wrapper sees every call; proposal times come from the log.
    views.select_active_views = timed("selection", views.select_active_views)

    def progress(p):
        if p.phase == "proposal":
            marks.setdefault("first_proposal", time.perf_counter())

    run_start = time.perf_counter()
    result = stylize(scene, cameras, style, config, progress=harness.THREADS.wrap(progress), plan=plan)
    stages = [e for e in result.log if e["stage"] != "post"]
    post = [e for e in result.log if e["stage"] == "post"]
    stage_s = sum(e["stage_seconds"] for e in stages)
    spent["proposals"] = sum(e["proposal_seconds"] for e in stages)
    fit_steps = sum(len(e["fit_losses"]) for e in stages)
    return {
        "scene": label,
        "gaussians": len(scene),
        "optimised": stages[0]["gaussians_optimised"] if stages else 0,
        "views": len(result.selection.indices),
        "cameras": len(cameras),
        "stages": len(stages),
        "fit_steps": fit_steps,
        "load_s": load_s,
        "selection_s": spent["selection"],
        "setup_s": marks.get("first_proposal", run_start) - run_start - spent["selection"],
        "proposals_s": spent["proposals"],
        "fitting_s": stage_s - spent["proposals"],
        "fit_step_s": (stage_s - spent["proposals"]) / max(fit_steps, 1),
        "post_s": sum(e["stage_seconds"] for e in post),
        "total_s": result.seconds,
        "config": {**asdict(plan), **config.to_dict()},
        "peak_rss": harness.peak_rss_bytes(),
    }


def run_sd15(spec: dict) -> dict:
    """Seconds per latent update of a tiny random SD1.5-layout model, loaded from a folder like a real one."""
    import torch
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    from dresg_addon.method.proposal import EnergyTerms, optimize_proposal
    from dresg_addon.method.proposal.sd15 import SD15Backend
    from dresg_addon.method.proposal.sd15_configs import SD15_TEXT_ENCODER_CONFIG, SD15_UNET_CONFIG, SD15_VAE_CONFIG
    from dresg_addon.method.schedule import stage_timesteps

    torch.manual_seed(0)
    unet_config = {"block_out_channels": [8, 16, 32, 32], "norm_num_groups": 8, "attention_head_dim": 2}
    unet = UNet2DConditionModel.from_config({**SD15_UNET_CONFIG, **unet_config, "cross_attention_dim": 16})
    vae = AutoencoderKL.from_config(
        {**SD15_VAE_CONFIG, "block_out_channels": [8, 16, 16, 16], "norm_num_groups": 8, "layers_per_block": 1}
    )
    text = {"hidden_size": 16, "intermediate_size": 32, "num_hidden_layers": 2, "num_attention_heads": 2}
    text_encoder = CLIPTextModel(CLIPTextConfig(**{**SD15_TEXT_ENCODER_CONFIG, **text, "projection_dim": 16}))
    width, height = spec["width"], spec["height"]
    with tempfile.TemporaryDirectory() as folder:
        for name, model in (("unet", unet), ("vae", vae), ("text_encoder", text_encoder)):
            model.eval().save_pretrained(Path(folder) / name)
        backend = SD15Backend(folder, device="cpu", dtype=torch.float32)
    gen = torch.Generator().manual_seed(1)
    image = torch.rand(3, height, width, generator=gen)
    style = torch.rand(3, height, width, generator=gen)
    state = backend.encode(image)
    timesteps = stage_timesteps(20, 10)[10].timesteps[: spec["updates"]]
    optimize_proposal(backend, state, timesteps[:1], style, image, EnergyTerms())  # warm-up, fills caches
    start = time.perf_counter()
    optimize_proposal(backend, state, timesteps, style, image, EnergyTerms())
    return {"seconds_per_update": (time.perf_counter() - start) / len(timesteps), "peak_rss": harness.peak_rss_bytes()}


def run_baseline(spec: dict) -> dict:
    import torch

    import dresg_addon.method.loop  # noqa: F401

    return {"torch": torch.__version__, "threads": torch.get_num_threads(), "peak_rss": harness.peak_rss_bytes()}


WORKERS = {"preset": run_preset, "sd15": run_sd15, "baseline": run_baseline}


# --- driver side ------------------------------------------------------------------------------------------


def call_worker(spec: dict) -> dict:
    return harness.call_worker(__file__, spec)


def secs(value: float) -> str:
    return f"{value / 60:.1f} min" if value >= 120 else f"{value:.1f} s"


def gb(n_bytes: float) -> str:
    return f"{n_bytes / 1e9:.2f} GB"


def verdict(ok: bool) -> str:
    return "meets" if ok else "MISSES"


def machine_lines(baseline: dict) -> list[str]:
    return [
        harness.machine_line(baseline),
        f"- load average (1, 5, 15 min) at start: {load_average()} (a shared machine makes every figure slower)",
        f"- baseline resident memory (interpreter + torch + engine): {gb(baseline.get('peak_rss', 0))}, "
        "included in every peak below",
    ]


def paper_extrapolation(one: dict, stages: int, post_steps: int) -> float:
    """Whole-run seconds from one measured stage: selection + setup + stages x stage + post steps x fit step."""
    stage = one["proposals_s"] + one["fitting_s"]
    return one["selection_s"] + one["setup_s"] + stages * stage + post_steps * one["fit_step_s"]


def preset_table(rows: list[tuple[str, str, dict]]) -> list[str]:
    head = (
        "| preset | ran | views | Gaussians optimised | selection | setup | proposals | fitting | post "
        "| total | peak memory |"
    )
    out = [head, "|" + "---|" * 11]
    for name, ran, r in rows:
        if "error" in r:
            out.append(f"| {name} | {ran} | {r['error']} |" + " |" * 8)
            continue
        out.append(
            f"| {name} | {ran} | {r['views']} of {r['cameras']} | {r['optimised']:,} of {r['gaussians']:,} "
            f"| {secs(r['selection_s'])} | {secs(r['setup_s'])} | {secs(r['proposals_s'])} | {secs(r['fitting_s'])} "
            f"| {secs(r['post_s'])} | {secs(r['total_s'])} | {gb(r['peak_rss'])} |"
        )
    return out


LOADED_TARGET = 2.0  # slowdown against quiet with one core taken


def finish(out: list[str], lines: list[str], markdown: str | None) -> int:
    """Print the last lines, and write the whole report when ``--markdown`` asked for it."""
    print("\n".join(lines), flush=True)
    out += lines
    if markdown:
        Path(markdown).write_text("\n".join(out) + "\n", encoding="utf-8")
    return 0


def loaded_run(args) -> int:
    """``--loaded``: the preview preset quiet and next to each of harness.LOADS, and the slowdowns."""
    size = QUICK if args.quick else FULL
    common = {**size, "threads": args.threads}
    overrides = {**QUICK_OVERRIDES, "stages": 1} if args.quick else {}
    started = time.perf_counter()
    baseline = call_worker({"kind": "baseline", **common})
    out = ["## Pipeline benchmark under load", "", *machine_lines(baseline), ""]
    print("\n".join(out), flush=True)
    rows = []
    for kind in ("quiet", *harness.LOADS):
        print(f"  running preview ({kind}) ...", file=sys.stderr, flush=True)
        spec = {"kind": "preset", "preset": "preview", "overrides": overrides, **common}
        if kind == "quiet":
            rows.append((kind, call_worker(spec)))
        else:
            with harness.background_load(kind):
                rows.append((kind, call_worker(spec)))
    quiet = rows[0][1]
    lines = [
        "The `preview` preset on the same scene, quiet and while one other process runs (started and stopped by",
        "the benchmark): `python`, a pure-Python busy loop (one core taken); `torch`, another torch job doing",
        "small ops with torch's default threads, which spin between ops.",
        "",
        "| machine | proposals | fitting | total | slowdown |",
        "|---|---:|---:|---:|---:|",
    ]
    for kind, result in rows:
        if "error" in result or "error" in quiet:
            lines.append(f"| {kind} | {result.get('error', quiet.get('error'))} | | | |")
            continue
        slowdown = result["total_s"] / quiet["total_s"]
        lines.append(
            f"| {kind} | {secs(result['proposals_s'])} | {secs(result['fitting_s'])} | {secs(result['total_s'])} "
            f"| {slowdown:.2f}x |"
        )
    if "error" not in rows[1][1] and "error" not in quiet:
        slowdown = rows[1][1]["total_s"] / quiet["total_s"]
        lines.append(
            f"- one core taken: {slowdown:.2f}x, target <= {LOADED_TARGET:g}x: {verdict(slowdown <= LOADED_TARGET)}"
        )
    lines += ["", f"Benchmark wall time: {secs(time.perf_counter() - started)}; load average after: {load_average()}."]
    return finish(out, lines, args.markdown)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: small scene, 4 small cameras, tiny schedules")
    parser.add_argument("--markdown", metavar="FILE", help="also write the report to FILE (markdown)")
    parser.add_argument("--threads", type=int, help="torch threads in every case (default: torch's own choice)")
    parser.add_argument("--no-sd15", action="store_true", help="skip the sd15 timing")
    parser.add_argument(
        "--loaded",
        action="store_true",
        help="instead: preview quiet, then while another process takes a core, then next to another torch job",
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.worker:
        return harness.run_worker(args.worker, WORKERS)
    if args.loaded:
        return loaded_run(args)

    from dresg_addon.method.config import preset_run

    size = QUICK if args.quick else FULL
    common = {**size, "threads": args.threads}
    quick = QUICK_OVERRIDES if args.quick else {}
    started = time.perf_counter()
    baseline = call_worker({"kind": "baseline", **common})
    title = "## Pipeline benchmark" + (" (quick smoke run: says nothing about the targets)" if args.quick else "")
    out = [title, "", *machine_lines(baseline)]
    if not BONSAI.is_file():
        out.append(f"- {BONSAI} is absent: the demo scene stands in for the bonsai")
    print("\n".join(out), flush=True)

    runs = []
    for name, overrides, ran in (
        ("preview", {**quick, "stages": 1} if args.quick else {}, "full run"),
        ("cpu", {**quick, "stages": 2} if args.quick else {}, "full run"),
        ("standard", {**quick, "stages": 2} if args.quick else {}, "full run"),
    ):
        print(f"  running {name} ...", file=sys.stderr, flush=True)
        runs.append((name, ran, call_worker({"kind": "preset", "preset": name, "overrides": overrides, **common})))
    paper, paper_plan = preset_run("paper", **quick, stages=3) if args.quick else preset_run("paper")
    print("  running one stage of paper ...", file=sys.stderr, flush=True)
    one_stage = {**quick, "stages": 1, "post_steps": 0}
    paper_one = call_worker({"kind": "preset", "preset": "paper", "overrides": one_stage, **common})
    runs.append(("paper", "1 stage (measured)", paper_one))

    r = runs[0][2]
    lines = [
        "",
        f"Scene: {r.get('scene', '?')}, {size['views']} orbit cameras at {size['width']}x{size['height']}, style: "
        f"{STYLE.name if STYLE.is_file() else 'the demo painting'}, proposal backend: synth.",
        "",
        *preset_table(runs),
        "",
    ]
    if "error" not in paper_one:
        estimate = paper_extrapolation(paper_one, paper.stages, paper_plan.post_steps)
        lines.append(
            f"- paper, extrapolated from its one measured stage to {paper.stages} stages + {paper_plan.post_steps} post "
            f"steps: about {secs(estimate)} (selection + setup + {paper.stages} x "
            f"{secs(paper_one['proposals_s'] + paper_one['fitting_s'])} per stage + {paper_plan.post_steps} x "
            f"{paper_one['fit_step_s']:.2f} s per fit step); peak memory {gb(paper_one['peak_rss'])}"
        )
        if not args.quick:
            lines.append(
                f"  - target <= {TARGET_PAPER_S / 60:.0f} min: {verdict(estimate <= TARGET_PAPER_S)}; "
                f"<= {TARGET_PAPER_GB:.0f} GB: {verdict(paper_one['peak_rss'] <= TARGET_PAPER_GB * 1e9)}"
            )
    cpu_run, preview_run = runs[1][2], runs[0][2]
    if not args.quick:
        if "error" not in preview_run:
            ok = preview_run["total_s"] <= TARGET_PREVIEW_S
            lines.append(f"- preview: {secs(preview_run['total_s'])}, target <= 60 s: {verdict(ok)}")
        standard_run = runs[2][2]
        if "error" not in standard_run:
            ok = standard_run["total_s"] <= TARGET_STANDARD_S and standard_run["peak_rss"] <= TARGET_PAPER_GB * 1e9
            lines.append(
                f"- standard (the default): {secs(standard_run['total_s'])}, {gb(standard_run['peak_rss'])}; "
                f"target <= 5 min and <= 8 GB: {verdict(ok)}"
            )
        if "error" not in cpu_run:
            ok = cpu_run["total_s"] <= TARGET_PAPER_S and cpu_run["peak_rss"] <= TARGET_PAPER_GB * 1e9
            lines.append(
                f"- cpu (the paper's schedule, colour-only fitting): {secs(cpu_run['total_s'])}, "
                f"{gb(cpu_run['peak_rss'])}; against the paper's 10 min / 8 GB target: {verdict(ok)}"
            )

    if not args.no_sd15:
        lines += ["", *sd15_lines(args, common, cpu_run)]
    lines += ["", f"Benchmark wall time: {secs(time.perf_counter() - started)}."]
    return finish(out, lines, args.markdown)


def sd15_lines(args, common: dict, cpu_run: dict) -> list[str]:
    from dresg_addon.method.backends import SD15Costs, estimate_cpu_seconds
    from dresg_addon.method.config import PRESETS

    if importlib.util.find_spec("diffusers") is None:
        return ["sd15: skipped (diffusers is not installed)"]
    print("  timing sd15 on a tiny model ...", file=sys.stderr, flush=True)
    width, height = (64, 48) if args.quick else SD15_SIZE
    tiny = call_worker({"kind": "sd15", **common, "width": width, "height": height, "updates": 2 if args.quick else 10})
    paper = PRESETS["paper"]
    views = cpu_run.get("views", 16) if "error" not in cpu_run else 16
    estimate = estimate_cpu_seconds(views, paper.stages, paper.plan().updates_per_stage, *SD15_SIZE)
    measured = "failed: " + tiny["error"] if "error" in tiny else f"{tiny['seconds_per_update']:.2f} s"
    return [
        f"sd15 (paper schedule, {SD15_SIZE[0]}x{SD15_SIZE[1]}, fp32 on this CPU):",
        f"- measured on a tiny random model of SD1.5's layout at {width}x{height}: {measured} per latent update "
        "(the loop, hooks and Adam; the real U-Net has ~1500x its parameters)",
        f"- real SD1.5, from its pass costs on a 2-core CPU (SD15Costs): {SD15Costs().seconds_per_update:.1f} s "
        f"per latent update; the proposals of a whole run with {views} views take about "
        f"{estimate / 3600:.1f} h (estimate_cpu_seconds; fitting comes on top). On a GPU in bf16 it is minutes.",
    ]


if __name__ == "__main__":
    sys.exit(main())
