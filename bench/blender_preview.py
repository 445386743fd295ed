# SPDX-License-Identifier: GPL-3.0-or-later
"""Does Blender's F12 look like the splat scene? EEVEE's and Workbench's renders against the engine's own.

    .venv/bin/python bench/blender_preview.py [--scenes luigi,bonsai-tree,thin] [--engines eevee,workbench]
        [--low-pass on|off|both] [--width 448 --height 320] [--samples 1] [--view 1]
        [--figure docs/blender_preview.png] [--json out.json]

Not a test (tests/test_blender_preview.py runs small cases with the same function). For each scene: a
fresh empty Blender file (bpy module), Import Gaussian Splats with its defaults (soft splats in
renders, Show Splat Colours) and the scene's axes, 8 orbit cameras from Add Orbit Cameras, an F12
render of one of them (view transform Standard, film transparent, composited over black) and the
engine's render of the same camera, converted through the object's transform as Stylize does
(``dresg render``'s rasterizer, over black). Compared on the pixels the engine covers (alpha > 0.5):
SSIM of luminance and mean absolute colour error. Targets: EEVEE SSIM >= 0.7 and error <= 0.08 on the
captures, SSIM >= 0.75 and error <= 0.06 on ``thin`` (issue 18); Workbench error <= 0.1. ``thin`` is
generated here: 6,000 sprinkles (splats 20 x 1 x 1 of their own widths, under a pixel wide) on a torus;
``bonsai-tree`` is the bonsai's tree and pot (:func:`crop_ply`), because an EEVEE frame of the whole bonsai
takes over 50 minutes on software OpenGL. ``--low-pass off`` (or ``both``) also renders EEVEE without the
render-time low-pass, as the viewport draws. Measured numbers: README, "Measured performance".
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from harness import load_addon

from dresg_addon.util.machine import cpu_model, load_average, usable_cores

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DRESG_SHARED_DATA", REPO.parent / "shared" / "data")) / "scenes"
SCENES = {  # name -> (file, axes); "thin" is written by thin_splats_ply, "bonsai-tree" by crop_ply
    "luigi": ("luigi.ply", "Y_UP_TO_BLENDER"),
    "bonsai": ("bonsai-7k-mini.splat", "OPENCV_TO_BLENDER"),
    "bonsai-tree": ("bonsai-7k-mini.splat", "OPENCV_TO_BLENDER"),
    "thin": ("", "NONE"),
}
TREE = (-0.256, -0.15, 0.229)  # the bonsai tree in the capture's coordinates (between trunk and canopy)
TREE_SPLATS = 40_000
ENGINES = {"eevee": "EEVEE", "workbench": "WORKBENCH"}
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


def thin_splats_ply(path: str | Path, n: int = 6000, seed: int = 0) -> Path:
    """Sprinkles on a donut: n elongated splats (0.06 long, 0.003 wide, under a pixel across at 448x320 from
    the orbit cameras) on a torus of radii 1 and 0.4 in the XY plane, z up, bright random colours, opaque."""
    from dresg_addon.scene.gaussians import SH_C0, GaussianScene
    from dresg_addon.scene.io import write_scene

    rng = np.random.default_rng(seed)
    around, tube = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n)
    ring = 1.0 + 0.4 * np.cos(tube)
    means = np.stack([ring * np.cos(around), ring * np.sin(around), 0.4 * np.sin(tube)], 1)
    half = rng.uniform(0, np.pi, n) / 2  # each sprinkle turned about z by a random angle: w, x, y, z
    quats = np.stack([np.cos(half), np.zeros(n), np.zeros(n), np.sin(half)], 1)
    colors = rng.choice(np.float32([[0.9, 0.2, 0.3], [0.2, 0.7, 0.9], [0.95, 0.85, 0.2], [0.3, 0.8, 0.3]]), n)
    scene = GaussianScene(
        means=means.astype(np.float32),
        log_scales=np.log(np.tile(np.float32([0.03, 0.0015, 0.0015]), (n, 1))),
        quats=quats.astype(np.float32),
        opacity_logits=np.full(n, 3.0, np.float32),
        sh_dc=((colors - 0.5) / SH_C0).astype(np.float32),
    )
    write_scene(scene, path)
    return Path(path)


def crop_ply(source: str | Path, path: str | Path, centre=TREE, n: int = TREE_SPLATS) -> Path:
    """The ``n`` splats of ``source`` nearest ``centre``, at the capture's own density: by default the bonsai's tree
    and pot. An EEVEE frame costs about the same per splat at any size here (software OpenGL): the whole bonsai
    ran over 50 minutes, so the bench compares this crop."""
    from dresg_addon.scene.io import read_scene, write_scene

    scene = read_scene(source)
    distance = np.linalg.norm(scene.means - np.asarray(centre, np.float32), axis=1)
    write_scene(scene.subset(np.sort(np.argsort(distance)[:n])), path)
    return Path(path)


@contextlib.contextmanager
def without_render_setup(addon):
    """Renders inside go without the add-on's render handlers: EEVEE without the render-time low-pass, as the
    viewport draws (the modifier's pixel inputs are 0 between renders)."""
    addon.operators.render_setup.unregister()
    try:
        yield
    finally:
        addon.operators.render_setup.register()


def luminance_ssim(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """SSIM of the luminance of two [H, W, 3] images over ``mask`` [H, W]."""
    import torch

    from dresg_addon.evaluation.metrics import ssim_per_image

    def luma(x):
        return torch.from_numpy(np.ascontiguousarray((x @ LUMA)[None].repeat(3, 0)))

    return float(ssim_per_image(luma(image), luma(reference), torch.from_numpy(mask)))


def case_label(engine_name: str, low_pass: bool) -> str:
    return engine_name if engine_name != "EEVEE" or low_pass else "EEVEE without the low-pass"


def compare(
    path: str | Path,
    axes: str,
    *,
    width: int,
    height: int,
    samples: int = 1,
    view: int = 0,
    orbit: int = 8,
    engine_name: str = "EEVEE",
    low_pass: bool = True,
) -> dict:
    """An F12 render (``engine_name``: EEVEE or WORKBENCH) of the imported splats and the engine's render of the same
    camera, and how close. ``low_pass=False`` renders EEVEE without the render-time low-pass (to measure what it
    changes)."""
    import bpy

    from dresg_addon.raster import RasterSettings, render_scene
    from dresg_addon.util.imageio import read_image

    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon = load_addon()
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    assert bpy.ops.dresg.import_splats(filepath=str(path), axis_conversion=axes) == {"FINISHED"}
    obj = bpy.context.active_object
    bpy.ops.dresg.add_orbit_cameras(count=orbit, elevation=20.0)
    camera_object = addon.operators.views.scene_cameras(scene)[view]
    scene.camera = camera_object
    if engine_name == "WORKBENCH":  # shading as the import's Show Splat Colours left it
        scene.render.engine = "BLENDER_WORKBENCH"
    else:
        scene.render.engine = eevee_engine()
        scene.eevee.taa_render_samples = samples
    scene.render.film_transparent = True
    scene.view_settings.view_transform = "Standard"
    scene.world = scene.world or bpy.data.worlds.new("World")
    with tempfile.TemporaryDirectory() as folder:
        scene.render.filepath = str(Path(folder) / "render.png")
        scene.render.image_settings.file_format = "PNG"
        scene.render.image_settings.color_mode = "RGBA"
        with contextlib.nullcontext() if low_pass else without_render_setup(addon):
            start = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            blender_seconds = time.perf_counter() - start
        rgba = read_image(scene.render.filepath)
    blender = rgba[..., :3] * rgba[..., 3:4]  # straight alpha over black

    camera = addon.operators.views.engine_cameras(scene, obj, [camera_object])[0]
    splats = addon.operators.splat_object.scene_from_object(obj)
    start = time.perf_counter()
    out = render_scene(splats, camera, RasterSettings(background=(0.0, 0.0, 0.0)))
    engine_seconds = time.perf_counter() - start
    engine = out.rgb.numpy()
    covered = out.alpha.numpy() > 0.5

    ssim = luminance_ssim(blender, engine, covered)
    error = float(np.abs(blender - engine)[covered].mean()) if covered.any() else float("nan")
    return {
        "scene": Path(path).name,
        "blender_engine": engine_name,
        "splats": len(splats),
        "size": [width, height],
        "samples": samples,
        "low_pass": low_pass,
        "covered": float(covered.mean()),
        "ssim_luminance": ssim,
        "mean_colour_error": error,
        "blender_seconds": blender_seconds,
        "engine_seconds": engine_seconds,
        "blender": blender,
        "engine": engine,
    }


def eevee_engine() -> str:
    """EEVEE's identifier in this Blender (BLENDER_EEVEE_NEXT in 4.2-4.x, BLENDER_EEVEE again from 5.0)."""
    import bpy

    engines = {item.identifier for item in bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items}
    return "BLENDER_EEVEE_NEXT" if "BLENDER_EEVEE_NEXT" in engines else "BLENDER_EEVEE"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="luigi,bonsai-tree,thin", help="luigi, bonsai, bonsai-tree, thin")
    parser.add_argument("--engines", default="eevee,workbench", help="comma-separated: eevee, workbench")
    parser.add_argument("--width", type=int, default=448)
    parser.add_argument("--height", type=int, default=320)
    parser.add_argument("--samples", type=int, default=1, help="EEVEE render samples (blended splats need one)")
    parser.add_argument(
        "--low-pass",
        default="on",
        choices=("on", "off", "both"),
        help="EEVEE with the render-time low-pass, without, or both",
    )
    parser.add_argument("--view", type=int, default=1, help="which of the 8 orbit cameras")
    parser.add_argument("--figure", help="write engine | each Blender engine side by side, one row per scene")
    parser.add_argument("--json", help="write the numbers")
    args = parser.parse_args(argv)

    engines = [ENGINES[name] for name in args.engines.split(",")]
    low_passes = {"on": [True], "off": [False], "both": [True, False]}[args.low_pass]
    cases = [(e, lp) for e in engines for lp in (low_passes if e == "EEVEE" else [True])]
    rows, results = [], []
    print(f"- machine: {cpu_model()}, {usable_cores()} cores usable; load average at start: {load_average()}")
    print("| scene | splats | Blender engine | its render | engine | luminance SSIM | mean colour error |")
    print("|---|---:|---|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as folder:
        for name in args.scenes.split(","):
            file, axes = SCENES[name]
            path = thin_splats_ply(Path(folder) / "thin.ply") if name == "thin" else SHARED / file
            if not path.exists():
                print(f"| {name} | skipped: {path} not present | | | | | |")
                continue
            if name == "bonsai-tree":
                path = crop_ply(path, Path(folder) / "bonsai-tree.ply")
            row = []
            for engine_name, low_pass in cases:
                result = compare(
                    path,
                    axes,
                    width=args.width,
                    height=args.height,
                    samples=args.samples,
                    view=args.view,
                    engine_name=engine_name,
                    low_pass=low_pass,
                )
                print(
                    f"| {name} | {result['splats']:,} | {case_label(engine_name, low_pass)} | {result['blender_seconds']:.1f} s "
                    f"| {result['engine_seconds']:.2f} s | {result['ssim_luminance']:.3f} "
                    f"| {result['mean_colour_error']:.4f} |"
                )
                engine, blender = result.pop("engine"), result.pop("blender")
                row = row or [engine]
                row += [np.ones((args.height, 4, 3)), blender]
                results.append({"name": name, **result})
            rows.append(np.concatenate(row, 1))
    if args.figure and rows:
        from dresg_addon.util.imageio import write_image

        gap = np.ones((4, rows[0].shape[1], 3))
        write_image(args.figure, np.concatenate([part for row in rows for part in (row, gap)][:-1], 0))
        shown = ", ".join(case_label(*case) for case in cases)
        print(f"wrote {args.figure} (left: the engine's render, then {shown})")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
