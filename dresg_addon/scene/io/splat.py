"""antimatter15 ``.splat``: headerless 32-byte records, one per splat.

===========  =======  ==========================================================
bytes        type     meaning
===========  =======  ==========================================================
0-11         3 f32    position
12-23        3 f32    linear scale (``exp`` of the log-scale)
24-27        4 u8     RGBA: DC colour ``0.5 + SH_C0 * f_dc`` and alpha, times 255
28-31        4 u8     rotation ``q * 128 + 128`` in (w, x, y, z) order
===========  =======  ==========================================================

The format keeps no SH rest, no normals and no extra properties; colour, alpha and rotation are
8-bit. Decoding maps back to the stored parametrisation with finite values everywhere: alpha is
clamped into (0, 1) before the logit and a zero scale becomes ``MIN_LOG_SCALE``.
"""

from __future__ import annotations

import numpy as np

from ...util.errors import SceneFormatError, with_path
from ..gaussians import SH_C0, GaussianScene

SPLAT_DTYPE = np.dtype(
    [("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rotation", "u1", (4,))]
)
MIN_LOG_SCALE = float(np.log(1e-8))
# Alpha 0 and 1 have infinite logits; 1e-6 keeps them finite and still quantises back to 0 and 255.
ALPHA_EPS = 1e-6


def opacity_logit(alpha: np.ndarray) -> np.ndarray:  # [N] float64 -> [N] float32
    """Inverse of the opacity activation, ``log(a / (1 - a))`` with ``a`` clamped to [eps, 1 - eps]."""
    alpha = np.clip(alpha, ALPHA_EPS, 1.0 - ALPHA_EPS)
    return np.log(alpha / (1.0 - alpha)).astype(np.float32)


def opacity_from_logit(logits: np.ndarray) -> np.ndarray:  # [N] -> [N] float64
    """The opacity activation ``sigmoid(x)``, written as ``(1 + tanh(x / 2)) / 2`` so it cannot overflow."""
    return 0.5 * (1.0 + np.tanh(0.5 * logits.astype(np.float64)))


def normalized_quats(quats: np.ndarray) -> np.ndarray:  # [N, 4] -> [N, 4] float64, identity where zero
    q = quats.astype(np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    degenerate = norm[:, 0] < 1e-12
    q[degenerate] = (1.0, 0.0, 0.0, 0.0)
    norm[degenerate] = 1.0
    return q / norm


def read_splat(path, data: bytes) -> GaussianScene:
    if len(data) % SPLAT_DTYPE.itemsize:
        raise SceneFormatError(
            with_path(path, f"truncated data: {len(data)} bytes is not a whole number of 32-byte .splat records")
        )
    records = np.frombuffer(data, dtype=SPLAT_DTYPE)
    rgba = records["rgba"].astype(np.float64) / 255.0
    scales = records["scale"].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_scales = np.log(scales)
    # A zero scale gets a finite floor; negative or NaN scales stay NaN for the validity check.
    log_scales[scales == 0.0] = MIN_LOG_SCALE
    return GaussianScene(
        means=records["position"].astype(np.float32),
        log_scales=log_scales.astype(np.float32),
        quats=((records["rotation"].astype(np.float32) - 128.0) / 128.0),
        opacity_logits=opacity_logit(rgba[:, 3]),
        sh_dc=((rgba[:, :3] - 0.5) / SH_C0).astype(np.float32),
    )


def encode_splat(scene: GaussianScene) -> list[bytes | memoryview]:
    """The .splat bytes of ``scene`` (SH rest, normals and extras are dropped; order is kept)."""
    records = np.empty(len(scene), dtype=SPLAT_DTYPE)
    records["position"] = scene.means
    # Absurd log-scales (> 88) would overflow float32 to inf; clamp to the largest finite scale.
    records["scale"] = np.minimum(np.exp(scene.log_scales.astype(np.float64)), np.finfo(np.float32).max)
    rgb = 0.5 + SH_C0 * scene.sh_dc.astype(np.float64)
    rgba = np.concatenate([rgb, opacity_from_logit(scene.opacity_logits)[:, None]], axis=1)
    records["rgba"] = np.clip(np.rint(rgba * 255.0), 0, 255)
    records["rotation"] = np.clip(np.rint(normalized_quats(scene.quats) * 128.0 + 128.0), 0, 255)
    return [memoryview(records.view(np.uint8))]
