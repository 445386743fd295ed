"""``python -m dresg_addon evaluate STYLIZED --base BASE --style IMG``: style, content, consistency, efficiency.

Both scenes are rendered from each camera, in order (the order of the camera file, or around the
orbit ring: that order is the path along which consistency is measured). Per view:

- style: sliced Wasserstein distance of colours and of 7 x 7 patches to the style image, which is
  first resized (aspect kept) so that its shorter side matches the first camera's;
- content: SSIM and gradient-structure similarity to the base render from the same camera;
- texture and forms, on the pixels the base render covers: ``texture_kept``, the correlation of the
  luminance high-pass (sigma 2 px) with the base render's, 4 px inside the silhouette (1: the scene's own
  fine texture is all still there, about 0: replaced, e.g. by the painting's marks), and ``shapes``, SSIM of
  the luminance blurred by a Gaussian of sigma 3 px (1: the same forms);
- optional CLIP-S (``--clip``) and DINO-C (``--dino``) with local transformers weights.

Along the path: the stylized render of view i warped into view i + gap with the stylized scene's
rendered depth and the known poses, masked RMSE for gap 1 (short-term) and N // 2 (long-term); the
same for the base scene, as the floor that the rasterizer and view-dependent colour alone give.
Efficiency: render FPS and peak memory of the stylized scene, and, with ``--log``, the optimisation
time and peak memory from the stylizer's log. All renders are clipped to [0, 1] before measuring.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from ..util.errors import ConfigError, NumericalError
from ._common import (
    ORBIT_SIZE,
    add_background_option,
    add_device_option,
    add_size_options,
    add_up_option,
    orbit_for,
    parse_background,
    parse_device,
    read_cameras,
    read_scene_noting,
)

NAME = "evaluate"
HELP = (
    "Measure a stylized scene against its base scene and style image: style distance, content similarity, "
    "cross-view consistency, render speed (and CLIP-S / DINO-C with local weights)."
)

DEFAULT_ORBIT = 8
PER_VIEW_KEYS = (
    "sw_colors",
    "sw_patches",
    "ssim",
    "gradient_structure",
    "texture_kept",
    "shapes",
    "clip_s",
    "dino_c",
    "alpha_coverage",
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("stylized", metavar="STYLIZED", help="the stylized scene (.ply, .splat or compressed .ply)")
    parser.add_argument("--base", metavar="BASE", required=True, help="the base (unstylized) scene it was made from")
    parser.add_argument("--style", metavar="IMG", required=True, help="the style image (alpha composited on white)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument(
        "--cameras",
        metavar="FILE",
        help="cameras, in path order: graphdeco cameras.json, a COLMAP model or LLFF poses_bounds.npy",
    )
    source.add_argument(
        "--orbit",
        metavar="N",
        type=int,
        help=f"N cameras on a ring around the base scene (the default, with N = {DEFAULT_ORBIT}), "
        f"{ORBIT_SIZE[0]}x{ORBIT_SIZE[1]} unless resized",
    )
    add_up_option(parser)
    add_size_options(parser, scale=True)
    parser.add_argument("--near", type=float, default=0.01, help="near plane of the rasterizer")
    add_background_option(parser)
    parser.add_argument("--log", metavar="FILE", help="the stylizer's log (JSON lines): optimisation time and memory")
    parser.add_argument("--clip", metavar="DIR", help="local transformers CLIP ViT-B/32 folder: adds CLIP-S")
    parser.add_argument("--dino", metavar="DIR", help="local transformers DINO (ViT, DINOv2) folder: adds DINO-C")
    parser.add_argument("--json", metavar="OUT", help="write every value (per view and means) to this JSON file")
    parser.add_argument(
        "--fps-repeats", type=int, default=2, metavar="K", help="render every camera K times for the FPS (0: skip)"
    )
    parser.add_argument("--projections", type=int, default=128, metavar="N", help="sliced Wasserstein projections")
    parser.add_argument(
        "--color-samples", type=int, default=65536, metavar="N", help="pixels drawn per image (fixed positions)"
    )
    parser.add_argument(
        "--patch", type=int, default=7, metavar="N", help="patch size of the patch sliced Wasserstein distance"
    )
    parser.add_argument(
        "--patch-samples", type=int, default=16384, metavar="N", help="patches drawn per image (fixed positions)"
    )
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the projections and patch positions")
    # Defaults come from dresg_addon.evaluation.metrics at run time: importing it (torch) here would slow every command.
    parser.add_argument(
        "--depth-tolerance",
        type=float,
        metavar="TOL",
        help="consistency occlusion test: a warped pixel whose depth differs from the surface the source view "
        "sees by more than TOL times its depth is occluded (default 0.03)",
    )
    parser.add_argument(
        "--alpha-threshold",
        type=float,
        metavar="A",
        help="consistency: pixels less opaque than A, in either view, are left out (default 0.5)",
    )
    parser.add_argument("--drop-invalid", action="store_true", help="drop splats with non-finite values")
    add_device_option(parser, use="where to render and run the CLIP / DINO models")


def _check_options(args: argparse.Namespace) -> tuple[float, float]:
    """Check the plain options; returns (depth tolerance, alpha threshold) with their defaults filled in."""
    from ..evaluation.metrics import ALPHA_THRESHOLD, DEPTH_TOLERANCE

    tolerance = DEPTH_TOLERANCE if args.depth_tolerance is None else args.depth_tolerance
    threshold = ALPHA_THRESHOLD if args.alpha_threshold is None else args.alpha_threshold
    if not (math.isfinite(args.near) and args.near >= 0.0):
        raise ConfigError(f"--near {args.near} must be a finite number >= 0")
    for option, value, low in (
        ("--fps-repeats", args.fps_repeats, 0),
        ("--projections", args.projections, 1),
        ("--patch", args.patch, 1),
        ("--color-samples", args.color_samples, 1),
        ("--patch-samples", args.patch_samples, 1),
    ):
        if value < low:
            raise ConfigError(f"{option} {value} must be at least {low}")
    if not (math.isfinite(tolerance) and tolerance > 0.0):
        raise ConfigError(f"--depth-tolerance {tolerance} must be a positive number")
    if not 0.0 <= threshold < 1.0:
        raise ConfigError(f"--alpha-threshold {threshold} must be in [0, 1)")
    if args.json is not None and Path(args.json).is_dir():
        raise ConfigError(f"--json {args.json}: is a folder; give a file name")
    return tolerance, threshold


def _render_all(scene, cameras, settings, device, label: str):
    """Per camera: (rgb [3, H, W] clipped to [0, 1], alpha [H, W], depth [H, W]) on the CPU, float32."""
    from ..raster import render_scene

    views = []
    for camera in cameras:
        out = render_scene(scene, camera, settings, device=device)
        if not bool(out.rgb.isfinite().all()):
            raise NumericalError(f"{label}: the render of camera {camera.name or len(views)} has non-finite values")
        rgb = out.rgb.float().clamp(0.0, 1.0).permute(2, 0, 1).cpu()
        views.append((rgb, out.alpha.float().cpu(), out.depth.float().cpu()))
    return views


def _style_for(style, camera):
    """The style image resized (aspect kept) so its shorter side equals the camera's."""
    from ..util.imageio import resize_image

    _, h, w = style.shape
    factor = min(camera.width, camera.height) / min(w, h)
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    return style if size == (w, h) else resize_image(style, *size)


def _mean(values) -> float | None:
    present = [v for v in values if v is not None]
    return sum(present) / len(present) if present else None


def evaluate(args: argparse.Namespace) -> dict:
    """Everything the command measures, as a JSON-ready dict (no NaN: missing values are None)."""
    from ..evaluation import metrics
    from ..raster import RasterSettings
    from ..util.imageio import STYLE_MAX_SIDE, read_rgb, to_tensor

    tolerance, threshold = _check_options(args)
    background = parse_background(args.background)
    device = parse_device(args.device)
    cameras = read_cameras(args)
    log = metrics.read_stylize_log(args.log).as_dict() if args.log else None
    if args.clip or args.dino:
        from ..evaluation.clip_dino import check_model_folder

        for kind, path in (("clip", args.clip), ("dino", args.dino)):
            if path:
                check_model_folder(path, kind)
    style = to_tensor(read_rgb(args.style, max_side=STYLE_MAX_SIDE))
    stylized = read_scene_noting(args.stylized, args.drop_invalid, "stylized scene")
    base = read_scene_noting(args.base, args.drop_invalid, "base scene")
    if cameras is None:
        cameras = orbit_for(args, base, DEFAULT_ORBIT)
    small = [c for c in cameras if min(c.width, c.height) < args.patch]
    if small:
        raise ConfigError(f"camera {small[0].name!r} is {small[0].width}x{small[0].height}, smaller than a patch")
    settings = RasterSettings(near=args.near, background=background)

    # Benchmark first, while the process holds little besides the two scenes.
    benchmark = None
    if args.fps_repeats:
        benchmark = metrics.measure_render(stylized, cameras, settings, args.fps_repeats, device).as_dict()
    ours = _render_all(stylized, cameras, settings, device, "stylized scene")
    theirs = _render_all(base, cameras, settings, device, "base scene")
    rgb = [v[0] for v in ours]
    base_rgb = [v[0] for v in theirs]

    style_small = _style_for(style, cameras[0])
    sw_colors = metrics.sliced_wasserstein_colors(rgb, style_small, args.projections, args.seed, args.color_samples)
    sw_patches = metrics.sliced_wasserstein_patches(
        rgb, style_small, args.patch, args.projections, args.seed, args.patch_samples
    )
    ssim = [float(metrics.ssim_per_image(a, b)) for a, b in zip(rgb, base_rgb)]
    structure = [float(metrics.gradient_structure_similarity(a, b)) for a, b in zip(rgb, base_rgb)]
    covered = [v[1] for v in theirs]  # the base render's alpha: the pixels the scene covers
    texture = [float(metrics.texture_kept(a, b, mask=m)) for a, b, m in zip(rgb, base_rgb, covered)]
    shapes = [float(metrics.shape_similarity(a, b, mask=m)) for a, b, m in zip(rgb, base_rgb, covered)]
    clip_s = dino_c = [None] * len(cameras)
    if args.clip:
        from ..evaluation.clip_dino import clip_style_score, load_clip

        clip_s = clip_style_score(load_clip(args.clip, device), rgb, style).tolist()
    if args.dino:
        from ..evaluation.clip_dino import dino_content_score, load_dino

        dino_c = dino_content_score(load_dino(args.dino, device), rgb, base_rgb).tolist()

    per_view = []
    for i, camera in enumerate(cameras):
        per_view.append(
            {
                "name": camera.name or f"view_{i:03d}",
                "width": camera.width,
                "height": camera.height,
                "sw_colors": float(sw_colors[i]),
                "sw_patches": float(sw_patches[i]),
                "ssim": ssim[i],
                "gradient_structure": structure[i],
                "texture_kept": texture[i],
                "shapes": shapes[i],
                "clip_s": clip_s[i],
                "dino_c": dino_c[i],
                "alpha_coverage": float((ours[i][1] > threshold).float().mean()),
            }
        )

    n = len(cameras)
    consistency = {}
    for label, views in (("stylized", ours), ("base", theirs)):
        images = [v[0].permute(1, 2, 0) for v in views]
        alphas, depths = [v[1] for v in views], [v[2] for v in views]
        consistency[label] = {
            term: metrics.consistency_rmse(images, depths, alphas, cameras, gap, tolerance, threshold).as_dict()
            for term, gap in (("short_term", 1), ("long_term", max(1, n // 2)))
        }

    return {
        "stylized": str(args.stylized),
        "base": str(args.base),
        "style": str(args.style),
        "cameras": str(args.cameras) if args.cameras else f"orbit {n}",
        "views": n,
        "device": str(device),
        "settings": {
            "projections": args.projections,
            "color_samples": args.color_samples,
            "patch": args.patch,
            "patch_samples": args.patch_samples,
            "seed": args.seed,
            "depth_tolerance": tolerance,
            "alpha_threshold": threshold,
            "style_size": [int(style_small.shape[2]), int(style_small.shape[1])],
        },
        "mean": {key: _mean(view[key] for view in per_view) for key in PER_VIEW_KEYS},
        "per_view": per_view,
        "consistency": consistency,
        "efficiency": {
            "splats": len(stylized),
            "render": benchmark,
            "stylize_log": log,
        },
    }


def _fmt(value, digits: int = 4) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def format_report(report: dict) -> str:
    """The report as a readable table."""
    columns = (
        ("SW col", "sw_colors"),
        ("SW patch", "sw_patches"),
        ("SSIM", "ssim"),
        ("GS", "gradient_structure"),
        ("texture kept", "texture_kept"),
        ("shapes", "shapes"),
        ("CLIP-S", "clip_s"),
        ("DINO-C", "dino_c"),
        ("alpha", "alpha_coverage"),
    )
    width = max([4, *(len(v["name"]) for v in report["per_view"])])
    cells = [max(10, len(title) + 2) for title, _ in columns]

    def row_of(name: str, values) -> str:
        return f"{name:<{width}}" + "".join(f"{_fmt(value):>{cell}}" for value, cell in zip(values, cells))

    lines = [f"{'view':<{width}}" + "".join(f"{title:>{cell}}" for (title, _), cell in zip(columns, cells))]
    for row in report["per_view"]:
        lines.append(row_of(row["name"], [row[key] for _, key in columns]))
    lines.append("-" * len(lines[0]))
    lines.append(row_of("mean", [report["mean"][key] for _, key in columns]))
    lines.append(
        "lower is better: SW col, SW patch, texture kept (less of the base's fine texture); "
        "higher is better: SSIM, GS, shapes, CLIP-S, DINO-C"
    )
    lines.append("consistency, masked RMSE of the warped render (lower is better; coverage = valid pixels):")
    for term in ("short_term", "long_term"):
        stylized, base = report["consistency"]["stylized"][term], report["consistency"]["base"][term]
        lines.append(
            f"  {term.replace('_', '-')} (gap {stylized['gap']}): stylized {_fmt(stylized['rmse'])} "
            f"(coverage {stylized['coverage']:.0%}), base {_fmt(base['rmse'])} (coverage {base['coverage']:.0%})"
        )
    efficiency = report["efficiency"]
    render = efficiency["render"]
    if render:
        memory = f"peak RSS {render['peak_rss_mb']:.0f} MB"
        if render["peak_cuda_mb"] is not None:
            memory += f", peak CUDA {render['peak_cuda_mb']:.0f} MB"
        lines.append(
            f"render: {render['fps']:.2f} FPS ({render['frames']} frames in {render['seconds']:.2f} s on "
            f"{report['device']}, {efficiency['splats']:,} splats), {memory}"
        )
    log = efficiency["stylize_log"]
    if log:
        peaks = ", ".join(f"{k} {v:.0f}" for k, v in log.items() if k.startswith("peak_")) or "no peak memory"
        lines.append(f"stylize: {_fmt(log['optimisation_seconds'], 1)} s, {peaks} ({log['records']} log records)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from ..util.fileutil import atomic_write_bytes

    report = evaluate(args)
    print(format_report(report))
    if args.json:
        atomic_write_bytes(args.json, (json.dumps(report, indent=2, allow_nan=False) + "\n").encode("utf-8"))
        print(f"wrote {args.json}")
    return 0
