"""The rasterizer's speed knobs as (name, value) pairs, for the error-against-run-time tables.

Each entry changes one thing of the default :class:`RasterSettings` (no truncation, per-sample
arithmetic in the colours' dtype); the benchmark and the report both measure these, so a user sees what
each knob costs in error and in time. Tiles (slower, same image), per-pixel caps (up to 0.67 error for
under 20% time) and float32 scans (5e-4 error for no time) were measured (bench/README.md, `raster.py`) and removed.
"""

from __future__ import annotations

import numpy as np
import torch

from .rasterizer import RasterSettings, RenderOutput

SPEED_KNOBS = (
    ("default", None),  # per-sample arithmetic in the colours' dtype, float64 scans
    ("truncation_sigma", 3.0),
    ("truncation_sigma", 2.0),
    ("dtype", "float64"),  # float64 per-sample arithmetic, whatever the colours' dtype
    ("dtype", "float32"),  # float32 per-sample arithmetic, float64 scans
    ("band_pairs", 100_000),
    ("band_pairs", 2_000_000),
)


def knob_settings(knob: str, value) -> RasterSettings:
    """The exact default with one knob changed; dtype values are given by name ("float32")."""
    if value is None:
        return RasterSettings()
    if knob == "dtype":
        return RasterSettings(dtype=getattr(torch, value))
    return RasterSettings(**{knob: value})


def window_errors(out: RenderOutput, reference: dict, window: tuple[int, int, int, int]) -> dict[str, float]:
    """Max abs error of a full-image render against the reference's ``rgb`` and ``alpha`` on its window (x0, y0, w, h)."""
    x0, y0, w, h = window
    rgb = out.rgb[y0 : y0 + h, x0 : x0 + w].double().cpu().numpy()
    alpha = out.alpha[y0 : y0 + h, x0 : x0 + w].double().cpu().numpy()
    return {
        "rgb_error": float(np.abs(rgb - reference["rgb"]).max()),
        "alpha_error": float(np.abs(alpha - reference["alpha"]).max()),
    }
