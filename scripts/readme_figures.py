"""Compose the README's before / colour transfer / ours / style figure from the quality benchmark's renders.

    .venv/bin/python bench/quality.py --figures FIGS --figure-views 3
    .venv/bin/python scripts/readme_figures.py --figures FIGS --view 3 \\
        --pairs bonsai:starry_night,bonsai:the_scream,bonsai:woman-with-hat-matisse,luigi:starry_night,... \\
        --out docs/before_after.jpg

Every picture is a novel view of the benchmark (a camera between the ones the scene was stylized from), so
the figure shows what the table measures, rendered at twice the fit size and cropped to the fit size around
the object, so that marks can be seen. Rows are scene x style pairs; columns: the unstylized scene, the
colour-transfer baseline, the ``standard`` preset (or the bench rows of ``--columns``, e.g. Stroke Size 1, 2
and 3 as ``standard@stroke_size=1;...``), and the painting at the same scale (its
shorter side twice the fit height, as the metrics resample it), centre-cropped. Needs the shared
paintings (../shared/data/styles) for the style column; ``demo`` and ``lines`` are generated.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from dresg_addon.scene.demo import demo_style_image, line_drawing_image  # noqa: E402
from dresg_addon.util.imageio import at_scale, object_window, read_rgb, write_image  # noqa: E402

DATA = REPO.parent / "shared" / "data"


def style_tile(name: str, height: int, width: int, short_side: int) -> np.ndarray:
    generated = {"demo": demo_style_image, "lines": line_drawing_image}
    style = generated[name]() if name in generated else read_rgb(DATA / "styles" / f"{name}.jpg")
    return at_scale(style, short_side, width, height)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--figures", required=True, help="the folder bench/quality.py --figures wrote")
    parser.add_argument("--pairs", required=True, help="comma-separated scene:style pairs, one row each")
    parser.add_argument("--view", type=int, default=3, help="novel-view index (as written by --figure-views)")
    parser.add_argument(
        "--columns",
        default="unstylized;colour-transfer;standard",
        help="';'-separated bench rows, one column each, before the painting (default: "
        "unstylized;colour-transfer;standard; a row may carry settings, e.g. standard@stroke_size=2)",
    )
    parser.add_argument("--out", default=str(REPO / "docs" / "before_after.jpg"))
    args = parser.parse_args()
    folder = Path(args.figures)
    rows = []
    for pair in args.pairs.split(","):
        scene, style = pair.split(":")
        images = [read_rgb(folder / f"{scene}_{style}_{row}_v{args.view:02d}.png") for row in args.columns.split(";")]
        height, width = images[0].shape[0] // 2, images[0].shape[1] // 2  # the fit size: a 2x crop of the object
        top, left = object_window(images[0], width, height)
        tiles = [image[top : top + height, left : left + width] for image in images]
        tiles.append(style_tile(style, height, width, images[0].shape[0]))  # the renders' scale
        gap = np.ones((height, 4, 3), np.float32)
        rows.append(np.concatenate([t for tile in tiles for t in (tile, gap)][:-1], 1))
        rows.append(np.ones((4, rows[-1].shape[1], 3), np.float32))
    write_image(args.out, np.concatenate(rows[:-1], 0))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
