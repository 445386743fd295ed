"""Run a proposal backend on a photo and a style image, without a 3D scene, and save before/after PNGs.

Emulates the proposal side of Algorithm 1: each stage starts from the previous stage's proposal (where
the real loop starts from the refitted render) and runs its updates. Usage:

    python scripts/try_proposal.py CONTENT STYLE [--stages 6 --updates 6] [--out-before B.png]
        [--out-after A.png] [--every PREFIX] [--set NAME=PYTHON_LITERAL ...]

``--set`` overrides fields of the synth backend's ``SynthSettings`` (e.g. ``--set content_weight=0.6``).
"""

from __future__ import annotations

import argparse
import ast
import time

from dresg_addon.method.proposal.synth import SynthBackend  # noqa: E402
from dresg_addon.method.schedule import stage_timesteps  # noqa: E402
from dresg_addon.util.imageio import read_rgb, resize_image, to_array, to_tensor, write_image  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("content")
    parser.add_argument("style")
    parser.add_argument("--width", type=int, default=448)
    parser.add_argument("--height", type=int, default=320)
    parser.add_argument("--stages", type=int, default=6)
    parser.add_argument("--updates", type=int, default=6)
    parser.add_argument("--out-before", default="/tmp/proposal_before.png")
    parser.add_argument("--out-after", default="/tmp/proposal_after.png")
    parser.add_argument("--every", default="", help="also save each stage's proposal to this prefix")
    parser.add_argument("--set", nargs="*", default=[], help="SynthSettings overrides, NAME=PYTHON_LITERAL")
    args = parser.parse_args()

    overrides = {name: ast.literal_eval(value) for name, value in (item.split("=", 1) for item in args.set)}
    backend = SynthBackend(**overrides)
    content = to_tensor(resize_image(read_rgb(args.content), args.width, args.height)).clamp(0, 1)
    style = to_tensor(resize_image(read_rgb(args.style), args.width, args.height)).clamp(0, 1)
    write_image(args.out_before, to_array(content))

    proposal, started = content, time.perf_counter()
    for stage in stage_timesteps(args.stages, args.updates):
        backend.prepare_stage([proposal], style, [content], [None])
        state, energies = backend.propose(backend.encode(proposal), stage, style, content)
        proposal = backend.decode(state)
        print(f"stage {stage.index:2d} energy {energies[0]:.4f} -> {energies[-1]:.4f}")
        if args.every:
            write_image(f"{args.every}{stage.index:02d}.png", to_array(proposal))
    print(f"{args.stages} stages in {time.perf_counter() - started:.1f} s")
    write_image(args.out_after, to_array(proposal))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
