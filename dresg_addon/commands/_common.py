"""Options shared by the commands that take a scene and cameras."""

from __future__ import annotations

import argparse
import sys

from ..util.errors import ConfigError


def add_scene_and_cameras(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE", help="scene file: graphdeco .ply, .splat or compressed .ply")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--cameras", metavar="PATH", help="cameras.json, a COLMAP model, or LLFF poses_bounds.npy")
    source.add_argument("--orbit", type=int, metavar="N", help="N cameras on a ring around the scene (no camera file)")
    parser.add_argument("--width", type=int, help="image width for orbit cameras, or to resize the given cameras")
    parser.add_argument("--height", type=int, help="image height (with --width)")
    parser.add_argument(
        "--drop-invalid", action="store_true", help="drop splats with non-finite values instead of failing"
    )


def load_scene_and_cameras(args, default_orbit: int = 16):
    """(scene, cameras) from the shared options; orbit cameras when no camera file is given."""
    from ..scene.camera_io import load_cameras, resize_cameras
    from ..scene.io import clamped_note, read_scene_detailed
    from ..scene.orbit import orbit_cameras

    if (args.width is None) != (args.height is None):
        raise ConfigError("--width and --height go together")
    from ..scene.camera_io import MAX_IMAGE_SIDE

    for flag, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and not 1 <= value <= MAX_IMAGE_SIDE:
            raise ConfigError(f"{flag} {value} must be between 1 and {MAX_IMAGE_SIDE} pixels")
    result = read_scene_detailed(args.scene, drop_invalid=args.drop_invalid)
    if result.clamped:
        print(f"note: {clamped_note(result.clamped)}", file=sys.stderr)
    scene = result.scene
    if args.cameras:
        cameras = load_cameras(args.cameras)
        if args.width:
            cameras = resize_cameras(cameras, width=args.width, height=args.height)
    else:
        size = {"width": args.width, "height": args.height} if args.width else {}
        cameras = orbit_cameras(scene, args.orbit or default_orbit, **size)
    return scene, cameras


def parse_background(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise ConfigError(f"--background must be three numbers in [0, 1] like 0,0,0 (got {text!r})")
    return values
