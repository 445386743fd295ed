"""``python -m dresg_addon info SCENE``: what a scene file holds, and whether it looks sane."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from ..scene.io import SceneReadResult, read_scene_detailed
from ..scene.io.splat import opacity_from_logit

NAME = "info"
HELP = "Print a scene file's format, splat count, SH degree, bounds, scale and opacity statistics."

PERCENTILES = (0, 1, 50, 99, 100)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE", help="scene file: graphdeco .ply, .splat or compressed .ply")
    parser.add_argument(
        "--drop-invalid",
        action="store_true",
        help="drop splats with non-finite values (NaN/Inf) instead of refusing the file; says how many",
    )
    parser.add_argument("--json", action="store_true", help="print the statistics as one JSON object")


def scene_summary(result: SceneReadResult) -> dict:
    """Plain-number statistics of a read scene (JSON-serialisable)."""
    scene = result.scene
    low, high = scene.bounds()
    robust_low, robust_high = scene.bounds(0.01)
    # Percentiles of the log-scales, then exp: the same order statistics, and no float32 overflow.
    scale_percentiles = np.exp(np.minimum(np.percentile(scene.log_scales.astype(np.float64), PERCENTILES), 700.0))
    opacities = opacity_from_logit(scene.opacity_logits)
    return {
        "format": result.format.value,
        "file_bytes": result.file_size,
        "splats": len(scene),
        "dropped_invalid": result.dropped,
        "sh_degree": scene.sh_degree,
        "normals": scene.normals is not None,
        "extras": list(scene.extras),
        "bounds_min": low.tolist(),
        "bounds_max": high.tolist(),
        "robust_bounds_min": robust_low.tolist(),
        "robust_bounds_max": robust_high.tolist(),
        "scale_percentiles": dict(zip(PERCENTILES, scale_percentiles.tolist())),
        "opacity_mean": float(opacities.mean()),
        "opacity_percentiles": dict(zip(PERCENTILES, np.percentile(opacities, PERCENTILES).tolist())),
        # Never drawn by the rasterizer; the margin keeps 8-bit alphas of exactly 1/255 out.
        "opacity_below_1_255": float((opacities < (1.0 - 1e-4) / 255.0).mean()),
    }


def _vector(values: list[float]) -> str:
    return "(" + ", ".join(f"{v:.4g}" for v in values) + ")"


def _percentiles(values: dict) -> str:
    names = {0: "min", 100: "max"}
    return "  ".join(f"{names.get(p, f'p{p}')} {v:.4g}" for p, v in values.items())


def format_summary(path: str, summary: dict) -> str:
    extras = ", ".join(summary["extras"]) or "none"
    lines = [
        f"file:            {path} ({summary['file_bytes'] / 1e6:.2f} MB)",
        f"format:          {summary['format']}",
        f"splats:          {summary['splats']:,}"
        + (f" ({summary['dropped_invalid']:,} dropped for non-finite values)" if summary["dropped_invalid"] else ""),
        f"SH degree:       {summary['sh_degree']}",
        f"normals:         {'yes' if summary['normals'] else 'no'}; extra properties: {extras}",
        f"bounds:          min {_vector(summary['bounds_min'])}  max {_vector(summary['bounds_max'])}",
        f"bounds 1%-99%:   min {_vector(summary['robust_bounds_min'])}  max {_vector(summary['robust_bounds_max'])}",
        f"scale (exp):     {_percentiles(summary['scale_percentiles'])}  (all axes)",
        f"opacity:         mean {summary['opacity_mean']:.3g}  {_percentiles(summary['opacity_percentiles'])}  "
        f"({summary['opacity_below_1_255']:.1%} below 1/255)",
    ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    result = read_scene_detailed(args.scene, drop_invalid=args.drop_invalid)
    summary = scene_summary(result)
    if args.json:
        print(json.dumps({"file": args.scene, **summary}))
    else:
        if result.dropped:
            print(f"note: dropped {result.dropped:,} splats with non-finite values", file=sys.stderr)
        print(format_summary(args.scene, summary))
    return 0
