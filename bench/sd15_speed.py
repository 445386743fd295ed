# SPDX-License-Identifier: GPL-3.0-or-later
"""How fast the sd15 proposals run, on a GPU or the CPU, without downloading a model.

    .venv/bin/python bench/sd15_speed.py [--device cuda] [--dtype float16] [--width 448 --height 320]
        [--updates 10] [--run bonsai:starry_night] [--preset preview] [--json FILE]

Stable Diffusion 1.5's architecture (its real U-Net, VAE and text-encoder configurations) with random
weights, saved to a temporary folder and loaded through the backend's own loader: the time of a forward
and backward pass does not depend on the weights' values, so this measures what a user with the real
weights waits for. The proposals it makes are noise and are not looked at.

It times one stage of one view (encode the render, ``updates`` fresh-Adam steps of the attention energy,
decode), next to ``estimate_cpu_seconds``'s CPU figure for the same work, and with ``--run`` a whole
``stylize`` of a quality-bench case with ``proposal=sd15`` (16 orbit views), the rasterizer and the colour
fit on the CPU as always.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import harness  # noqa: E402


def random_sd15(folder: Path, dtype) -> Path:
    """SD1.5's three models with random weights, saved as a diffusers folder."""
    import torch
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    from dresg_addon.method.proposal.sd15_configs import (
        SD15_TEXT_ENCODER_CONFIG,
        SD15_UNET_CONFIG,
        SD15_VAE_CONFIG,
    )

    torch.manual_seed(0)
    models = {
        "unet": UNet2DConditionModel.from_config(SD15_UNET_CONFIG),
        "vae": AutoencoderKL.from_config(SD15_VAE_CONFIG),
        "text_encoder": CLIPTextModel(CLIPTextConfig(**SD15_TEXT_ENCODER_CONFIG)),
    }
    for name, model in models.items():
        model.to(dtype).save_pretrained(folder / name)
    return folder


def synchronize(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_one_stage(backend, device: str, width: int, height: int, updates: int) -> dict:
    """Seconds of one view's stage (encode, ``updates`` energy steps, decode): a warm-up, then the mean of 3."""
    import torch

    from dresg_addon.method.proposal import EnergyTerms, optimize_proposal

    generator = torch.Generator().manual_seed(0)
    render, style, content = (torch.rand(3, height, width, generator=generator) for _ in range(3))
    terms = EnergyTerms(content_weight=0.15)
    timesteps = list(range(951, 951 - 5 * updates, -5))

    def stage():
        latent, _ = optimize_proposal(backend, backend.encode(render), timesteps, style, content, terms)
        backend.decode(latent)

    stage()
    synchronize(device)
    seconds = []
    for _ in range(3):
        started = time.perf_counter()
        stage()
        synchronize(device)
        seconds.append(time.perf_counter() - started)
    return {"stage_view_seconds": sum(seconds) / len(seconds), "runs": seconds}


def whole_run(case: str, preset_name: str, folder: Path, device: str) -> dict:
    """A quality-bench case stylized with ``proposal=sd15``: wall time, stages run, peak memory."""
    import quality
    import torch

    from dresg_addon.method.config import preset
    from dresg_addon.method.loop import stylize

    scene_name, style_name = case.split(":")
    scene, train, _, style = quality.load_case(
        {"scene": scene_name, "style": style_name, "views": 16, "width": 448, "height": 320}
    )
    config = preset(preset_name, proposal="sd15", model_path=str(folder))
    started = time.perf_counter()
    result = stylize(scene, train, style, config, device=device)
    seconds = time.perf_counter() - started
    stages = [e for e in result.log if e.get("stage") != "post"]
    out = {
        "case": case,
        "preset": preset_name,
        "seconds": seconds,
        "stages": len(stages),
        "of_stages": config.stages,
        "proposal_seconds": sum(e.get("proposal_seconds", 0.0) for e in stages),
        "peak_rss_mb": harness.peak_rss_bytes() / 2**20,
    }
    if device.startswith("cuda"):
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--dtype", default="float16", choices=("float16", "bfloat16", "float32"))
    parser.add_argument("--width", type=int, default=448)
    parser.add_argument("--height", type=int, default=320)
    parser.add_argument("--updates", type=int, default=10, help="energy steps per stage (the paper's 10)")
    parser.add_argument("--run", metavar="SCENE:STYLE", help="also stylize a quality-bench case with sd15")
    parser.add_argument("--preset", default="preview")
    parser.add_argument("--json", metavar="FILE")
    args = parser.parse_args()

    import torch

    from dresg_addon.method.backends import estimate_cpu_seconds
    from dresg_addon.method.proposal.sd15 import SD15Backend

    harness.apply_thread_policy()
    dtype = getattr(torch, args.dtype)
    report = {"device": args.device, "dtype": args.dtype, "size": f"{args.width}x{args.height}"}
    if args.device.startswith("cuda"):
        report["gpu"] = torch.cuda.get_device_name(args.device)
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        folder = random_sd15(Path(tmp) / "sd15-random", dtype)
        backend = SD15Backend(folder, device=args.device, dtype=dtype)
        report["load_seconds"] = time.perf_counter() - started
        report.update(time_one_stage(backend, args.device, args.width, args.height, args.updates))
        report["cpu_estimate_stage_view_seconds"] = estimate_cpu_seconds(
            1, stages=1, updates_per_stage=args.updates, width=args.width, height=args.height
        )
        del backend
        write(report, args.json)
        if args.run:
            report["run"] = whole_run(args.run, args.preset, folder, args.device)
            write(report, args.json)
    return 0


def write(report: dict, path: str | None) -> None:
    """Print the report; with ``path`` also write it atomically (a failed write: one line, exit 1)."""
    from dresg_addon.util.errors import DresgError
    from dresg_addon.util.fileutil import atomic_write_bytes

    text = json.dumps(report, indent=1)
    print(text, flush=True)
    if path:
        try:
            atomic_write_bytes(path, text.encode("utf-8"))
        except DresgError as error:
            raise SystemExit(f"sd15_speed: {error}") from None


if __name__ == "__main__":
    raise SystemExit(main())
