# SPDX-License-Identifier: GPL-3.0-or-later
"""Build the extension zip with Blender's own extension tool, then validate it.

    python scripts/build_extension.py [--output-dir dist] [--blender /path/to/blender]

With ``--blender`` it runs ``blender --command extension build`` and ``validate``. Without, it runs
the same tool (``blender_ext.py``, with Blender's list of valid tags) from the ``bpy`` module's
bundled scripts, so no Blender binary is needed. What goes into the zip is decided by the
``[build]`` section of ``blender_manifest.toml``. Prints the path of the zip.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def bundled_tool() -> tuple[Path, Path]:
    """(blender_ext.py, tags.py) from the scripts of the installed ``bpy`` module."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("error: no Blender binary given (--blender) and the bpy module is not installed")
    package = Path(next(iter(spec.submodule_search_locations)))
    for scripts in sorted(package.glob("*/scripts")):
        tool = scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
        tags = scripts / "modules" / "_bpy_internal" / "extensions" / "tags.py"
        if tool.exists() and tags.exists():
            return tool, tags
    raise SystemExit(f"error: Blender's extension tool is not in the bpy module at {package}")


def extension_command(blender: str | None) -> tuple[list[str], list[str]]:
    """(command prefix, extra arguments for build) running Blender's extension tool."""
    if blender:
        return [blender, "--factory-startup", "--command", "extension"], []
    tool, tags = bundled_tool()
    return [sys.executable, str(tool)], [f"--valid-tags={tags}"]


def build(output_dir: Path, blender: str | None = None) -> Path:
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text(encoding="utf-8"))
    output = output_dir.resolve() / f"{manifest['id']}-{manifest['version']}.zip"
    output.parent.mkdir(parents=True, exist_ok=True)
    prefix, build_extra = extension_command(blender)
    steps = [
        [*prefix, "build", "--source-dir", str(REPO), "--output-filepath", str(output), *build_extra],
        [*prefix, "validate", str(output)],
    ]
    for command in steps:
        completed = subprocess.run(command, capture_output=True, text=True)
        if completed.returncode != 0:
            raise SystemExit(f"error: {' '.join(command)}\n{completed.stdout}{completed.stderr}")
    return output


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output-dir", type=Path, default=REPO / "dist", help="where the zip goes")
    parser.add_argument("--blender", help="a Blender binary (otherwise the bpy module's copy of the tool is used)")
    args = parser.parse_args(argv)
    print(build(args.output_dir, args.blender))
    return 0


if __name__ == "__main__":
    sys.exit(main())
