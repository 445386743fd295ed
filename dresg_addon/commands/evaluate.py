"""``python -m dresg_addon evaluate STYLIZED --base BASE --style IMG``: style, content, consistency, efficiency.

Both scenes are rendered from each camera, in order (the order of the camera file, or around the orbit ring:
that order is the path along which consistency is measured), and measured by
:func:`dresg_addon.evaluation.views.evaluate_views`, the evaluator of ``dresg report`` and ``bench/quality.py``
too, so the three give the same numbers for the same scenes, painting and cameras. Per view, on the pixels the
base render covers:

- style: sliced Wasserstein distance of 7 x 7 patches to the painting at the cameras' size, half and a quarter
  (renders at twice the size area-downsampled by 2, 4 and 8, the painting resampled to each size, its shorter
  side to the render's), and of the colours;
- content: SSIM and gradient structure to the base render from the same camera; ``texture_kept``, the
  correlation of the luminance high-pass (sigma 2 px) with the base render's, 4 px inside the silhouette (1:
  the scene's own fine texture is all still there, about 0: replaced, e.g. by the painting's marks), and
  ``shapes``, SSIM of the luminance blurred by a Gaussian of sigma 3 px (1: the same forms), and ``forms``, SSIM's
  structure term alone on it (1: the same forms, whatever the palette's brightness and contrast);
- mark contrast ``marks_fine``, ``marks_mid``, ``marks_coarse``: the luminance band-pass (differences of Gaussians at
  sigma 0.6/1.2, 1.2/2.4 and 2.4/4.8 px) of the 2x render area-downsampled to the cameras' size, less what the base
  render's same band explains, 4 px inside the silhouette, over the painting's own at ``--stroke-size`` (1: marks
  as strong as the painting's, about 0: none); ``mark_elongation``: how long the marks run for their
  width (the fine band's correlation length along the local mark direction over that across it) over the painting's
  own (1: strokes as elongated as the painting's; below: fragments, dabs and blobs);
- optional CLIP-S (``--clip``) and DINO-C (``--dino``) with local transformers weights.

Along the path: the stylized render of view i warped into view i + gap with the stylized scene's
rendered depth and the known poses, masked RMSE for gap 1 (short-term) and N // 2 (long-term); the
same for the base scene, as the floor that the rasterizer and view-dependent colour alone give.
Efficiency: render FPS and peak memory of the stylized scene, and, with ``--log``, the optimisation
time and peak memory from the stylizer's log. Renders are measured as the rasterizer gives them (not clipped).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from ..util.errors import ConfigError
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
    "Measure a stylized scene against its base scene and style image, as the report and the quality benchmark "
    "do: style distance (patches at three scales, colours), content similarity, texture kept, shapes, forms, mark "
    "contrast, cross-view consistency, render speed (and CLIP-S / DINO-C with local weights)."
)

DEFAULT_ORBIT = 8
EXTRA_KEYS = ("clip_s", "dino_c", "alpha_coverage")  # per view, besides evaluate_views's


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
        "--patch",
        type=int,
        default=7,
        metavar="N",
        help="patch size of the patch sliced Wasserstein distance (cameras need 4 N pixels a side: the quarter scale)",
    )
    parser.add_argument(
        "--patch-samples", type=int, default=16384, metavar="N", help="patches drawn per image (fixed positions)"
    )
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the projections and patch positions")
    parser.add_argument(
        "--stroke-size",
        type=float,
        metavar="S",
        help="the run's Stroke Size: mark contrast compares with the painting resampled to the cameras' size x S "
        "(default: the standard preset's, 1.5)",
    )
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
    if args.stroke_size is not None and not (math.isfinite(args.stroke_size) and args.stroke_size > 0.0):
        raise ConfigError(f"--stroke-size {args.stroke_size} must be a positive number")
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


def _mean(values) -> float | None:
    present = [v for v in values if v is not None]
    return sum(present) / len(present) if present else None


def evaluate(args: argparse.Namespace) -> dict:
    """Everything the command measures, as a JSON-ready dict (no NaN: missing values are None)."""
    from ..evaluation import metrics
    from ..evaluation.views import base_views, check_camera_sizes, evaluate_views, path_consistency
    from ..method.config import DEFAULT_PRESET, PRESETS
    from ..raster import RasterSettings
    from ..scene.camera import view_name
    from ..util.imageio import STYLE_MAX_SIDE, read_rgb, to_tensor

    tolerance, threshold = _check_options(args)
    stroke_size = PRESETS[DEFAULT_PRESET].stroke_size if args.stroke_size is None else args.stroke_size
    background = parse_background(args.background)
    device = parse_device(args.device)
    cameras = read_cameras(args)
    log = metrics.read_stylize_log(args.log).as_dict() if args.log else None
    if args.clip or args.dino:
        from ..evaluation.clip_dino import check_model_folder

        for kind, path in (("clip", args.clip), ("dino", args.dino)):
            if path:
                check_model_folder(path, kind)
    style = read_rgb(args.style, max_side=STYLE_MAX_SIDE)
    stylized = read_scene_noting(args.stylized, args.drop_invalid, "stylized scene")
    base = read_scene_noting(args.base, args.drop_invalid, "base scene")
    if cameras is None:
        cameras = orbit_for(args, base, DEFAULT_ORBIT)
    check_camera_sizes(cameras, args.patch)
    settings = RasterSettings(near=args.near, background=background)

    # Benchmark first, while the process holds little besides the two scenes.
    benchmark = None
    if args.fps_repeats:
        benchmark = metrics.measure_render(stylized, cameras, settings, args.fps_repeats, device).as_dict()
    base_renders = base_views(base, cameras, settings, device)
    measured = evaluate_views(
        stylized,
        base_renders,
        style,
        settings,
        device,
        patch=args.patch,
        projections=args.projections,
        seed=args.seed,
        color_samples=args.color_samples,
        patch_samples=args.patch_samples,
        depth_tolerance=tolerance,
        alpha_threshold=threshold,
        stroke_size=stroke_size,
    )
    n = len(cameras)
    extra = {key: [None] * n for key in EXTRA_KEYS}
    extra["alpha_coverage"] = [float((alpha > threshold).float().mean()) for alpha in measured.renders.alpha]
    clipped = [rgb.clamp(0.0, 1.0) for rgb in measured.renders.rgb]  # the models take images in [0, 1]
    if args.clip:
        from ..evaluation.clip_dino import clip_style_score, load_clip

        extra["clip_s"] = clip_style_score(load_clip(args.clip, device), clipped, to_tensor(style)).tolist()
    if args.dino:
        from ..evaluation.clip_dino import dino_content_score, load_dino

        base_clipped = [rgb.clamp(0.0, 1.0) for rgb in base_renders.renders.rgb]
        extra["dino_c"] = dino_content_score(load_dino(args.dino, device), clipped, base_clipped).tolist()

    per_view = [
        {
            "name": view_name(camera, i),
            "width": camera.width,
            "height": camera.height,
            **{key: values[i] for key, values in measured.per_view.items()},
            **{key: values[i] for key, values in extra.items()},
        }
        for i, camera in enumerate(cameras)
    ]
    floor = path_consistency(base_renders.renders, cameras, tolerance, threshold)
    consistency = {
        label: {"short_term": short.as_dict(), "long_term": long.as_dict()}
        for label, (short, long) in (("stylized", (measured.short, measured.long)), ("base", floor))
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
            "style_size": list(measured.style_size),
            "stroke_size": stroke_size,
        },
        # The metrics' means as evaluate_views takes them (the quality bench's numbers), then the extras'.
        "mean": {**measured.mean, **{key: _mean(values) for key, values in extra.items()}},
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
        ("SW patch", "sw_patches"),
        ("1/2", "sw_patches_half"),
        ("1/4", "sw_patches_quarter"),
        ("SW col", "sw_colors"),
        ("SSIM", "ssim"),
        ("GS", "structure"),
        ("texture kept", "texture_kept"),
        ("kept at 2x", "texture_kept_2x"),
        ("shapes", "shapes"),
        ("forms", "forms"),
        ("marks fine", "marks_fine"),
        ("mid", "marks_mid"),
        ("coarse", "marks_coarse"),
        ("elongation", "mark_elongation"),
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
        "SW patch, 1/2, 1/4: 7x7 patch sliced-Wasserstein distance to the painting at the cameras' size, half and a "
        "quarter; SW col: the same on colours; SSIM, GS (gradient structure), shapes (SSIM of the forms, sigma 3 px), "
        "forms (its structure term alone) to the base render; texture kept: correlation of the fine texture (sigma "
        "2 px) with the base render's; marks fine, mid, coarse: mark contrast, the render's own band-pass (sigma "
        "0.6/1.2, 1.2/2.4, 2.4/4.8 px) less the base render's, over the painting's at Stroke Size "
        f"{report['settings']['stroke_size']:g}; all on the pixels the base render covers, as dresg report and the "
        "quality benchmark measure them"
    )
    lines.append(
        "lower is better: SW patch, 1/2, 1/4, SW col, texture kept (less of the base's fine texture); "
        "higher is better: SSIM, GS, shapes, forms, CLIP-S, DINO-C; near 1 is best: marks (the painting's strength)"
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
