# SPDX-License-Identifier: GPL-3.0-or-later
"""Does Blender's soft-splat preview look like the splat scene? EEVEE against the engine's own render.

    .venv/bin/python bench/blender_preview.py [--scenes luigi,bonsai] [--width 448 --height 320]
        [--samples 1] [--view 1] [--figure docs/blender_preview.png] [--json out.json]

Not a test (tests/test_blender_preview.py runs a small case with the same function). For each scene: a
fresh empty Blender file (bpy module), Import Gaussian Splats with its defaults (soft splats in
renders) and the scene's axes, 8 orbit cameras from Add Orbit Cameras, an EEVEE render of one of them
(view transform Standard, film transparent, composited over black) and the engine's render of the same
camera, converted through the object's transform as Stylize does (``python -m dresg_addon render``'s
rasterizer, over black). Compared on the pixels the engine covers (alpha > 0.5): SSIM of luminance and
mean absolute colour error. Targets: SSIM >= 0.7, error <= 0.08.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
SHARED = REPO.parent / "shared" / "data" / "scenes"
SCENES = {  # name -> (file, axes)
    "luigi": ("luigi.ply", "Y_UP_TO_BLENDER"),
    "bonsai": ("bonsai-7k-mini.splat", "OPENCV_TO_BLENDER"),
}
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


def _load_addon():
    spec = importlib.util.spec_from_file_location("dresg_headless", REPO / "scripts" / "stylize_headless.py")
    headless = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(headless)
    return headless.load_addon()


def compare(
    path: str | Path, axes: str, *, width: int, height: int, samples: int, view: int = 0, orbit: int = 8
) -> dict:
    """EEVEE's render of the imported splats and the engine's render of the same camera, and how close."""
    import bpy
    import torch

    from dresg_addon.evaluation.metrics import ssim_per_image
    from dresg_addon.raster import RasterSettings, render_scene
    from dresg_addon.util.imageio import read_image

    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon = _load_addon()
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    assert bpy.ops.dresg.import_splats(filepath=str(path), axis_conversion=axes) == {"FINISHED"}
    obj = bpy.context.active_object
    bpy.ops.dresg.add_orbit_cameras(count=orbit, elevation=20.0)
    camera_object = addon.operators.views.scene_cameras(scene)[view]
    scene.camera = camera_object
    scene.render.engine = "BLENDER_EEVEE_NEXT" if "BLENDER_EEVEE_NEXT" in _engines() else "BLENDER_EEVEE"
    scene.eevee.taa_render_samples = samples
    scene.render.film_transparent = True
    scene.view_settings.view_transform = "Standard"
    scene.world = scene.world or bpy.data.worlds.new("World")
    with tempfile.TemporaryDirectory() as folder:
        scene.render.filepath = str(Path(folder) / "eevee.png")
        scene.render.image_settings.file_format = "PNG"
        scene.render.image_settings.color_mode = "RGBA"
        start = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        eevee_seconds = time.perf_counter() - start
        rgba = read_image(scene.render.filepath)
    eevee = rgba[..., :3] * rgba[..., 3:4]  # straight alpha over black

    camera = addon.operators.views.engine_cameras(scene, obj, [camera_object])[0]
    splats = addon.operators.splat_object.scene_from_object(obj)
    start = time.perf_counter()
    out = render_scene(splats, camera, RasterSettings(background=(0.0, 0.0, 0.0)))
    engine_seconds = time.perf_counter() - start
    engine = out.rgb.numpy()
    covered = out.alpha.numpy() > 0.5

    def luma(image):
        return torch.from_numpy(np.ascontiguousarray((image @ LUMA)[None].repeat(3, 0)))

    ssim = float(ssim_per_image(luma(eevee), luma(engine), torch.from_numpy(covered)))
    error = float(np.abs(eevee - engine)[covered].mean()) if covered.any() else float("nan")
    return {
        "scene": Path(path).name,
        "splats": len(splats),
        "size": [width, height],
        "samples": samples,
        "covered": float(covered.mean()),
        "ssim_luminance": ssim,
        "mean_colour_error": error,
        "eevee_seconds": eevee_seconds,
        "engine_seconds": engine_seconds,
        "eevee": eevee,
        "engine": engine,
    }


def _engines() -> set[str]:
    import bpy

    return {item.identifier for item in bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="luigi,bonsai")
    parser.add_argument("--width", type=int, default=448)
    parser.add_argument("--height", type=int, default=320)
    parser.add_argument("--samples", type=int, default=1, help="EEVEE render samples (blended splats need one)")
    parser.add_argument("--view", type=int, default=1, help="which of the 8 orbit cameras")
    parser.add_argument("--figure", help="write engine | EEVEE side by side, one row per scene")
    parser.add_argument("--json", help="write the numbers")
    args = parser.parse_args(argv)

    rows, results = [], []
    print("| scene | splats | EEVEE | engine | luminance SSIM (>= 0.7) | mean colour error (<= 0.08) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name in args.scenes.split(","):
        file, axes = SCENES[name]
        if not (SHARED / file).exists():
            print(f"| {name} | skipped: {SHARED / file} not present | | | | |")
            continue
        result = compare(
            SHARED / file, axes, width=args.width, height=args.height, samples=args.samples, view=args.view
        )
        print(
            f"| {name} | {result['splats']:,} | {result['eevee_seconds']:.1f} s | {result['engine_seconds']:.2f} s "
            f"| {result['ssim_luminance']:.3f} | {result['mean_colour_error']:.4f} |"
        )
        rows.append(np.concatenate([result.pop("engine"), np.ones((args.height, 4, 3)), result.pop("eevee")], 1))
        results.append(result)
    if args.figure and rows:
        from dresg_addon.util.imageio import write_image

        gap = np.ones((4, rows[0].shape[1], 3))
        write_image(args.figure, np.concatenate([part for row in rows for part in (row, gap)][:-1], 0))
        print(f"wrote {args.figure} (left: the engine's render, right: EEVEE)")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
