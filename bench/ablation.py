# SPDX-License-Identifier: GPL-3.0-or-later
"""The paper's ablations on scene-style pairs, as paper-style Markdown tables. Not a test.

    .venv/bin/python bench/ablation.py [--quick] [--scene PATH | --scene demo] [--styles A.jpg B.jpg]
        [--width 224 --height 160 --views 8] [--stages N --updates S --fit-steps M --post-steps P
        --proposal-size WxH --max-views V] [--variants full,no-qc,...] [--markdown OUT.md] [--json OUT.json]

Variants (each changes one setting of the base configuration, the preview preset unless flags say
otherwise): the full method; w/o Q_c (the content term: the content query of the attention energy, the
content fusion of the synth backend); w/o K_s, w/o V_s (attention backends only: the synth backend has
no attention energy, so they are left out for it); w/o feedback
(the latent is not re-encoded from the fitted render); w/o colour-gradient projection (view
gradients averaged instead of PCGrad); image-space scaling (the residual target of Eq. 12 in image
space instead of RGB logits); and the residual-strength schedules fixed-1, fixed-2, triangle and
timestep-cosine against the SNR-balanced default.

Pairs: the shared bonsai (orbit cameras) with two shared paintings when ../shared/data is present
(``bench/report.py``'s defaults), else the built-in demo scene and painting. Metrics
(``dresg_addon.evaluation.views.evaluate_views``, as in ``dresg evaluate`` and ``bench/quality.py``) on the novel
views between the orbit cameras (covered pixels), averaged over the pairs: sliced
Wasserstein distances of colours and 7x7 patches to the style (lower is better), SSIM and gradient
structure to the base render (higher is better), masked RMSE of the exact warp for gap 1 and N/2
(lower is better), and the stylization's wall time. ``--quick`` shrinks the base configuration like
``report --quick`` (2 stages of 2 updates, 3 fit and post steps, 2 views, 112x80 proposals).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# (key, row label, table, Plan changes: the ablation flags and the residual curve)
VARIANTS = (
    ("full", "DReSG (full)", "both", {}),
    ("no-qc", "w/o Q_c", "components", {"use_content_query": False}),
    ("no-ks", "w/o K_s", "components", {"use_style_keys": False}),  # attention backends only
    ("no-vs", "w/o V_s", "components", {"use_style_values": False}),  # attention backends only
    ("no-feedback", "w/o feedback", "components", {"feedback": False}),
    ("no-pcgrad", "w/o colour-gradient projection", "components", {"pcgrad": False}),
    ("image-space", "image-space scaling", "components", {"logit_space": False}),
    ("fixed-1", "fixed gamma = 1", "schedules", {"schedule": "fixed-1"}),
    ("fixed-2", "fixed gamma = 2", "schedules", {"schedule": "fixed-2"}),
    ("triangle", "triangle", "schedules", {"schedule": "triangle"}),
    ("timestep-cosine", "timestep cosine", "schedules", {"schedule": "timestep-cosine"}),
)
METRICS = (
    ("sw_colors", "SW colour ↓", 4),
    ("sw_patches", "SW patch ↓", 4),
    ("ssim", "SSIM ↑", 3),
    ("structure", "GS ↑", 3),
    ("short_rmse", "short RMSE ↓", 4),
    ("long_rmse", "long RMSE ↓", 4),
)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="shrink the base configuration (a smoke run)")
    parser.add_argument("--scene", metavar="PATH", help="scene file or 'demo' (default: the shared bonsai, else demo)")
    parser.add_argument("--styles", nargs="+", metavar="IMG", help="style images (default: two shared paintings)")
    parser.add_argument("--width", type=int, default=224, help="orbit camera width")
    parser.add_argument("--height", type=int, default=160, help="orbit camera height")
    parser.add_argument("--views", type=int, default=8, help="orbit cameras (evaluation path and candidates)")
    parser.add_argument("--stages", type=int, help="feedback stages")
    parser.add_argument("--updates", type=int, help="latent updates per stage")
    parser.add_argument("--fit-steps", type=int, help="fit steps per stage")
    parser.add_argument("--post-steps", type=int, help="fit steps of the post stage")
    parser.add_argument("--proposal-size", metavar="WxH", help="proposal resolution")
    parser.add_argument("--max-views", type=int, help="cap on active views")
    parser.add_argument("--proposal", help="proposal backend (default: the preset's, synth)")
    parser.add_argument("--model", metavar="PATH", help="local SD1.5 model (sd15)")
    parser.add_argument("--variants", metavar="A,B", help=f"subset of: {', '.join(v[0] for v in VARIANTS)}")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", metavar="OUT.md", help="also write the tables to this file")
    parser.add_argument("--json", metavar="OUT.json", help="also write every measured value to this file")
    return parser.parse_args(argv)


def base_config(args):
    """(config, plan) of the variants' base: the preview preset, shrunk by --quick and changed by the flags."""
    from dresg_addon.evaluation.report_measure import quick_config
    from dresg_addon.method.config import preset
    from dresg_addon.util.errors import ConfigError

    config = preset("preview", seed=args.seed)
    plan = config.plan()
    if args.quick:
        config, plan = quick_config(config, plan)
    changes = {"stages": args.stages, "max_views": args.max_views, "proposal": args.proposal, "model_path": args.model}
    if args.proposal_size:
        try:
            width, height = (int(v) for v in args.proposal_size.lower().split("x"))
        except ValueError:
            raise ConfigError(f"--proposal-size must look like 224x160, got {args.proposal_size!r}") from None
        changes.update(proposal_width=width, proposal_height=height)
    steps = {"updates_per_stage": args.updates, "fit_steps": args.fit_steps, "post_steps": args.post_steps}
    config = config.with_(**{k: v for k, v in changes.items() if v is not None})
    return config, plan.with_(**{k: v for k, v in steps.items() if v is not None})


ATTENTION_ONLY = ("no-ks", "no-vs")


def chosen_variants(args, proposal: str):
    from dresg_addon.method.backends import BACKENDS

    attention = BACKENDS[proposal].has_attention
    if not args.variants:
        return [v for v in VARIANTS if attention or v[0] not in ATTENTION_ONLY]
    keys = [k.strip() for k in args.variants.split(",") if k.strip()]
    known = {v[0]: v for v in VARIANTS}
    unknown = [k for k in keys if k not in known]
    if unknown:
        raise SystemExit(f"unknown variant(s) {', '.join(unknown)}; choose from {', '.join(known)}")
    if not attention and set(keys) & set(ATTENTION_ONLY):
        raise SystemExit(f"w/o K_s and w/o V_s change the attention energy, which the {proposal} backend has not")
    return [known[k] for k in keys]


def run(args) -> dict:
    from report import shared_defaults  # bench/, beside this script

    from dresg_addon.evaluation.report_measure import (
        ReportOptions,
        load_inputs,
        machine_description,
        stylize_with_log,
    )
    from dresg_addon.evaluation.views import base_views, evaluate_views

    machine = machine_description()
    config, plan = base_config(args)
    defaults = shared_defaults(args.scene, args.styles, quick=False)
    options = ReportOptions(width=args.width, height=args.height, views=args.views, **defaults).resolved()
    inputs = load_inputs(options)
    variants = chosen_variants(args, config.proposal)
    print(f"{inputs.scene_label}; styles: {', '.join(n for n, _ in inputs.styles)}", file=sys.stderr)
    results = {key: [] for key, *_ in variants}
    started = time.perf_counter()
    base = base_views(inputs.scene, inputs.eval_cameras)
    for style_name, style in inputs.styles:
        for key, label, _, changes in variants:
            variant = plan.with_(**changes)
            with tempfile.TemporaryDirectory() as work:
                log = Path(work) / "log.jsonl"
                result, _, _ = stylize_with_log(inputs.scene, inputs.cameras, style, config, log, variant)
            measured = {
                "style": style_name,
                "seconds": result.seconds,
                **evaluate_views(result.scene, base, style, stroke_size=config.stroke_size).mean,
            }
            results[key].append(measured)
            print(
                f"  {style_name} / {label}: {result.seconds:.1f} s, SW colour {measured['sw_colors']:.4f}, "
                f"SSIM {measured['ssim']:.3f}",
                file=sys.stderr,
                flush=True,
            )
    return {
        "machine": machine,
        "scene": inputs.scene_label,
        "styles": [n for n, _ in inputs.styles],
        "cameras": f"{len(inputs.cameras)} orbit views at {options.width}x{options.height} (metrics on the "
        f"{len(inputs.eval_cameras)} novel views between them)",
        "config": {**asdict(plan), **config.to_dict()},
        "variants": [(key, label, table) for key, label, table, _ in variants],
        "results": results,
        "seconds": time.perf_counter() - started,
    }


def _mean(rows, key):
    values = [r[key] for r in rows if r.get(key) is not None]
    return statistics.mean(values) if values else None


def _cell(value, digits):
    return "-" if value is None else f"{value:.{digits}f}"


def table(report: dict, which: str, title: str) -> list[str]:
    rows = [(k, label) for k, label, t in report["variants"] if t in (which, "both")]
    if len(rows) < 2:
        return []
    head = "| " + title + " | " + " | ".join(name for _, name, _ in METRICS) + " | time (s) |"
    lines = [head, "|---|" + "---:|" * (len(METRICS) + 1)]
    for key, label in rows:
        if which == "schedules" and key == "full":
            label = "SNR-balanced (DReSG)"
        measured = report["results"][key]
        cells = [_cell(_mean(measured, m), digits) for m, _, digits in METRICS]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {_cell(_mean(measured, 'seconds'), 1)} |")
    return lines + [""]


def markdown(report: dict) -> str:
    c = report["config"]
    lines = [
        f"Ablations on {report['scene']} with {', '.join(report['styles'])} ({len(report['styles'])} pairs), "
        f"{report['cameras']}; base configuration: {c['stages']} stages x {c['updates_per_stage']} updates, "
        f"{c['fit_steps']} fit / {c['post_steps']} post steps, proposals {c['proposal_width']}x"
        f"{c['proposal_height']}, {c['proposal']} proposal backend, geometry {'on' if c['optimize_geometry'] else 'off'}, "
        f"at most {c['max_views'] or 'all'} active views. Means over the pairs; "
        f"time is the stylization's wall time. Machine: {report['machine']}.",
        "",
    ]
    lines += table(report, "components", "variant")
    lines += table(report, "schedules", "residual schedule (gamma)")
    lines.append(f"Total {report['seconds']:.0f} s.")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    report = run(args)
    text = markdown(report)
    print(text)
    from dresg_addon.util.fileutil import atomic_write_bytes

    if args.markdown:
        atomic_write_bytes(args.markdown, (text + "\n").encode("utf-8"))
    if args.json:
        atomic_write_bytes(args.json, (json.dumps(report, indent=2) + "\n").encode("utf-8"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
