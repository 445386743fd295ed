"""``python -m dresg_addon demo --out DIR``: the embedded default, end to end, with nothing downloaded.

Makes the demo scene, cameras and style image, stylizes the scene, and writes the stylized PLY, the
per-stage log, before/after images of every camera, and ``before_after.png``: before | colour transfer |
after | style from four novel views (between the cameras the scene was stylized from), rendered at twice
the fit size and cropped to the fit size around the objects, so that the marks can be seen; the style
is shown at the same scale. The colour transfer column is the baseline a stylization must beat: the
paper's post stage alone, one covariance colour map from the base renders to the style
(:func:`~dresg_addon.method.color_transfer.transfer_scene_colors`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..method.config import PRESETS
from ._common import add_device_option, parse_device

NAME = "demo"
HELP = "Generate the built-in demo scene and style image, stylize it, and write before/after images."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="demo_out", metavar="DIR", help="output folder")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="preview", help="stylization preset")
    parser.add_argument("--views", type=int, default=8, help="number of demo cameras")
    parser.add_argument("--seed", type=int, default=0, help="seed of the demo assets and of the run")
    add_device_option(parser, use="where the before/after images are rendered")


def run(args) -> int:
    import numpy as np
    import torch

    from ..method.color_transfer import transfer_scene_colors
    from ..method.config import preset
    from ..method.loop import stylize
    from ..raster import render_scene
    from ..scene.camera_io import write_cameras_json
    from ..scene.demo import demo_cameras, demo_scene, demo_style_image
    from ..scene.io import write_scene
    from ..util.imageio import at_scale, object_window, write_image

    device = parse_device(args.device)
    out = Path(args.out)
    started = time.perf_counter()
    scene = demo_scene(args.seed)
    cameras = demo_cameras(scene, n=args.views)
    style = demo_style_image(seed=args.seed)
    write_scene(scene, out / "scene.ply")
    write_cameras_json(out / "cameras.json", cameras)
    write_image(out / "style.png", style)
    print(f"demo scene: {len(scene)} splats, {len(cameras)} cameras -> {out}", file=sys.stderr)
    config = preset(args.preset, seed=args.seed)

    def progress(p):
        if p.phase in ("fit", "post") and p.step == p.steps:
            label = "post" if p.phase == "post" else f"stage {p.stage}/{p.stages}"
            print(f"{label}: loss {p.loss:.4f}, {time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)

    result = stylize(
        scene,
        cameras,
        style,
        config,
        progress=args.threads.wrap(progress),
        log_path=out / "stylize.log.jsonl",
        messages=lambda m: print(m, file=sys.stderr),
    )
    write_scene(result.scene, out / "stylized.ply")
    settings = config.raster()

    def image(splats, camera):  # [H, W, 3] on the CPU
        return render_scene(splats, camera, settings, device=device).rgb.cpu()

    for camera in cameras:
        write_image(out / "views" / f"{camera.name}_before.png", image(scene, camera).numpy())
        write_image(out / "views" / f"{camera.name}_after.png", image(result.scene, camera).numpy())
    base = [render_scene(scene, camera, settings, device=device) for camera in cameras]
    transferred = transfer_scene_colors(
        scene,
        torch.stack([view.rgb.permute(2, 0, 1).cpu() for view in base]),
        torch.stack([view.alpha.cpu() for view in base]),
        torch.from_numpy(np.ascontiguousarray(style.transpose(2, 0, 1))),
    )
    rows = []
    for camera in demo_cameras(scene, n=args.views, azimuth_offset_deg=180.0 / args.views)[:4]:
        large = camera.resized(2 * camera.width, 2 * camera.height)
        columns = [image(s, large).numpy() for s in (scene, transferred, result.scene)]
        top, left = object_window(columns[0], camera.width, camera.height)
        crops = [c[top : top + camera.height, left : left + camera.width] for c in columns]
        rows.append(np.concatenate([*crops, at_scale(style, large.height, camera.width, camera.height)], 1))
    write_image(out / "before_after.png", np.concatenate(rows, 0))
    print(f"wrote {out / 'stylized.ply'} and {out / 'before_after.png'} in {time.perf_counter() - started:.0f} s")
    return 0
