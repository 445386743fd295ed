"""``python -m dresg_addon select-views SCENE --cameras cameras.json``: the active views by coverage."""

from __future__ import annotations

import argparse
import json

from ._common import add_device_option, add_scene_and_cameras, load_scene_and_cameras, parse_device

NAME = "select-views"
HELP = "Choose active views by capped Gaussian coverage (Sec. 4.3) and print them with their coverage."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_and_cameras(parser)
    parser.add_argument("--max-views", type=int, default=0, help="cap on the number of views (0: none)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    add_device_option(parser, use="where the coverage renders run")


def run(args) -> int:
    from ..method.config import StylizeConfig
    from ..method.views import select_active_views
    from ..scene.camera import view_name

    device = parse_device(args.device)
    scene, cameras = load_scene_and_cameras(args)
    config = StylizeConfig(max_views=args.max_views)
    chosen = select_active_views(scene, cameras, config, progress=args.threads.wrap(None), device=device)
    names = [view_name(c, i) for i, c in enumerate(cameras)]
    if args.json:
        print(json.dumps({
            "views": [{"index": v, "name": names[v], "coverage_after": c, "own_coverage": chosen.per_view_coverage[v]} for v, c in zip(chosen.indices, chosen.coverage)],
            "stop_reason": chosen.reason,
            "blind": [names[v] for v in chosen.blind],
        }))  # fmt: skip
        return 0
    print(f"{'pick':>4}  {'index':>5}  {'camera':<24} {'own':>7}  {'total':>7}")
    for pick, (v, total) in enumerate(zip(chosen.indices, chosen.coverage), 1):
        print(f"{pick:>4}  {v:>5}  {names[v]:<24} {chosen.per_view_coverage[v]:>7.4f}  {total:>7.4f}")
    print(f"{len(chosen.indices)} of {len(cameras)} cameras; stopped: {chosen.reason}")
    if chosen.blind:
        print(f"cameras that see nothing: {', '.join(names[v] for v in chosen.blind)}")
    return 0
