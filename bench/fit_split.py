"""Where the fit loses a stage's proposals: the joint fit against each view's own, by the splat width under each pixel.

    .venv/bin/python -m dresg_addon stylize SCENE --orbit 16 --style IMG --out OUT.ply --save-views VIEWS
    .venv/bin/python bench/fit_split.py SCENE --orbit 16 --stage VIEWS/stage09 --check 3,8

For each view in ``--check`` and each band of splat width (``--edges``, pixels at the fit size), the RMSE over
the view's covered pixels of the joint bounded least-squares fit of every saved view's image (``--kind``: the
stage's proposals, or its gamma-amplified targets), and of the view fitted alone
(``color_solve.fit_split``). The view alone fits as well as its splats can: its error is what they cannot draw.
The joint error's excess over it is what the other views ask of the same splats. Pass the run's own scene and
camera options; the views are the cameras whose images the stage folder holds (the run's active views).
Geometry is the scene's (colour-only runs). The saved images are 8-bit PNGs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from dresg_addon.commands._common import add_scene_and_cameras, load_scene_and_cameras
from dresg_addon.util.errors import DresgError


def parse_numbers(text: str, kind, option: str) -> list:
    try:
        return [kind(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise SystemExit(f"fit_split: {option} {text!r}: expected comma-separated numbers") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scene_and_cameras(parser)
    parser.add_argument("--stage", required=True, metavar="DIR", help="a stage folder that --save-views wrote")
    parser.add_argument("--kind", choices=("proposal", "target"), default="proposal", help="which images to fit")
    parser.add_argument("--check", default="0", metavar="I,J", help="camera indices to report (default 0)")
    parser.add_argument("--edges", default="3,8", metavar="A,B", help="band edges in pixels (default 3,8)")
    args = parser.parse_args(argv)

    import torch

    from dresg_addon.method.bookkeeping import saved_view_path
    from dresg_addon.method.color_solve import fit_split
    from dresg_addon.method.fitting import SOLVE_MIN_WEIGHT, ViewRenderer, pixel_widths, seen_gaussians
    from dresg_addon.raster import RasterSettings
    from dresg_addon.scene.camera import view_name
    from dresg_addon.util.imageio import read_rgb

    stage = Path(args.stage)
    if not (stage.name.startswith("stage") and stage.name.removeprefix("stage").isdigit()):
        raise SystemExit(f"fit_split: --stage {stage}: expected a stageNN folder that --save-views wrote")
    stage_number = int(stage.name.removeprefix("stage"))
    check = parse_numbers(args.check, int, "--check")
    edges = parse_numbers(args.edges, float, "--edges")
    try:
        scene, cameras = load_scene_and_cameras(args)
        names = [view_name(camera, v) for v, camera in enumerate(cameras)]
        files = [saved_view_path(stage.parent, stage_number, name, args.kind) for name in names]
        active = [v for v, path in enumerate(files) if path.is_file()]
        if not active:
            raise SystemExit(f"fit_split: {stage}: no {args.kind} image of any of the {len(cameras)} cameras")
        missing = [v for v in check if v not in active]
        if missing:
            raise SystemExit(f"fit_split: {stage}: no {args.kind} image of camera(s) {missing}")
        chosen = [cameras[v] for v in active]
        targets = []
        for v, camera in zip(active, chosen):
            image = read_rgb(files[v])
            if image.shape[:2] != (camera.height, camera.width):
                raise SystemExit(
                    f"fit_split: {files[v]} is {image.shape[1]}x{image.shape[0]}, "
                    f"the camera {camera.width}x{camera.height}: pass the run's --width/--height"
                )
            targets.append(torch.from_numpy(image).permute(2, 0, 1).float())
    except DresgError as error:
        raise SystemExit(f"fit_split: {error}") from None

    started = time.perf_counter()
    seen, fast = seen_gaussians(scene, chosen, RasterSettings(), False)
    renderer = ViewRenderer(scene, chosen, seen, RasterSettings(), False, fast)
    views = renderer.linear_views(SOLVE_MIN_WEIGHT)
    widths = [width for width, _ in pixel_widths(renderer)]
    rows = fit_split(views, targets, widths, [active.index(v) for v in check], edges)
    print(f"{len(active)} views from {stage}, their {args.kind}s; {time.perf_counter() - started:.0f} s")
    print("| camera | pixels on splats | share | joint fit | view alone |")
    print("|---|---|---:|---:|---:|")
    for row in rows:
        camera = active[row.view]
        print(f"| {names[camera]} | {row.band} | {row.share:.2f} | {row.joint_rmse:.3f} | {row.single_rmse:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
