"""What mark contrast reads on a slanted plane whose marks every view agrees on: each painting laid flat on the demo's
ground.

    .venv/bin/python bench/planar_marks.py                     # the shared paintings and the demo's, about 9 min
    .venv/bin/python bench/planar_marks.py --styles the_scream --quick

The painting is laid on the ground plane by a planar map (the painting at the view's width x Stroke Size, its aspect
kept, one painting pixel to a screen pixel across the ground's centre in novel view 3; mirrored past its edges), and the demo's splats are coloured two ways: each ground splat the painting at its centre (the objects as
they are), and every splat's colour solved over the 16 training views to draw the flat painting where they see the
ground and the scene as it is elsewhere (what a colour fit to perfectly consistent targets draws). The quality
bench's 16 novel views then measure each as they measure a stylization. The marks are the painting's own and the
same in every view, so what lifts their bands above 1 is the ground's slant (its marks foreshortened into finer
bands) and the objects' edges against a new ground: the reading of a perfect stylization of this scene.
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
from dresg_addon.method.color_solve import ColorSolveSettings, LinearViews, solve_colors
from dresg_addon.raster import ColorOnlyRenderer, geometry_tensors, render_scene
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


class FlatPainting:
    """The painting laid flat on the ground (y = 0): its colour at any ground point (x, z)."""

    def __init__(self, painting: np.ndarray, camera: Camera, stroke_size: float):
        self.width = int(round(camera.width * stroke_size))
        self.height = int(round(painting.shape[0] / painting.shape[1] * self.width))
        image = torch.from_numpy(np.ascontiguousarray(painting, dtype=np.float32)).permute(2, 0, 1)[None]
        self.image = F.interpolate(image, size=(self.height, self.width), mode="area")
        self.scale = screen_scale(camera)

    def at(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:  # [K] each -> [K, 3]
        u = _mirrored(self.width / 2 + x * self.scale, self.width) / (self.width - 1) * 2 - 1
        v = _mirrored(self.height / 2 + z * self.scale, self.height) / (self.height - 1) * 2 - 1
        grid = torch.from_numpy(np.stack([u, v], -1)).float()[None, None]
        return F.grid_sample(self.image, grid, align_corners=True)[0, :, 0].T.numpy()


def painted_ground(scene: GaussianScene, painting: np.ndarray, camera: Camera, stroke_size: float) -> GaussianScene:
    """``scene`` (the demo's) with each ground splat the painting laid flat on it at the splat's centre."""
    means = scene.means.astype(np.float64)
    ground = np.abs(means[:, 1]) < GROUND_HEIGHT
    sh_dc = scene.sh_dc.copy()
    sh_dc[ground] = (FlatPainting(painting, camera, stroke_size).at(means[ground, 0], means[ground, 2]) - 0.5) / SH_C0
    return replace(scene, sh_dc=sh_dc.astype(np.float32))


def flat_target(scene: GaussianScene, camera: Camera, flat: FlatPainting) -> torch.Tensor:  # -> [3, H, W]
    """What ``camera`` would see with the painting on the ground itself: the scene's render, and where the surface
    it draws is the ground plane (the render's depth within 2% of the plane's along the ray), the flat painting."""
    out = render_scene(scene, camera)
    image, depth = out.rgb.numpy().reshape(-1, 3).copy(), out.depth.numpy().reshape(-1)
    v, u = np.divmod(np.arange(camera.width * camera.height), camera.width)
    rays = np.stack([(u + 0.5 - camera.cx) / camera.fx, (v + 0.5 - camera.cy) / camera.fy, np.ones(u.size)], 1)
    world = rays @ np.asarray(camera.camera_to_world, dtype=np.float64)[:3, :3].T  # z = 1 along each ray
    centre = np.asarray(camera.center, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -centre[1] / world[:, 1]  # the camera-space z at which each ray meets y = 0
    hit = centre + t[:, None] * world
    ground = (t > 0) & (depth > 0) & (np.abs(depth - t) <= 0.02 * t) & (hit[:, 0] ** 2 + hit[:, 2] ** 2 <= 9.0)
    image[ground] = flat.at(hit[ground, 0], hit[ground, 2])
    return torch.from_numpy(image.reshape(camera.height, camera.width, 3)).permute(2, 0, 1).float()


def fitted_ground(scene: GaussianScene, painting: np.ndarray, cameras, camera: Camera, stroke_size: float):
    """``scene`` with every splat's colour solved (bounded least squares over ``cameras``) to draw the flat
    painting on the ground and the scene as it is elsewhere: what a colour fit to perfectly consistent targets gives."""
    flat = FlatPainting(painting, camera, stroke_size)
    targets = [flat_target(scene, c, flat) for c in cameras]
    tensors = geometry_tensors(scene)
    renderers = [ColorOnlyRenderer(*tensors, c) for c in cameras]
    views = LinearViews([r.linear_map() for r in renderers], [r.background for r in renderers])
    start = torch.from_numpy(np.minimum(scene.base_colors, 1.0)).float()
    colors = solve_colors(views, targets, start, ColorSolveSettings(max_rounds=12)).colors.numpy()
    return replace(scene, sh_dc=((colors - 0.5) / SH_C0).astype(np.float32))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--styles", help="comma-separated style names (default: every shared painting and the demo's)")
    parser.add_argument("--stroke-size", type=float, default=1.5, help="the painting's scale (default 1.5, standard's)")
    parser.add_argument("--quick", action="store_true", help="smoke run: 4 cameras at 112x80")
    args = parser.parse_args(argv)
    shared = sorted(path.stem for path in (quality.SHARED / "styles").glob("*.jpg"))
    names = [name for name in args.styles.split(",") if name] if args.styles else [*shared, "demo"]
    size = quality.QUICK if args.quick else quality.FULL
    print("| painting | each splat at its centre: marks fine / mid / coarse | fitted to the flat painting |")
    print("|---|---|---|")
    for name in names:
        if name not in quality.GENERATED and quality.style_path(name) is None:
            print(f"planar_marks: no painting {name!r} (shared data absent?)", file=sys.stderr)
            continue
        scene, train, novel, style = quality.load_case({"scene": "demo", "style": name, **size})
        scale_view = novel[min(SCALE_VIEW, len(novel) - 1)]
        base = base_views(scene, novel)
        cells = []
        for painted in (
            painted_ground(scene, style, scale_view, args.stroke_size),
            fitted_ground(scene, style, train, scale_view, args.stroke_size),
        ):
            measured = evaluate_views(painted, base, style, stroke_size=args.stroke_size)
            cells.append(" / ".join(f"{measured.mean[key]:.2f}" for key in MARK_KEYS))
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
