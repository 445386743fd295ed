"""The README's Python example runs as written, on the demo's own files and a tiny schedule."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _python_example() -> str:
    text = (REPO / "README.md").read_text()
    section = text.split("### From Python", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_readme_python_example_runs(tmp_path, monkeypatch):
    from dresg_addon.scene.demo import write_demo_assets
    from dresg_addon.scene.io import read_scene

    assets = write_demo_assets(tmp_path)
    code = _python_example()
    tiny = (
        'preset("preview", stages=1, updates_per_stage=2, fit_steps=2, post_steps=1, proposal_width=32, '
        "proposal_height=24, max_views=2)"
    )
    for old, new in (
        ('"scene.ply"', repr(str(assets["scene"]))),
        ('"cameras.json"', f"{str(assets['cameras'])!r}, width=64, height=48"),
        ('"painting.jpg"', repr(str(assets["style"]))),
        ('"stylized.ply"', repr(str(tmp_path / "stylized.ply"))),
        ('preset("preview")', tiny),
    ):
        assert old in code, f"the README example no longer has {old}"
        code = code.replace(old, new)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    stylized, base = read_scene(tmp_path / "stylized.ply"), read_scene(assets["scene"])
    assert len(stylized) == len(base) and not np.array_equal(stylized.sh_dc, base.sh_dc)
