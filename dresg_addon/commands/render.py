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
from ..util.errors import ConfigError
from ._common import (
    ORBIT_SIZE,
    add_background_option,
    add_device_option,
    add_size_options,
    add_up_option,
    load_scene_and_cameras,
    parse_background,
    parse_device,
)

NAME = "render"
HELP = "Render a scene from its cameras (cameras.json, COLMAP, LLFF) or an orbit, one image per camera."

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
    add_up_option(parser)
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
    add_background_option(parser)
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
    add_size_options(parser, scale=True)
    parser.add_argument(
        "--drop-invalid",
        action="store_true",
        help="drop splats with non-finite values (NaN/Inf) instead of refusing the scene; says how many",
    )
    add_device_option(parser)


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
    from ..raster import RasterSettings, render_scene, scene_covariances
    from ..util.imageio import write_image

    # Options first, so that a typo fails before a large scene is read.
    background = parse_background(args.background)
    if not (math.isfinite(args.near) and args.near >= 0.0):
        raise ConfigError(f"--near {args.near} must be a finite number >= 0")
    device = parse_device(args.device)
    scene, cameras = load_scene_and_cameras(args)
    out_dir = _output_dir(args.out)
    settings = RasterSettings(near=args.near, background=background)
    ext = args.format

    started = time.perf_counter()
    covariances = scene_covariances(scene, device)
    total_pairs, empty = 0, 0
    for camera, stem in zip(cameras, output_stems(cameras)):
        args.threads.adapt()
        view_start = time.perf_counter()
        out = render_scene(scene, camera, settings, device=device, covariances=covariances)
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
