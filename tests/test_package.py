"""Package hygiene: the engine never imports bpy, and the CLI starts without heavy imports."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", f"import sys; {code}; print(' '.join(sorted(sys.modules)))"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    return set(out.stdout.split())


def test_engine_imports_no_bpy():
    modules = _modules_after(
        "import dresg_addon, dresg_addon.pipeline, dresg_addon.raster, dresg_addon.io, dresg_addon.camera_io, "
        "dresg_addon.metrics, dresg_addon.proposal, dresg_addon.cli"
    )
    assert "bpy" not in modules
    assert "diffusers" not in modules  # only the sd15 backend imports it, lazily


def test_package_import_is_light():
    modules = _modules_after("import dresg_addon, dresg_addon.cli; dresg_addon.cli.build_parser()")
    assert "torch" not in modules and "bpy" not in modules


@pytest.mark.parametrize("command", ["info", "convert", "render", "select-views", "stylize", "evaluate", "demo"])
def test_every_command_has_help(command, capsys):
    from dresg_addon.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    assert command in capsys.readouterr().out
