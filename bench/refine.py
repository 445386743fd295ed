# SPDX-License-Identifier: GPL-3.0-or-later
"""How many splats the render-preserving split adds, how long it takes, and how much it changes the render.

    .venv/bin/python bench/refine.py [--scenes demo,bonsai,luigi,bonsai8] [--stroke-sigma 1.35] [--max-added-share 0.35]
        [--min-added 50000] [--views 16] [--width 448] [--height 320]

Cameras as bench/quality.py places them: ``--views`` orbit cameras (the fit views, the ones the split is
measured in) and as many novel ones half a step between them. Per scene: the splats split and added
(:func:`dresg_addon.method.refine.split_wide_splats`, its summary), the time, and the unstylized render's change,
split against unsplit, on the fit views and on the novel views: RMSE over the pixels either render covers
(alpha > 0.5), the largest change of any pixel and channel, the share of pixels changed by more than 0.05, and
the largest change of alpha. Not a test: it prints a table.
"""

from __future__ import annotations

import argparse
import sys
import time

import harness  # bench/, beside this script
from quality import DENSIFIED, SCENES

from dresg_addon.util.machine import load_average


def render_change(before, after) -> dict:
    """RMSE over the covered pixels, the largest change, the share changed by > 0.05, the largest alpha change."""
    rgb = (after.rgb.double() - before.rgb.double()).abs()
    covered = (before.alpha > 0.5) | (after.alpha > 0.5)
    worst = rgb.amax(-1)
    return {
        "rmse": float(rgb[covered].square().mean().sqrt()) if bool(covered.any()) else 0.0,
        "max": float(worst.max()),
        "over": float((worst > 0.05).double().mean()),
        "alpha": float((after.alpha.double() - before.alpha.double()).abs().max()),
    }


def measure(scene, split, cameras) -> dict:
    """Means of RMSE and share over the views, the largest max and alpha change."""
    from dresg_addon.raster import render_scene

    rows = [render_change(render_scene(scene, camera), render_scene(split, camera)) for camera in cameras]
    return {
        "rmse": sum(r["rmse"] for r in rows) / len(rows),
        "rmse_worst": max(r["rmse"] for r in rows),
        "max": max(r["max"] for r in rows),
        "over": sum(r["over"] for r in rows) / len(rows),
        "alpha": max(r["alpha"] for r in rows),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="demo,bonsai", help="comma-separated: demo, bonsai, luigi, bonsai8")
    parser.add_argument(
        "--stroke-sigma",
        type=float,
        default=1.35,
        help="children at most this wide, pixels of the views (standard: 0.3 x 4.5)",
    )
    parser.add_argument("--max-added-share", type=float, default=0.35, help="cap on splats added, share of the scene")
    parser.add_argument("--min-added", type=int, default=50_000, help="... but at least this many (standard's floor)")
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--width", type=int, default=448)
    parser.add_argument("--height", type=int, default=320)
    args = parser.parse_args(argv)

    from dresg_addon.method.refine import split_wide_splats
    from dresg_addon.scene.demo import demo_scene
    from dresg_addon.scene.io import read_scene
    from dresg_addon.scene.orbit import orbit_cameras

    print(f"load average before: {load_average()}; stroke sigma {args.stroke_sigma} px at {args.width}x{args.height}")
    print("| scene | splats | split | added | time | fit views RMSE / worst / max / >0.05 / alpha | novel views |")
    print("|---|---:|---:|---:|---:|---|---|")
    for name in [part for part in args.scenes.split(",") if part]:
        if name not in SCENES:
            raise SystemExit(f"refine: unknown scene {name!r} (known: {', '.join(SCENES)})")
        path, up = SCENES[name]
        if path is not None and not path.is_file():
            print(f"| {name} | absent: {path} |")
            continue
        scene = demo_scene() if path is None else read_scene(path)
        if name in DENSIFIED:
            scene = harness.densified(scene, DENSIFIED[name])
        size = {"width": args.width, "height": args.height, "up": up}
        fit_views = orbit_cameras(scene, args.views, **size)
        novel = orbit_cameras(scene, args.views, azimuth_offset_deg=180.0 / args.views, **size)
        started = time.perf_counter()
        result = split_wide_splats(
            scene, fit_views, args.stroke_sigma, max(int(args.max_added_share * len(scene)), args.min_added)
        )
        seconds = time.perf_counter() - started
        cells = []
        for cameras in (fit_views, novel):
            m = measure(scene, result.scene, cameras)
            cells.append(
                f"{m['rmse']:.4f} / {m['rmse_worst']:.4f} / {m['max']:.3f} / {m['over']:.4%} / {m['alpha']:.3f}"
            )
        share = result.added / len(scene)
        print(
            f"| {name} | {len(scene):,} | {result.split:,} | {result.added:,} ({share:.1%}) | {seconds:.1f} s "
            f"| {cells[0]} | {cells[1]} |"
        )
        print(f"  {name}: {result.summary}")
    print(f"load average after: {load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
