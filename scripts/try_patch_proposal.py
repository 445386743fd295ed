"""Run the ``patch`` proposal backend on a photo and a style image and save before/after PNGs.

Emulates the proposal side of Algorithm 1 without a 3D scene: each stage re-encodes the previous
stage's proposal (where the real loop re-encodes the refitted render), runs its 10 latent updates and
decodes. Usage:

    python scripts/try_patch_proposal.py CONTENT STYLE [--out-before B.png] [--out-after A.png]
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dresg_addon.proposal import EnergyTerms, optimize_proposal  # noqa: E402
from dresg_addon.proposal.patch import PatchBackend  # noqa: E402
from dresg_addon.schedule import stage_timesteps  # noqa: E402


def read_image(path: str, width: int, height: int) -> torch.Tensor:  # -> [3, H, W]
    buf = oiio.ImageBuf(path)
    pixels = buf.get_pixels(oiio.FLOAT)
    if pixels is None:
        raise SystemExit(f"{path}: cannot read ({buf.geterror()})")
    image = torch.from_numpy(np.ascontiguousarray(pixels[..., :3])).permute(2, 0, 1)
    if image.shape[0] == 1:
        image = image.expand(3, -1, -1)
    return F.interpolate(image[None], size=(height, width), mode="area")[0].clamp(0, 1)


def write_image(path: str, image: torch.Tensor) -> None:  # image [3, H, W]
    pixels = (image.permute(1, 2, 0).clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.UINT8)
    buf = oiio.ImageBuf(spec)
    buf.set_pixels(oiio.ROI(0, pixels.shape[1], 0, pixels.shape[0], 0, 1, 0, 3), np.ascontiguousarray(pixels))
    if not buf.write(path):
        raise SystemExit(f"{path}: cannot write ({buf.geterror()})")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("content")
    parser.add_argument("style")
    parser.add_argument("--width", type=int, default=448)
    parser.add_argument("--height", type=int, default=320)
    parser.add_argument("--stages", type=int, default=20)
    parser.add_argument("--out-before", default="/tmp/patch_before.png")
    parser.add_argument("--out-after", default="/tmp/patch_after.png")
    parser.add_argument("--every", default="", help="also save each stage's proposal to this prefix")
    parser.add_argument("--set", nargs="*", default=[], help="PatchSettings overrides, NAME=PYTHON_LITERAL")
    args = parser.parse_args()

    overrides = {}
    for item in args.set:
        name, value = item.split("=", 1)
        overrides[name] = ast.literal_eval(value)
    backend = PatchBackend(**overrides)
    content = read_image(args.content, args.width, args.height)
    style = read_image(args.style, args.width, args.height)
    terms = EnergyTerms()
    write_image(args.out_before, content)

    proposal = content
    steps, started = 0, time.perf_counter()
    for stage in stage_timesteps(num_stages=args.stages):
        state = backend.encode(proposal)
        state, energies = optimize_proposal(backend, state, stage.timesteps, style, content, terms)
        proposal = backend.decode(state).detach()
        steps += len(stage.timesteps)
        print(f"stage {stage.index:2d} t={stage.state:3d} energy {energies[0]:.4f} -> {energies[-1]:.4f}")
        if args.every:
            write_image(f"{args.every}{stage.index:02d}.png", proposal)
    elapsed = time.perf_counter() - started
    print(f"{steps} steps in {elapsed:.1f} s: {elapsed / steps:.3f} s per step")
    write_image(args.out_after, proposal)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
