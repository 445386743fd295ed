"""The options several commands share, each defined and checked in one place.

A command adds a shared option with its ``add_*`` function and reads it with the matching parser, so that
``render --background 1`` and ``stylize --background 1`` mean the same and a bad value gives the same one-line
ConfigError everywhere. Commands import shared helpers from here only, never from each other. Nothing here
imports torch at import time: building the parser (``--help``, ``info``) stays instant.
"""

from __future__ import annotations

import argparse
import math
import sys

from ..util.errors import ConfigError

ORBIT_SIZE = (448, 320)  # orbit cameras' image size unless resized: the proposal resolution
DEFAULT_ORBIT = 16  # orbit cameras of stylize and select-views when no camera file is given


def add_scene_and_cameras(parser: argparse.ArgumentParser) -> None:
    """SCENE, ``--cameras`` or ``--orbit``, ``--up``, ``--width``/``--height`` and ``--drop-invalid``."""
    parser.add_argument("scene", metavar="SCENE", help="scene file: graphdeco .ply, .splat or compressed .ply")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--cameras", metavar="PATH", help="cameras.json, a COLMAP model, or LLFF poses_bounds.npy")
    source.add_argument(
        "--orbit",
        type=int,
        metavar="N",
        help=f"N cameras on a ring around the scene ({DEFAULT_ORBIT} when no camera file is given), "
        f"{ORBIT_SIZE[0]}x{ORBIT_SIZE[1]} unless resized",
    )
    add_up_option(parser)
    add_size_options(parser)
    parser.add_argument(
        "--drop-invalid", action="store_true", help="drop splats with non-finite values instead of failing"
    )


def add_up_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--up",
        metavar="X,Y,Z",
        default="0,-1,0",
        help="with --orbit: the world direction shown up in the images (COLMAP/graphdeco worlds are y-down: "
        "0,-1,0; y-up scenes: 0,1,0; z-up: 0,0,1)",
    )


def add_size_options(
    parser: argparse.ArgumentParser,
    *,
    scale: bool = False,
    unset: str = f"the cameras' own size, {ORBIT_SIZE[0]}x{ORBIT_SIZE[1]} for orbit cameras",
) -> None:
    """``--width``/``--height``, and ``--scale`` with ``scale`` (commands with a ``--render-scale`` of their own
    would find a second scale confusing); ``unset`` says what size the images have without them."""
    for flag, metavar, what in (("--width", "W", "width"), ("--height", "H", "height")):
        parser.add_argument(
            flag,
            type=int,
            metavar=metavar,
            help=f"image {what}, the cameras' intrinsics scaled to match; alone, the other side keeps the aspect "
            f"ratio (without either: {unset})",
        )
    if scale:
        parser.add_argument(
            "--scale",
            type=float,
            metavar="S",
            help="multiply every image size by S (0.5: half resolution); not with --width/--height",
        )


def add_background_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--background",
        metavar="R,G,B",
        default="0,0,0",
        help="background colour behind the splats, linear, in [0, 1] per channel (one value gives a grey)",
    )


def add_device_option(
    parser: argparse.ArgumentParser, *, use: str = "where to render", default: str | None = "cpu"
) -> None:
    """``--device``; ``use`` says what runs on it (None ``default``: the engine chooses)."""
    parser.add_argument(
        "--device",
        default=default,
        help=f"torch device, cpu, cuda or cuda:N (a GPU that this torch build sees): {use}",
    )


def _numbers(option: str, text: str, example: str, counts: tuple[int, ...]) -> list[float]:
    try:
        values = [float(part) for part in str(text).split(",")]
    except ValueError:
        raise ConfigError(f"{option} {text!r}: expected comma-separated numbers such as {example}") from None
    if len(values) not in counts:
        raise ConfigError(f"{option} {text!r}: expected {' or '.join(map(str, counts))} numbers, got {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{option} {text!r}: values must be finite")
    return values


def parse_background(text: str) -> tuple[float, float, float]:
    """``'R,G,B'``, or one value for a grey, each in [0, 1]; ``ConfigError`` otherwise.

    [0, 1] because it is a linear RGB colour like the splats' own, and stylization's targets (sigmoids of
    RGB logits) cannot reach a channel above 1.
    """
    values = _numbers("--background", text, "0,0,0 or 1", counts=(1, 3))
    if not all(0.0 <= v <= 1.0 for v in values):
        raise ConfigError(f"--background {text!r}: values must be in [0, 1]")
    r, g, b = values * 3 if len(values) == 1 else values
    return r, g, b


def parse_up(text: str) -> tuple[float, float, float]:
    """``'X,Y,Z'`` -> a non-zero finite direction; ``ConfigError`` otherwise."""
    x, y, z = _numbers("--up", text, "0,-1,0", counts=(3,))
    if x == y == z == 0.0:
        raise ConfigError(f"--up {text!r}: the direction must not be zero")
    return x, y, z


def check_size_options(args: argparse.Namespace) -> float | None:
    """The downscale factor for ``load_cameras`` (1 / ``--scale``; None without it), after checking the sizes."""
    from ..scene.camera_io import MAX_IMAGE_SIDE

    scale = getattr(args, "scale", None)  # only commands added with add_size_options(scale=True) have it
    if scale is not None and (args.width is not None or args.height is not None):
        raise ConfigError("give either --scale or --width/--height, not both")
    for flag, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and not 1 <= value <= MAX_IMAGE_SIDE:
            raise ConfigError(f"{flag} {value} must be between 1 and {MAX_IMAGE_SIDE} pixels")
    if scale is None:
        return None
    if not (math.isfinite(scale) and scale > 0):
        raise ConfigError(f"--scale {scale} must be a positive number")
    return 1.0 / scale


def orbit_size(args: argparse.Namespace) -> tuple[int, int]:
    """Orbit cameras' (width, height): ORBIT_SIZE resized as the size options say (one alone keeps its aspect)."""
    from ..scene.camera_io import MAX_IMAGE_SIDE

    base_w, base_h = ORBIT_SIZE
    scale = getattr(args, "scale", None)
    if scale is not None:
        size = (round(base_w * scale), round(base_h * scale))
    elif args.width is not None and args.height is not None:
        size = (args.width, args.height)
    elif args.width is not None:
        size = (args.width, round(args.width * base_h / base_w))
    elif args.height is not None:
        size = (round(args.height * base_w / base_h), args.height)
    else:
        size = ORBIT_SIZE
    if not all(1 <= side <= MAX_IMAGE_SIDE for side in size):
        raise ConfigError(f"orbit image size {size[0]}x{size[1]} must be between 1 and {MAX_IMAGE_SIDE} pixels a side")
    return size


def parse_device(name: str):
    """``--device`` as a ``torch.device``: cpu, cuda or cuda:N, the GPU present; ``ConfigError`` otherwise."""
    import torch

    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        device = None
    # Only what the rasterizer is tested on; cpu:N would name no other CPU.
    if device is None or not (device.type == "cuda" or device == torch.device("cpu")):
        raise ConfigError(f"--device {name!r}: expected cpu, cuda or cuda:N")
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ConfigError(f"--device {name!r}: this torch build sees no CUDA GPU; use --device cpu")
        if device.index is not None and device.index >= count:
            raise ConfigError(
                f"--device {name!r}: this torch build sees {count} CUDA GPU(s), cuda:0 to cuda:{count - 1}"
            )
    return device


def read_cameras(args: argparse.Namespace):
    """The ``--cameras`` file's cameras, resized as the size options say; None for orbit cameras (they need the
    scene: :func:`orbit_for`). Checks ``--orbit``, ``--up`` and the sizes first, so a typo fails before any read."""
    from ..scene.camera_io import load_cameras

    if args.orbit is not None and args.orbit < 1:
        raise ConfigError(f"--orbit {args.orbit}: needs at least one camera")
    parse_up(args.up)
    factor = check_size_options(args)
    if args.cameras is None:
        orbit_size(args)
        return None
    return load_cameras(args.cameras, factor=factor, width=args.width, height=args.height)


def orbit_for(args: argparse.Namespace, scene, default_orbit: int):
    """``--orbit N`` cameras (``default_orbit`` without it) around ``scene``, sized and turned as the options say."""
    from ..scene.orbit import orbit_cameras

    width, height = orbit_size(args)
    return orbit_cameras(scene, args.orbit or default_orbit, width=width, height=height, up=parse_up(args.up))


def read_scene_noting(path, drop_invalid: bool, label: str = ""):
    """The scene at ``path``; what reading it dropped or clamped is noted on stderr (prefixed with ``label``)."""
    from ..scene.io import clamped_note, read_scene_detailed

    result = read_scene_detailed(path, drop_invalid=drop_invalid)
    prefix = f"note: {label}: " if label else "note: "
    if result.dropped:
        print(f"{prefix}dropped {result.dropped:,} splats with non-finite values", file=sys.stderr)
    if result.clamped:
        print(f"{prefix}{clamped_note(result.clamped)}", file=sys.stderr)
    return result.scene


def load_scene_and_cameras(args: argparse.Namespace, default_orbit: int = DEFAULT_ORBIT):
    """(scene, cameras) from SCENE and the camera options: the camera file is read before the scene (a bad
    file fails at once), orbit cameras once the scene is known."""
    cameras = read_cameras(args)
    scene = read_scene_noting(args.scene, args.drop_invalid)
    return scene, cameras if cameras is not None else orbit_for(args, scene, default_orbit)
