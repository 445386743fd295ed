# SPDX-License-Identifier: GPL-3.0-or-later
"""Stylize a Gaussian splat scene without the Blender interface, through the add-on's operators.

    blender -b [scene.blend] -P scripts/stylize_headless.py -- --ply IN.ply --style STYLE.jpg --out OUT.ply [options]
    python scripts/stylize_headless.py --ply IN.ply --style STYLE.jpg --out OUT.ply [--blend scene.blend] [options]

The second form needs the ``bpy`` module. Axes (``--axes``): ``auto`` unless given, as the import dialog's
Automatic. Views: the cameras of ``--cameras`` (cameras.json, a COLMAP
model, poses_bounds.npy) when given; else the .blend's cameras (the ticked ones, or all of them); else
an orbit ring of ``--orbit`` cameras around the splats. Without a .blend the run starts from an empty
scene, not Blender's startup file (whose default camera is not a view of the splats). Background mode runs the
optimizer synchronously and prints its progress. Exit code 0 on success, 1 on a bad command line,
2 when an operator fails (its message is printed).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "stylize_gaussians"
AXES = {"auto": "AUTO", "opencv": "OPENCV_TO_BLENDER", "y-up": "Y_UP_TO_BLENDER", "z-up": "NONE", "none": "NONE"}
OVERRIDES = {  # command-line option -> panel setting
    "stages": "stages",
    "width": "proposal_width",
    "height": "proposal_height",
    "stroke_size": "stroke_size",
    "paint_scene": "scene_weight",
    "scene_light": "scene_light",
    "medium": "medium",
    "geometry": "optimize_geometry",
    "max_views": "max_views",
    "render_scale": "render_scale",
    "seed": "seed",
}


def extension(package: str = PACKAGE):
    """This checkout's add-on imported as package ``package``, as Blender imports an extension from its folder
    (not registered). The engine comes with it as ``<package>.dresg_addon``: nothing needs to be installed."""
    module = sys.modules.get(package)
    if module is None:
        spec = importlib.util.spec_from_file_location(
            package, REPO / "__init__.py", submodule_search_locations=[str(REPO)]
        )
        module = importlib.util.module_from_spec(spec)
        sys.modules[package] = module
        spec.loader.exec_module(module)
    return module


def engine(module: str, package: str = PACKAGE):
    """A module of the add-on's engine, e.g. ``engine("method.config")``."""
    extension(package)
    return importlib.import_module(f"{package}.dresg_addon.{module}")


def load_addon(package: str = PACKAGE):
    """This checkout's add-on as package ``package``, registered unless an installed copy already is."""
    import bpy

    module = extension(package)
    if not hasattr(bpy.types, "DRESG_OT_stylize"):
        module.register()
    return module


def parse_args(argv: list[str]) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def build_parser() -> argparse.ArgumentParser:
    config, backends = engine("method.config"), engine("method.backends")
    DEFAULT_PRESET, PRESETS = config.DEFAULT_PRESET, config.PRESETS

    parser = argparse.ArgumentParser(
        prog="stylize_headless.py", description="Stylize a Gaussian splat scene after a style image (DReSG)."
    )
    parser.add_argument("--ply", required=True, help="input scene (.ply, .splat, compressed .ply)")
    parser.add_argument("--style", required=True, help="style image")
    parser.add_argument("--out", required=True, help="output graphdeco .ply")
    parser.add_argument("--blend", help="a .blend whose cameras to use (python form; Blender takes it before -P)")
    parser.add_argument("--preset", default=DEFAULT_PRESET, help=f"settings preset ({', '.join(PRESETS)})")
    parser.add_argument("--proposal", choices=tuple(backends.BACKENDS), default=backends.DEFAULT_BACKEND)
    parser.add_argument("--model-path", default="", help="SD1.5 diffusers folder or .safetensors (sd15)")
    parser.add_argument("--dino-path", default="", help="local DINOv2 weights for the feature loss")
    parser.add_argument(
        "--axes",
        choices=tuple(AXES),
        default="auto",
        help="which way is up in the input file (default: auto, as the import dialog's Automatic: from the "
        "cameras of --cameras or beside the file, else the splats, else opencv, y down)",
    )
    parser.add_argument("--cameras", help="camera file or folder (cameras.json, COLMAP, poses_bounds.npy)")
    parser.add_argument("--orbit", type=int, default=12, help="orbit cameras to add when there are none")
    knobs = {flag: (kind, text) for flag, _, kind, text in engine("commands.stylize").KNOBS}  # the CLI's words
    parser.add_argument("--stages", type=knobs["--stages"][0], help=knobs["--stages"][1])
    parser.add_argument("--width", type=int, help="View Size X: the width the views are painted at")
    parser.add_argument("--height", type=int, help="View Size Y: the height the views are painted at")
    for flag in ("--stroke-size", "--paint-scene", "--scene-light"):
        parser.add_argument(flag, type=knobs[flag][0], help=knobs[flag][1])
    medium = engine("method.medium")
    parser.add_argument(
        "--medium",
        choices=medium.MEDIA,
        help="what the painting is; " + "; ".join(f"{name}: {text[1]}" for name, text in medium.MEDIUM_LABELS.items()),
    )
    parser.add_argument("--geometry", action=argparse.BooleanOptionalAction, help="optimise geometry offsets")
    for flag in ("--max-views", "--seed"):
        parser.add_argument(flag, type=knobs[flag][0], help=knobs[flag][1])
    parser.add_argument("--render-scale", type=float, help="render resolution relative to the cameras' own")
    return parser


def script_arguments(argv: list[str]) -> list[str]:
    """Arguments meant for this script: after ``--`` under Blender, all but the program otherwise."""
    return argv[argv.index("--") + 1 :] if "--" in argv else argv[1:]


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse_args(script_arguments(sys.argv) if argv is None else argv)
    except SystemExit as exit_:
        return 1 if exit_.code else 0
    import bpy

    DresgError = engine("util.errors").DresgError

    try:
        if args.blend:
            bpy.ops.wm.open_mainfile(filepath=args.blend)
        elif not bpy.data.filepath:
            bpy.ops.wm.read_factory_settings(use_empty=True)
            print("[stylize] no .blend: starting from an empty scene")
        load_addon()
        scene = bpy.context.scene
        axes = AXES[args.axes]
        if axes == "AUTO" and args.cameras:  # the views' own up
            camera_io, splat_mesh = engine("scene.camera_io"), engine("blender.splat_mesh")
            axes = splat_mesh.axis_conversion_for_up(camera_io.mean_camera_up(camera_io.load_cameras(args.cameras)))
            print(f"[stylize] axes: {splat_mesh.AXIS_LABELS[axes]}, from the cameras in {args.cameras}")
        bpy.ops.dresg.import_splats(filepath=args.ply, axis_conversion=axes)
        settings = scene.dresg
        settings.preset = args.preset
        for option, field in OVERRIDES.items():
            value = getattr(args, option)
            if value is not None:
                setattr(settings, field, value)
        settings.proposal = args.proposal
        settings.style_source, settings.style_path = "FILE", args.style
        cameras = [obj for obj in scene.objects if obj.type == "CAMERA"]
        if args.cameras:
            for obj in cameras:  # the file's cameras are the views, not the .blend's
                obj.dresg_view.use = False
            bpy.ops.dresg.import_cameras(filepath=args.cameras)
            print(f"[stylize] using the cameras of {args.cameras}")
        elif cameras:
            print(f"[stylize] using the .blend's cameras: {', '.join(sorted(obj.name for obj in cameras))}")
        else:
            bpy.ops.dresg.add_orbit_cameras(count=args.orbit)
            print(f"[stylize] no cameras: added {args.orbit} orbit cameras")
        bpy.ops.dresg.stylize(model_path=args.model_path, dino_path=args.dino_path)
        bpy.ops.dresg.export_splats(filepath=args.out)
    except RuntimeError as error:  # an operator reported an error (its message says what)
        print(f"error: {str(error).strip()}", file=sys.stderr)
        return 2
    except DresgError as error:  # the camera file, read here for its up direction
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"[stylize] wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
