# SPDX-License-Identifier: GPL-3.0-or-later
"""``dresg report`` on the shared benchmark data: the bonsai and two paintings unless told otherwise.

    .venv/bin/python bench/report.py [--quick] [any other option of ``dresg report``]

The engine's report measures the user's scene, paintings and cameras (the built-in demo without them); this
script gives it the benchmark's defaults from ``../shared/data`` (or ``$DRESG_SHARED_DATA``): without
``--scene``, the bonsai (273k Gaussians, y-down) unless ``--quick``; without ``--styles``, Starry Night and The
Scream (only the first with ``--quick``) for a real scene. Absent files are left out (the demo then runs).
docs/report.md was written this way: ``bench/report.py --presets preview,standard --width 448 --height 320
--out DIR``, then DIR's report.md and plots copied into docs/ (the plots as ``report_*.png``, the links renamed).
"""

from __future__ import annotations

import argparse
import sys

from quality import SCENES, style_path  # bench/, beside this script

from dresg_addon.cli import main as dresg

PAINTINGS = ("starry_night", "the_scream")


def shared_defaults(scene: str | None, styles, quick: bool) -> dict:
    """ReportOptions' scene, styles and up: the ones given, else the shared bonsai and paintings where present."""
    bonsai, up = SCENES["bonsai"]
    if scene is None and not quick and bonsai.is_file():
        scene = str(bonsai)
    if not styles and scene not in (None, "demo"):
        found = [path for path in map(style_path, PAINTINGS) if path is not None]
        styles = [str(path) for path in found[: 1 if quick else 2]]
    return {"scene": scene, "styles": tuple(styles or ()), "up": up}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(add_help=False)  # only what the defaults depend on; dresg report checks all
    parser.add_argument("--scene")
    parser.add_argument("--styles", nargs="+")
    parser.add_argument("--quick", action="store_true")
    given, _ = parser.parse_known_args(argv)
    defaults = shared_defaults(given.scene, given.styles, given.quick)
    extra = []
    if given.scene is None and defaults["scene"] is not None:
        extra += ["--scene", defaults["scene"], "--up", ",".join(map(str, defaults["up"]))]
    if not given.styles and defaults["styles"]:
        extra += ["--styles", *defaults["styles"]]
    return dresg(["report", *argv, *extra])


if __name__ == "__main__":
    sys.exit(main())
