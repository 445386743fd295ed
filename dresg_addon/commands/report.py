"""``python -m dresg_addon report [--scene PATH] [--styles IMG ...] [--out DIR] [--quick]``.

Measures the rasterizer's error against its float64 reference, the stylization's metrics against
wall time (presets and stage counts), the fit loss per stage and step, and the numerical-stability
cases, and writes ``report.md`` with PNG plots (see :mod:`dresg_addon.evaluation.report`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import add_size_options, check_size_options, orbit_size

NAME = "report"
HELP = (
    "Write a Markdown report with PNG plots: rasterizer error against time, stylization metrics against time "
    "(presets, stage counts), convergence of the fit loss, and the numerical-stability cases."
)


def _int_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers like 1,2,5,10, got {text!r}") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scene",
        metavar="PATH",
        help="scene file, or 'demo' for the built-in demo; when not given, the shared bonsai if present (not with "
        "--quick), else the demo",
    )
    parser.add_argument(
        "--styles",
        nargs="+",
        metavar="IMG",
        help="style images; when not given, two shared paintings (one with --quick), or the demo's",
    )
    parser.add_argument("--out", default="report", metavar="DIR", help="output folder")
    parser.add_argument(
        "--quick", action="store_true", help="shrink every budget (about a minute or two; numbers are indicative)"
    )
    add_size_options(parser, unset="quick 112x80, full 224x160")
    parser.add_argument("--views", type=int, metavar="N", help="orbit cameras (quick 4, full 8)")
    parser.add_argument("--presets", metavar="A,B", help="presets to run, comma-separated; all when not given")
    parser.add_argument(
        "--stage-counts",
        type=_int_list,
        metavar="1,2,5",
        help="stage counts of the default preset, early stop off (quick 1,2; full 1,2,4,6)",
    )
    parser.add_argument("--repeats", type=int, metavar="K", help="timing repeats per rasterizer knob (quick 1, full 3)")
    parser.add_argument("--no-stability", action="store_true", help="leave out the numerical-stability section")
    parser.add_argument("--seed", type=int, default=0, help="seed of the runs (and of the demo assets)")


def run(args: argparse.Namespace) -> int:
    check_size_options(args)
    width, height = args.width, args.height
    if (width is None) != (height is None):  # the report's sizes (112x80, 224x160) have the orbit aspect ratio
        width, height = orbit_size(args)
    from ..evaluation.report import ReportOptions, build_report

    presets = None if args.presets is None else tuple(p.strip() for p in args.presets.split(",") if p.strip())
    options = ReportOptions(
        out=Path(args.out),
        scene=args.scene,
        styles=tuple(args.styles or ()),
        quick=args.quick,
        width=width,
        height=height,
        views=args.views,
        presets=presets,
        stage_counts=args.stage_counts,
        repeats=args.repeats,
        stability=not args.no_stability,
        seed=args.seed,
    )
    path = build_report(options)
    print(f"wrote {path}")
    return 0
