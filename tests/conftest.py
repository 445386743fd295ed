"""Shared fixtures: the real third-party data in ../shared/data (tests skip when it is absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Tests compare runs bit for bit: keep torch's thread count fixed (tests/test_threads.py turns it back on).
os.environ.setdefault("DRESG_ADAPTIVE_THREADS", "0")

SHARED_DATA = Path(os.environ.get("DRESG_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_file(relative: str) -> Path:
    """Path of a file in ../shared/data; skips the test when it is not there."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"shared data not present: {path}")
    return path


@pytest.fixture
def shared_data():
    return shared_file


@pytest.fixture
def addon():
    """The extension registered in a clean, empty Blender file (bpy module); unregistered afterwards."""
    bpy = pytest.importorskip("bpy")
    import stylize_headless  # scripts/, on pytest's pythonpath

    bpy.ops.wm.read_factory_settings(use_empty=True)
    module = stylize_headless.load_addon()
    yield module
    module.unregister()  # cancels and forgets the jobs
