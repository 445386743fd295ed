"""The README's Strength and selection figure, from engine renders of what the Blender object shows.

    .venv/bin/python scripts/strength_selection_figure.py [--out docs/strength_selection.png]

Top row: the demo scene stylized after the demo painting (``preview``, 8 orbit views) shown at Strength
0, 0.5 and 1 (``scene.gaussians.blend_colors``, as the slider blends). Bottom row: the far half of the
scene (x < 0) stylized after the Starry Night, then the near half after a generated line drawing on top
of it (``stylize(mask=...)``: the first painting's colours stay), and the Starry Night. A novel view
between the cameras, rendered at 3x and cropped around the object. Needs ../shared/data/styles.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from dresg_addon.method.config import preset  # noqa: E402
from dresg_addon.method.loop import stylize  # noqa: E402
from dresg_addon.raster import render_scene  # noqa: E402
from dresg_addon.scene.demo import demo_scene, demo_style_image, line_drawing_image  # noqa: E402
from dresg_addon.scene.gaussians import blend_colors  # noqa: E402
from dresg_addon.scene.orbit import orbit_cameras  # noqa: E402
from dresg_addon.util.imageio import at_scale, object_window, read_rgb, write_image  # noqa: E402

WIDTH, HEIGHT = 448, 320


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(REPO / "docs" / "strength_selection.png"))
    args = parser.parse_args()
    scene = demo_scene()
    cameras = orbit_cameras(scene, 8, width=WIDTH, height=HEIGHT)
    view = orbit_cameras(scene, 8, width=3 * WIDTH, height=3 * HEIGHT, azimuth_offset_deg=22.5)[1]
    config = preset("preview")
    starry = read_rgb(REPO.parent / "shared" / "data" / "styles" / "starry_night.jpg")
    window = []

    def render(candidate) -> np.ndarray:
        image = render_scene(candidate, view).rgb.numpy()
        if not window:
            window.extend(object_window(image, WIDTH, HEIGHT))
        top, left = window
        return image[top : top + HEIGHT, left : left + WIDTH]

    stylized = stylize(scene, cameras, demo_style_image(), config).scene
    strengths = [render(blend_colors(scene, stylized, s)) for s in (0.0, 0.5, 1.0)]
    far = scene.means[:, 0] < 0.0
    first = stylize(scene, cameras, starry, config, mask=far).scene
    both = stylize(first, cameras, line_drawing_image(), config, mask=~far).scene
    selections = [render(first), render(both), at_scale(starry, HEIGHT, WIDTH, HEIGHT)]
    gap = np.ones((HEIGHT, 4, 3), np.float32)
    rows = [np.concatenate([row[0], gap, row[1], gap, row[2]], 1) for row in (strengths, selections)]
    write_image(args.out, np.concatenate([rows[0], np.ones((4, rows[0].shape[1], 3), np.float32), rows[1]], 0))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
