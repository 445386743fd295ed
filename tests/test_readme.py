"""The README's Python example runs as written, on the demo's own files and a tiny schedule, from outside the
repository (the engine is an installed package); the console command works from anywhere too."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def _python_example() -> str:
    text = (REPO / "README.md").read_text()
    section = text.split("### From Python", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def _outside_the_repository() -> dict:
    """An environment whose imports cannot come from the checkout by accident: no PYTHONPATH."""
    return {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}


@pytest.mark.slow
def test_the_readme_python_example_runs(tmp_path):
    from dresg_addon.scene.demo import write_demo_assets
    from dresg_addon.scene.io import read_scene

    assets = write_demo_assets(tmp_path)
    code = _python_example()
    tiny = 'preset("preview", stages=1, proposal_width=32, proposal_height=24, max_views=2)'
    for old, new in (
        ('"scene.ply"', repr(str(assets["scene"]))),
        ('"cameras.json"', f"{str(assets['cameras'])!r}, width=64, height=48"),
        ('"painting.jpg"', repr(str(assets["style"]))),
        ('"stylized.ply"', repr(str(tmp_path / "stylized.ply"))),
        ('preset("preview")', tiny),
    ):
        assert old in code, f"the README example no longer has {old}"
        code = code.replace(old, new)
    assert not tmp_path.resolve().is_relative_to(REPO)
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=_outside_the_repository(), capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-2000:]
    stylized, base = read_scene(tmp_path / "stylized.ply"), read_scene(assets["scene"])
    assert len(stylized) == len(base) and not np.array_equal(stylized.sh_dc, base.sh_dc)


def test_the_console_command_runs_from_any_directory(tmp_path):
    dresg = Path(sys.executable).with_name("dresg")
    assert dresg.exists(), "the dresg console command is not installed (pip install -e .)"
    env = _outside_the_repository()
    done = subprocess.run([str(dresg), "--help"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.startswith("usage: dresg "), done.stdout + done.stderr
    for command in ("info", "convert", "render", "evaluate", "select-views", "stylize", "demo", "report"):
        assert command in done.stdout
    module = subprocess.run(
        [sys.executable, "-m", "dresg_addon", "--version"], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert module.returncode == 0 and module.stdout.startswith("python -m dresg_addon "), module.stderr
    version = subprocess.run([str(dresg), "--version"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert version.stdout.split()[-1] == module.stdout.split()[-1]
