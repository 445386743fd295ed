"""``python -m dresg_addon report [--scene PATH] [--styles IMG ...] [--cameras FILE] [--out DIR] [--quick]``.

On the user's scene, paintings and cameras (the built-in demo when none are given), measures the rasterizer's
error against its float64 reference, the stylization's metrics against wall time (presets and stage counts),
the fit loss per stage and step, and the numerical-stability cases
(:mod:`dresg_addon.evaluation.report_measure`), and writes ``report.md`` with PNG plots
(:mod:`dresg_addon.evaluation.report`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import add_size_options, add_up_option, check_size_options, orbit_size, parse_up

NAME = "report"
HELP = (
    "Write a Markdown report with PNG plots: rasterizer error against time, stylization metrics against time "
    "(presets, stage counts), convergence of the fit loss, and the numerical-stability cases, on your scene, "
    "paintings and cameras (the built-in demo scene and painting when not given)."
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
        help="the scene to stylize and measure (.ply, .splat or compressed .ply); default: the built-in demo scene",
    )
    parser.add_argument(
        "--styles",
        nargs="+",
        metavar="IMG",
        help="the paintings to stylize after, one run each (metrics averaged over them); default: the demo painting",
    )
    parser.add_argument(
        "--cameras",
        metavar="FILE",
        help="cameras in path order (cameras.json, a COLMAP model or LLFF poses_bounds.npy), at least 4: the 1st, "
        "3rd, ... to stylize from, the 2nd, 4th, ... held out as the novel views to measure on; default: an orbit "
        "ring to stylize from and the ring half a step further round to measure on",
    )
    add_up_option(parser)
    parser.add_argument("--out", default="report", metavar="DIR", help="output folder")
    parser.add_argument(
        "--quick", action="store_true", help="shrink every budget (about a minute or two; numbers are indicative)"
    )
    add_size_options(parser, unset="quick 112x80, full 224x160; a camera file keeps its aspect ratio")
    parser.add_argument(
        "--views", type=int, metavar="N", help="orbit cameras, and as many novel views (quick 4, full 8)"
    )
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
    if args.cameras is None and (width is None) != (height is None):  # the report's sizes have the orbit aspect
        width, height = orbit_size(args)
    from ..evaluation.report import build_report
    from ..evaluation.report_measure import ReportOptions

    presets = None if args.presets is None else tuple(p.strip() for p in args.presets.split(",") if p.strip())
    options = ReportOptions(
        out=Path(args.out),
        scene=args.scene,
        styles=tuple(args.styles or ()),
        cameras=args.cameras,
        up=parse_up(args.up),
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
