"""Blender's soft-splat preview against the engine's render of the same camera (issue 10, item 1): an EEVEE
render of the imported Luigi must look like `python -m dresg_addon render` of it. bpy module, EEVEE."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytest.importorskip("torch")
pytestmark = pytest.mark.blender
REPO = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("blender_preview_bench", REPO / "bench" / "blender_preview.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_eevee_soft_splats_look_like_the_engine_render(addon, shared_data):
    result = _bench().compare(
        shared_data("scenes/luigi.ply"), "Y_UP_TO_BLENDER", width=160, height=120, samples=1, view=1
    )
    assert result["covered"] > 0.05
    assert np.isfinite(result["eevee"]).all() and result["eevee"].max() > 0.2  # not a blank or grey render
    assert result["ssim_luminance"] >= 0.7, result["ssim_luminance"]
    assert result["mean_colour_error"] <= 0.08, result["mean_colour_error"]
