"""Make the README's before/after figure of the real bonsai scene with two shared styles.

    .venv/bin/python scripts/readme_figures.py [--preset preview] [--out docs/bonsai_before_after.png]

Needs ../shared/data (the bonsai scene and the public-domain paintings). Orbit cameras use the
scene's own up direction from its camera hint.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dresg_addon.config import preset  # noqa: E402
from dresg_addon.imageio import read_rgb, resize_image, write_image  # noqa: E402
from dresg_addon.io import read_scene  # noqa: E402
from dresg_addon.orbit import orbit_cameras  # noqa: E402
from dresg_addon.pipeline import stylize  # noqa: E402
from dresg_addon.raster import render_scene  # noqa: E402

DATA = REPO.parent / "shared" / "data"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="preview")
    parser.add_argument("--styles", nargs="+", default=["starry_night.jpg", "shipwreck.jpg"])
    parser.add_argument("--views", type=int, default=16, help="orbit cameras to choose active views from")
    parser.add_argument("--out", default=str(REPO / "docs" / "bonsai_before_after.png"))
    args = parser.parse_args()
    scene = read_scene(DATA / "scenes" / "bonsai-7k-mini.splat")
    hint = json.loads((DATA / "scenes" / "bonsai-7k-mini.camera_hint.json").read_text())
    cameras = orbit_cameras(scene, args.views, up=hint["cameraUp"], elevation_deg=25.0, radius_scale=0.8)
    shown = [cameras[0], cameras[args.views // 3]]
    rows = []
    before = [render_scene(scene, c).rgb.numpy() for c in shown]
    for name in args.styles:
        style = read_rgb(DATA / "styles" / name)
        started = time.perf_counter()
        result = stylize(scene, cameras, style, preset(args.preset), messages=print)
        print(f"{name}: {time.perf_counter() - started:.0f} s with preset {args.preset}")
        after = [render_scene(result.scene, c).rgb.numpy() for c in shown]
        thumb = resize_image(style, 224, 320)
        rows.append(np.concatenate([before[0], after[0], after[1], thumb], 1))
    write_image(args.out, np.concatenate(rows, 0))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
