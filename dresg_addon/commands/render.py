"""``python -m dresg_addon render SCENE (--cameras FILE | --orbit N) --out DIR``: one image per camera.

Outputs, per camera, with ``NAME`` the camera's image name (extension dropped, path separators
replaced by ``_``) or ``orbit_000``, ``orbit_001``... for orbit cameras:

===================  ===========================================================================
file                 content
===================  ===========================================================================
``NAME.exr``         float32 linear RGB, exactly the rasterizer's output (no colour transform)
``NAME.png``         the same values in 8 bits: ``round(clip(x, 0, 1) * 255)``, no colour transform
``NAME_alpha.EXT``   coverage ``1 - T_final``, one channel, in the chosen format
``NAME_depth.exr``   always EXR (8 or 16 bits cannot hold scene depths): float32 expected camera-space
                     depth of the visible splats (z along the view axis, scene units), 0 where
                     nothing is seen
===================  ===========================================================================
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import time
from pathlib import Path

import numpy as np

from ..scene.camera import Camera
from ..scene.camera_io import load_cameras
from ..scene.io import read_scene_detailed
from ..scene.orbit import orbit_cameras
from ..util.errors import ConfigError

NAME = "render"
HELP = "Render a scene from its cameras (cameras.json, COLMAP, LLFF) or an orbit, one image per camera."

ORBIT_SIZE = (448, 320)  # the proposal resolution
_EXTENSION = re.compile(r"\.[A-Za-z][A-Za-z0-9]{0,4}$")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE", help="scene file: graphdeco .ply, .splat or compressed .ply")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--cameras",
        metavar="FILE",
        help="cameras to render: graphdeco cameras.json, a COLMAP model (folder, cameras/images .bin or .txt) "
        "or LLFF poses_bounds.npy; each camera's image name names its output",
    )
    source.add_argument(
        "--orbit",
        metavar="N",
        type=int,
        help=f"render N cameras on a ring around the scene's robust bounds instead (50 degree horizontal field "
        f"of view, {ORBIT_SIZE[0]}x{ORBIT_SIZE[1]} unless resized), named orbit_000, orbit_001, ...",
    )
    parser.add_argument(
        "--up",
        metavar="X,Y,Z",
        default="0,-1,0",
        help="with --orbit: the world direction shown up in the images (COLMAP/graphdeco worlds are y-down: "
        "0,-1,0; y-up scenes: 0,1,0; z-up: 0,0,1)",
    )
    parser.add_argument("--out", metavar="DIR", required=True, help="output folder, created if missing")
    parser.add_argument(
        "--format",
        choices=("png", "exr"),
        default="png",
        help="exr: float32 linear RGB as rendered; png: the same values in 8 bits (clipped to [0, 1], "
        "no colour transform)",
    )
    parser.add_argument(
        "--near", type=float, default=0.01, help="near plane: splats at camera depth <= NEAR are not drawn"
    )
    parser.add_argument(
        "--background",
        metavar="R,G,B",
        default="0,0,0",
        help="background colour behind the splats, linear, 0-1 per channel (one value gives a grey)",
    )
    parser.add_argument(
        "--depth",
        action="store_true",
        help="also write NAME_depth.exr: float32 expected camera-space depth of the visible splats "
        "(0 where nothing is seen); always EXR, whatever --format says",
    )
    parser.add_argument(
        "--alpha",
        action="store_true",
        help="also write NAME_alpha.<format>: the coverage (1 - final transmittance), one channel",
    )
    parser.add_argument(
        "--width",
        type=int,
        metavar="W",
        help="image width; the cameras' intrinsics are scaled to match (alone: keeps the aspect ratio)",
    )
    parser.add_argument(
        "--height",
        type=int,
        metavar="H",
        help="image height; the cameras' intrinsics are scaled to match (alone: keeps the aspect ratio)",
    )
    parser.add_argument(
        "--scale",
        type=float,
        metavar="S",
        help="multiply every image size by S (0.5: half resolution); not with --width/--height",
    )
    parser.add_argument(
        "--drop-invalid",
        action="store_true",
        help="drop splats with non-finite values (NaN/Inf) instead of refusing the scene; says how many",
    )
    parser.add_argument(
        "--device",
        default="cpu",
        help="torch device to render on: cpu, or cuda / cuda:N where a CUDA build of torch sees a GPU",
    )


def _numbers(option: str, text: str, example: str, counts: tuple[int, ...] = (3,)) -> list[float]:
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
    """``'R,G,B'`` (or one value for a grey) -> three finite non-negative floats; ``ConfigError`` otherwise."""
    values = _numbers("--background", text, "0,0,0 or 1,1,1", counts=(1, 3))
    if min(values) < 0.0:
        raise ConfigError(f"--background {text!r}: values must be non-negative")
    r, g, b = values * 3 if len(values) == 1 else values
    return r, g, b


def parse_up(text: str) -> tuple[float, float, float]:
    """``'X,Y,Z'`` -> a non-zero finite direction; ``ConfigError`` otherwise."""
    x, y, z = _numbers("--up", text, "0,-1,0")
    if x == y == z == 0.0:
        raise ConfigError(f"--up {text!r}: the direction must not be zero")
    return x, y, z


def output_stems(cameras: list[Camera]) -> list[str]:
    """File name stems, one per camera: the image name without extension, path separators (and characters
    file systems refuse) replaced by ``_``.

    Unnamed cameras get ``view_000``...; repeated names get ``_2``, ``_3``... so no output overwrites another.
    """
    stems: list[str] = []
    taken: set[str] = set()
    for index, camera in enumerate(cameras):
        stem = _EXTENSION.sub("", camera.name.strip())
        # Separators, control characters and what Windows forbids in names all become "_".
        stem = re.sub(r'[/\\\x00-\x1f<>:"|?*]', "_", stem).strip(" .") or f"view_{index:03d}"
        unique, count = stem, 1
        while unique.lower() in taken:  # case-insensitive file systems would overwrite too
            count += 1
            unique = f"{stem}_{count}"
        taken.add(unique.lower())
        stems.append(unique)
    return stems


def _check_size_options(args: argparse.Namespace) -> float | None:
    """The downscale factor for ``load_cameras`` (1 / scale), after checking the size options."""
    if args.scale is not None and (args.width is not None or args.height is not None):
        raise ConfigError("give either --scale or --width/--height, not both")
    for label, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and value < 1:
            raise ConfigError(f"{label} {value} must be at least 1")
    if args.scale is None:
        return None
    if not (math.isfinite(args.scale) and args.scale > 0):
        raise ConfigError(f"--scale {args.scale} must be a positive number")
    return 1.0 / args.scale


def _orbit_size(args: argparse.Namespace) -> tuple[int, int]:
    base_w, base_h = ORBIT_SIZE
    if args.scale is not None:
        size = (round(base_w * args.scale), round(base_h * args.scale))
    elif args.width is not None and args.height is not None:
        size = (args.width, args.height)
    elif args.width is not None:
        size = (args.width, round(args.width * base_h / base_w))
    elif args.height is not None:
        size = (round(args.height * base_w / base_h), args.height)
    else:
        size = ORBIT_SIZE
    if min(size) < 1:
        raise ConfigError(f"orbit image size {size[0]}x{size[1]} is empty")
    return size


def _device(name: str):
    import torch

    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"--device {name!r} is not a torch device (use cpu or cuda)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: this torch build sees no CUDA GPU; use --device cpu")
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"--device {name}: only cpu and cuda are supported")
    return device


def _output_dir(path: str) -> Path:
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"--out {out}: cannot create the folder ({error.strerror or error})") from None
    return out


def run(args: argparse.Namespace) -> int:
    from ..raster import RasterSettings, render_scene
    from ..util.imageio import write_image

    # Options first, so that a typo fails before a large scene is read.
    background = parse_background(args.background)
    if not (math.isfinite(args.near) and args.near >= 0.0):
        raise ConfigError(f"--near {args.near} must be a finite number >= 0")
    up = parse_up(args.up)
    factor = _check_size_options(args)
    device = _device(args.device)
    if args.orbit is not None:
        if args.orbit < 1:
            raise ConfigError(f"--orbit {args.orbit}: needs at least one camera")
        orbit_size = _orbit_size(args)
    else:
        cameras = load_cameras(args.cameras, factor=factor, width=args.width, height=args.height)

    result = read_scene_detailed(args.scene, drop_invalid=args.drop_invalid)
    if result.dropped:
        print(f"note: dropped {result.dropped:,} splats with non-finite values", file=sys.stderr)
    scene = result.scene
    if args.orbit is not None:
        cameras = orbit_cameras(scene, args.orbit, width=orbit_size[0], height=orbit_size[1], up=up)
    out_dir = _output_dir(args.out)
    settings = RasterSettings(near=args.near, background=background)
    ext = args.format

    started = time.perf_counter()
    total_pairs, empty = 0, 0
    for camera, stem in zip(cameras, output_stems(cameras)):
        view_start = time.perf_counter()
        out = render_scene(scene, camera, settings, device=device)
        seconds = time.perf_counter() - view_start
        alpha = out.alpha.cpu().numpy()
        write_image(out_dir / f"{stem}.{ext}", out.rgb.cpu().numpy())
        if args.alpha:
            write_image(out_dir / f"{stem}_alpha.{ext}", alpha)
        if args.depth:
            write_image(out_dir / f"{stem}_depth.exr", out.depth.cpu().numpy())
        total_pairs += out.n_pairs
        print(f"{stem}.{ext}: {camera.width}x{camera.height}, {out.n_pairs:,} pairs, {seconds:.2f} s", flush=True)
        if not np.any(alpha > 0):
            empty += 1
            print(f"warning: {stem}: the camera sees nothing of the scene (alpha is 0 everywhere)", file=sys.stderr)
    elapsed = time.perf_counter() - started
    summary = (
        f"rendered {len(cameras)} view{'s' if len(cameras) != 1 else ''} of {len(scene):,} splats "
        f"(SH degree {scene.sh_degree}) to {out_dir} in {elapsed:.1f} s, {total_pairs:,} pairs"
    )
    if empty:
        summary += f"; {empty} saw nothing"
    print(summary)
    return 0
