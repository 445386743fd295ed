"""What mark contrast reads on a slanted plane whose marks every view agrees on: each painting laid flat on the demo's
ground.

    .venv/bin/python bench/planar_marks.py                     # the shared paintings and the demo's, about 1 min each
    .venv/bin/python bench/planar_marks.py --styles the_scream --quick

The demo's ground splats take the painting by a planar map (each splat the painting's colour at its centre, the
painting at the evaluation's scale, the view's size x Stroke Size, one painting pixel to a screen pixel across the
ground's centre in novel view 3; mirrored past its edges); the objects keep their colours. The quality bench's 16
novel views then measure it as they measure a stylization. The marks are the painting's own and the same in every
view, so what lifts their bands above 1 is the ground's slant (its marks foreshortened into finer bands) and the
objects' edges against a new ground: the reading of a perfect stylization of this scene.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import numpy as np
import quality  # bench/, beside this file
import torch
import torch.nn.functional as F

from dresg_addon.evaluation.views import MARK_KEYS, base_views, evaluate_views
from dresg_addon.scene.camera import Camera
from dresg_addon.scene.gaussians import SH_C0, GaussianScene

GROUND_HEIGHT = 0.02  # |y| below this: a ground splat (scene.demo's ground is the plane y = 0)
SCALE_VIEW = 3  # the novel view whose scale across the ground's centre sets the map's


def screen_scale(camera: Camera) -> float:
    """Screen pixels per world unit along the view's horizontal, on the ground, at the world origin."""
    world_to_camera = np.asarray(camera.world_to_camera, dtype=np.float64)
    right = world_to_camera[0, :3].copy()
    right[1] = 0.0  # along the ground
    right /= np.linalg.norm(right)

    def project(point):
        x, y, z = world_to_camera[:3, :3] @ point + world_to_camera[:3, 3]
        return np.array([camera.fx * x / z, camera.fy * y / z])

    return float(np.linalg.norm(project(0.5 * right) - project(-0.5 * right)))


def _mirrored(t: np.ndarray, n: int) -> np.ndarray:
    t = np.mod(t, 2 * n)
    return np.where(t >= n, 2 * n - 1 - t, t)


def painted_ground(scene: GaussianScene, painting: np.ndarray, camera: Camera, stroke_size: float) -> GaussianScene:
    """``scene`` (the demo's) with its ground splats coloured by the painting laid flat on it."""
    width = int(round(camera.width * stroke_size))
    height = int(round(painting.shape[0] / painting.shape[1] * width))
    image = torch.from_numpy(np.ascontiguousarray(painting, dtype=np.float32)).permute(2, 0, 1)[None]
    image = F.interpolate(image, size=(height, width), mode="area")
    means = scene.means.astype(np.float64)
    ground = np.abs(means[:, 1]) < GROUND_HEIGHT
    scale = screen_scale(camera)
    u = _mirrored(width / 2 + means[ground, 0] * scale, width)
    v = _mirrored(height / 2 + means[ground, 2] * scale, height)
    grid = torch.from_numpy(np.stack([u / (width - 1) * 2 - 1, v / (height - 1) * 2 - 1], -1)).float()[None, None]
    colours = F.grid_sample(image, grid, align_corners=True)[0, :, 0].T.numpy()
    sh_dc = scene.sh_dc.copy()
    sh_dc[ground] = (colours - 0.5) / SH_C0
    return replace(scene, sh_dc=sh_dc.astype(np.float32))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--styles", help="comma-separated style names (default: every shared painting and the demo's)")
    parser.add_argument("--stroke-size", type=float, default=1.5, help="the painting's scale (default 1.5, standard's)")
    parser.add_argument("--quick", action="store_true", help="smoke run: 4 cameras at 112x80")
    args = parser.parse_args(argv)
    shared = sorted(path.stem for path in (quality.SHARED / "styles").glob("*.jpg"))
    names = [name for name in args.styles.split(",") if name] if args.styles else [*shared, "demo"]
    size = quality.QUICK if args.quick else quality.FULL
    print("| painting | marks fine | mid | coarse |")
    print("|---|---:|---:|---:|")
    for name in names:
        if name not in quality.GENERATED and quality.style_path(name) is None:
            print(f"planar_marks: no painting {name!r} (shared data absent?)", file=sys.stderr)
            continue
        scene, _, novel, style = quality.load_case({"scene": "demo", "style": name, **size})
        painted = painted_ground(scene, style, novel[min(SCALE_VIEW, len(novel) - 1)], args.stroke_size)
        measured = evaluate_views(painted, base_views(scene, novel), style, stroke_size=args.stroke_size)
        print(f"| {name} | " + " | ".join(f"{measured.mean[key]:.2f}" for key in MARK_KEYS) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
