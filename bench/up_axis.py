# SPDX-License-Identifier: GPL-3.0-or-later
"""Which way is up from the splats alone (issue 28): what ``up_axis_from_splats`` says on every scene at hand.
Not a test: it prints a Markdown table.

    python bench/up_axis.py [--repeats 5]

Scenes: the shared bonsai, Luigi and graphdeco files (``../shared/data/scenes``, skipped when absent) and the
built-in demo. For each: the truth and how it is known, the axis chosen, the two margins and the confidence
(>= 1: sure), the time of one call (median of the repeats), and the same scene tilted by 5, 10 and 20 degrees
about x and about z: how many of those six it still gets right and sure, and how many it gets wrong but sure.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

from dresg_addon.scene.demo import demo_scene
from dresg_addon.scene.io import read_scene
from dresg_addon.scene.up_axis import up_axis_from_splats

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DRESG_SHARED_DATA", REPO.parent / "shared" / "data")) / "scenes"
SCENES = (  # file (None: the demo), truth, how the truth is known
    ("bonsai-7k-mini.splat", "-Y", "COLMAP capture; its camera hint's up is (0.02, -0.76, -0.65)"),
    ("luigi.ply", "+Y", "y-up model: upright in renders with up +y"),
    ("graphdeco_it7000_sh3.ply", "?", "unknown: no cameras.json anywhere, unrecognisable in renders"),
    (None, "-Y", "demo.py: objects stand on the plane y = 0 at negative y"),
)
TILTS = (5.0, 10.0, 20.0)


def tilted(scene, axis: int, degrees: float):
    """The scene turned as a whole by ``degrees`` about a coordinate axis (positions and splat orientations)."""
    half = np.radians(degrees) / 2.0
    q = np.zeros(4)
    q[0], q[1 + axis] = np.cos(half), np.sin(half)
    w, x, y, z = q
    matrix = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    out = scene.copy()
    out.means = (scene.means.astype(np.float64) @ matrix.T).astype(np.float32)
    w2, x2, y2, z2 = scene.quats.astype(np.float64).T
    out.quats = np.stack(
        [
            w * w2 - x * x2 - y * y2 - z * z2,
            w * x2 + x * w2 + y * z2 - z * y2,
            w * y2 - x * z2 + y * w2 + z * x2,
            w * z2 + x * y2 - y * x2 + z * w2,
        ],
        1,
    ).astype(np.float32)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(
        "| scene | splats | truth | chose | plane ratio | footprint ratio | confidence | time | tilted: right / wrong, sure |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    notes = []
    for name, truth, how in SCENES:
        if name is not None and not (SHARED / name).exists():
            print(f"| {name} | (absent) |||||||")
            continue
        scene = demo_scene() if name is None else read_scene(SHARED / name)
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            guess = up_axis_from_splats(scene)
            times.append(time.perf_counter() - start)
        right = wrong = 0
        for axis in (0, 2):
            for degrees in TILTS:
                turned = up_axis_from_splats(tilted(scene, axis, degrees))
                right += turned.sure and turned.axis == truth
                wrong += turned.sure and turned.axis != truth
        chose = guess.axis if guess.sure else f"not sure ({guess.axis}) -> -Y"
        print(
            f"| {name or 'demo'} | {len(scene):,} | {truth} | {chose} | {guess.plane_ratio:.2f} | "
            f"{guess.footprint_ratio:.2f} | {guess.confidence:.2f} | {1000 * statistics.median(times):.0f} ms | "
            f"{right} / {wrong} of {2 * len(TILTS)} |"
        )
        notes.append(f"- {name or 'demo'}: truth {how}")
    print()
    print("\n".join(notes))


if __name__ == "__main__":
    main()
