"""``python -m dresg_addon stylize SCENE --style IMG --out OUT.ply``: the DReSG method end to end."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..method.backends import BACKENDS, slow_note
from ..method.config import DEFAULT_PRESET, PRESETS, SETTINGS, SH_REST_MODES, preset, preset_description
from ..method.medium import MEDIA, MEDIUM_LABELS
from ..util.errors import ConfigError, WriteError
from ._common import (
    add_background_option,
    add_device_option,
    add_scene_and_cameras,
    load_scene_and_cameras,
    parse_background,
    parse_device,
)

NAME = "stylize"
HELP = "Stylize a 3DGS scene after a style image (DReSG) and write the stylized scene."

# Options that map one-to-one onto StylizeConfig fields: (flag, field, type, help). The headless Blender script takes
# its help from here.
KNOBS = (
    ("--stages", "stages", int, "feedback stages N/S (default: the preset's)"),
    (
        "--max-views",
        "max_views",
        int,
        "active views at most, those that see the most (0: no cap; default: the preset's)",
    ),
    (
        "--stroke-size",
        "stroke_size",
        float,
        "the painting's scale against the view, in [0.25, 8]: 1 the painting resampled to the proposal size, "
        "2 twice that, so its strokes come out twice as large",
    ),
    (
        "--paint-scene",
        "scene_weight",
        float,
        "Paint <-> Scene in [0, 1]: how much of the scene's forms and light the painting may override "
        "(0 the painting's, 1 the scene's)",
    ),
    (
        "--scene-light",
        "scene_light",
        float,
        "how much of the scene's light above the stroke scale the proposals hold, in [0, 1], as a share "
        "of what Paint <-> Scene asks (0: the painting's marks set the light too)",
    ),
    ("--seed", "seed", int, "random seed (runs are deterministic for a seed)"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_and_cameras(parser)
    parser.add_argument("--style", required=True, metavar="IMG", help="the style image (png, jpg, exr, tif)")
    parser.add_argument("--out", required=True, metavar="OUT.ply", help="where to write the stylized scene")
    parser.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default=DEFAULT_PRESET,
        help="; ".join(f"{name}: {preset_description(name)}" for name in PRESETS),
    )
    parser.add_argument(
        "--proposal",
        choices=tuple(BACKENDS),
        help=f"proposal backend (default {PRESETS[DEFAULT_PRESET].proposal}); "
        + "; ".join(f"{entry.name}: {entry.description}" for entry in BACKENDS.values()),
    )
    parser.add_argument("--model", metavar="PATH", help="local Stable Diffusion 1.5 folder or .safetensors (sd15)")
    parser.add_argument(
        "--dino", metavar="PATH", help="local DINO weights for the fit loss's feature term (--geometry)"
    )
    parser.add_argument(
        "--medium",
        choices=MEDIA,
        help="what the painting is (default: the preset's, auto in standard and preview); "
        + "; ".join(f"{name}: {text[1]}" for name, text in MEDIUM_LABELS.items()),
    )
    parser.add_argument(
        "--sh-rest", choices=SH_REST_MODES, help="zero (default): drop view-dependent SH bands; keep: keep them"
    )
    parser.add_argument(
        "--proposal-size", metavar="WxH", help="the fit size the views are painted at (default 448x320)"
    )
    parser.add_argument(
        "--render-scale",
        type=float,
        default=1.0,
        help="render resolution relative to the cameras' own (lower is faster)",
    )
    geometry = parser.add_mutually_exclusive_group()
    geometry.add_argument(
        "--geometry", dest="geometry", action="store_true", default=None, help="optimise bounded geometry offsets"
    )
    geometry.add_argument(
        "--no-geometry", dest="geometry", action="store_false", help="freeze geometry (colour-only fast path)"
    )
    parser.add_argument("--views", metavar="I,J,...", help="use these camera indices as active views (skip selection)")
    add_background_option(parser)
    add_device_option(
        parser,
        use="where the networks run (sd15 proposals, DINO features); the rasterizer and the colour fit run on "
        "the CPU. Without it, sd15 takes the GPU when there is one and DINO the CPU",
        default=None,
    )
    for flag, _, kind, text in KNOBS:
        parser.add_argument(flag, type=kind, help=text)
    parser.add_argument(
        "--save-views", metavar="DIR", help="write each active view's render, proposal, target and residual per stage"
    )
    parser.add_argument("--log", metavar="PATH", help="per-stage JSON-lines log (default: OUT.ply with .log.jsonl)")
    parser.add_argument(
        "--checkpoint-dir",
        metavar="DIR",
        help="stage checkpoints; a rerun with the same settings resumes (default: OUT.ply with .checkpoint)",
    )
    selection = parser.add_mutually_exclusive_group()
    selection.add_argument(
        "--mask",
        metavar="FILE",
        help="stylize only these splats: a .npy bool mask or index array, or a text file of splat indices; "
        "every other splat is written back unchanged",
    )
    selection.add_argument(
        "--box",
        metavar="X0,Y0,Z0,X1,Y1,Z1",
        help="stylize only the splats whose centres lie in this axis-aligned box (scene coordinates)",
    )
    parser.add_argument(
        "--strength",
        type=float,
        default=1.0,
        help="how far the written colours go from the scene's own (0) to the stylized ones (1, the default)",
    )
    parser.add_argument("--quiet", action="store_true", help="print only the summary")


def config_from_args(args):
    overrides = {field: getattr(args, flag[2:].replace("-", "_")) for flag, field, _, _ in KNOBS}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    for name, field in (
        ("proposal", "proposal"),
        ("model", "model_path"),
        ("sh_rest", "sh_rest"),
        ("medium", "medium"),
    ):
        if getattr(args, name):
            overrides[field] = getattr(args, name)
    if args.geometry is not None:
        overrides["optimize_geometry"] = args.geometry
    overrides["background"] = parse_background(args.background)
    if args.proposal_size:
        try:
            width, height = (int(v) for v in args.proposal_size.lower().split("x"))
        except ValueError:
            raise ConfigError(f"--proposal-size must look like 448x320 (got {args.proposal_size!r})") from None
        overrides["proposal_width"], overrides["proposal_height"] = width, height
    assert set(overrides) <= set(SETTINGS)  # the tables above name real settings
    return preset(args.preset, **overrides)


def selection_from_args(args, scene):
    """The --mask file's or the --box's selection (None: every splat)."""
    import numpy as np

    if args.box:
        try:
            bounds = np.array([float(v) for v in args.box.split(",")], np.float64)
        except ValueError:
            bounds = np.zeros(0)
        if bounds.size != 6 or not np.isfinite(bounds).all():
            raise ConfigError(f"--box must be six numbers X0,Y0,Z0,X1,Y1,Z1 (got {args.box!r})")
        low, high = np.minimum(bounds[:3], bounds[3:]), np.maximum(bounds[:3], bounds[3:])
        inside = np.all((scene.means >= low) & (scene.means <= high), axis=1)
        if not inside.any():
            raise ConfigError(f"--box {args.box}: no splat centre lies inside it")
        return inside
    if not args.mask:
        return None
    path = Path(args.mask)
    try:
        if path.suffix.lower() == ".npy":
            values = np.load(path, allow_pickle=False)
        else:
            values = np.array(path.read_text(encoding="utf-8").replace(",", " ").split(), dtype=np.int64)
    except (OSError, ValueError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: cannot read a selection ({error})") from None
    if values.dtype != bool and not np.issubdtype(values.dtype, np.integer):
        raise ConfigError(f"{path}: a selection is a bool mask or splat indices, not {values.dtype}")
    return values.reshape(-1)


def room_needed(scene, cameras, config, out: Path, log_path: Path, checkpoint_dir: Path, views_dir) -> dict[Path, int]:
    """What a run writes, by folder, at most: the stylized scene, the checkpoint (parameters, Adam's two
    moments, each view's state), the log, and with ``views_dir`` four 8-bit images per view and stage."""
    from ..scene.io import encoded_size

    views = min(len(cameras), config.max_views or len(cameras))
    pixels = config.proposal_width * config.proposal_height
    per_splat = 3 + (10 if config.optimize_geometry else 0)  # colours, and mean, scale and rotation offsets
    needs: dict[Path, int] = {}
    for folder, size in (
        (out.parent, encoded_size(scene, out)),
        (checkpoint_dir, 3 * 4 * per_splat * len(scene) + 4 * 3 * pixels * views + 2**20),
        (log_path.parent, 2**20),
        *([(Path(views_dir), 4 * 3 * pixels * views * (config.stages + 1))] if views_dir else []),
    ):
        needs[folder] = needs.get(folder, 0) + size
    return needs


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def run(args) -> int:
    from ..method.bookkeeping import ProgressLines
    from ..method.config import check_run_settings
    from ..method.loop import selection_mask, stylize
    from ..method.medium import check_painting
    from ..method.views import scaled_cameras
    from ..scene.io import write_scene
    from ..util.fileutil import check_room
    from ..util.imageio import STYLE_MAX_SIDE, read_rgb

    config = config_from_args(args)
    check_run_settings(config)
    device = None if args.device is None else parse_device(args.device)
    style = read_rgb(args.style, max_side=STYLE_MAX_SIDE)  # before the scene, so a bad style path fails at once
    check_painting(style, args.style)
    scene, cameras = load_scene_and_cameras(args)
    if not (args.render_scale > 0 and args.render_scale == args.render_scale):
        raise ConfigError(f"--render-scale must be > 0 (got {args.render_scale})")
    cameras = scaled_cameras(cameras, args.render_scale)
    views = None
    if args.views:
        try:
            views = [int(v) for v in args.views.split(",")]
        except ValueError:
            raise ConfigError(f"--views must be comma-separated camera indices (got {args.views!r})") from None
    selection = selection_from_args(args, scene)
    try:
        mask = selection_mask(selection, len(scene), config)  # checked before any note
    except ConfigError as error:
        if not args.mask:
            raise
        raise ConfigError(f"--mask {args.mask}: {error}") from None  # which file the selection came from
    out = Path(args.out)
    log_path = Path(args.log) if args.log else out.with_suffix(".log.jsonl")
    checkpoint_dir = Path(args.checkpoint_dir) if args.checkpoint_dir else out.with_suffix(".checkpoint")
    # A long run must not lose its work to an output problem found at its end.
    check_room(room_needed(scene, cameras, config, out, log_path, checkpoint_dir, args.save_views))
    note = None if args.quiet else slow_note(config, device)
    if note:
        print(f"note: {note}", file=sys.stderr)
    if not args.quiet and config.optimize_geometry and not _cuda_available():
        plan = config.plan()
        steps = config.stages * plan.fit_steps + plan.post_steps
        print(
            f"note: geometry offsets are on: each of the {steps} fit steps renders every active view with "
            "gradients (about 0.6 s per view for a 270k-splat scene at 448x320 on 2 cores, so hours with 16 "
            "views); --preset cpu keeps the schedule with colour-only fitting. The time left shows once the first stage has ended.",
            file=sys.stderr,
        )

    lines = ProgressLines()

    def progress(p):
        # The run's fraction, where it is, the fit's RMSE and the time left (bookkeeping.Progress): the first
        # report of each phase of each stage, and at most one line every 2 s in between.
        line = None if args.quiet else lines.line(p)
        if line is not None:
            print(line, file=sys.stderr, flush=True)

    messages = (lambda _m: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    started = time.perf_counter()
    result = stylize(
        scene,
        cameras,
        style,
        config,
        views=views,
        progress=args.threads.wrap(progress),
        checkpoint_dir=checkpoint_dir,
        log_path=log_path,
        save_views_dir=args.save_views,
        messages=messages,
        strength=args.strength,
        mask=mask,
        device=device,
        dino_path=args.dino or "",
    )
    try:
        write_scene(result.scene, out)
    except WriteError as error:  # the stages are in the checkpoint: a rerun resumes after the last one
        raise WriteError(f"{error}; {checkpoint_dir} keeps the run, so the same command resumes it") from None
    print(
        f"wrote {out} ({len(result.scene)} splats, {result.stylized} of them stylized, "
        f"{len(result.selection.indices)} active views, {time.perf_counter() - started:.1f} s); log {log_path}"
    )
    return 0
