"""Shared fixtures: the real third-party data in ../shared/data (tests skip when it is absent)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

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
    import importlib.util

    bpy = pytest.importorskip("bpy")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    spec = importlib.util.spec_from_file_location("dresg_stylize_headless", REPO / "scripts" / "stylize_headless.py")
    headless = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(headless)
    module = headless.load_addon()
    yield module
    module.operators.job.set_current(None)
    module.unregister()
