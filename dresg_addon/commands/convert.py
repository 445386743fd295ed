"""``python -m dresg_addon convert IN OUT``: convert a scene between formats, chosen by extension."""

from __future__ import annotations

import argparse
import sys

from ..scene.gaussians import GaussianScene
from ..scene.io import SceneFormat, clamped_note, output_format, read_scene_detailed, write_scene

NAME = "convert"
HELP = "Convert a scene between graphdeco .ply, PlayCanvas .compressed.ply and .splat (format by extension)."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "input", metavar="IN", help="scene file to read: graphdeco .ply, .splat or compressed .ply (detected)"
    )
    parser.add_argument(
        "output",
        metavar="OUT",
        help="file to write, replaced atomically if it exists (may be IN). Its extension picks the format: "
        ".ply = graphdeco (lossless), .compressed.ply = PlayCanvas (quantised, Morton-ordered), "
        ".splat = antimatter15 (8-bit colour, opacity and rotation, no SH rest)",
    )
    parser.add_argument(
        "--drop-invalid",
        action="store_true",
        help="drop splats with non-finite values (NaN/Inf) instead of refusing the input; says how many",
    )


def lossy_notes(scene: GaussianScene, fmt: SceneFormat) -> list[str]:
    """What the output format cannot keep of ``scene``."""
    notes: list[str] = []
    if fmt is SceneFormat.GRAPHDECO_PLY:
        return notes
    if fmt is SceneFormat.SPLAT and scene.sh_degree:
        notes.append(f".splat keeps no SH rest: SH degree {scene.sh_degree} -> 0")
    # graphdeco writes all-zero normals; only real ones are worth a note.
    has_normals = scene.normals is not None and bool(scene.normals.any())
    dropped = (["normals"] if has_normals else []) + list(scene.extras)
    if dropped:
        notes.append(f"{fmt.value} keeps no {', '.join(dropped)}")
    if fmt is SceneFormat.SPLAT:
        notes.append(".splat stores colour, opacity and rotation in 8 bits")
    else:
        notes.append("compressed PLY quantises every value and stores the splats in Morton order")
    return notes


def run(args: argparse.Namespace) -> int:
    fmt = output_format(args.output)  # an unusable OUT fails before reading IN
    result = read_scene_detailed(args.input, drop_invalid=args.drop_invalid)
    if result.dropped:
        print(f"note: dropped {result.dropped:,} splats with non-finite values", file=sys.stderr)
    if result.clamped:
        print(f"note: {clamped_note(result.clamped)}", file=sys.stderr)
    for note in lossy_notes(result.scene, fmt):
        print(f"note: {note}", file=sys.stderr)
    write_scene(result.scene, args.output)
    degree = 0 if fmt is SceneFormat.SPLAT else result.scene.sh_degree
    print(f"wrote {args.output} ({fmt.value}): {len(result.scene):,} splats, SH degree {degree}")
    return 0
