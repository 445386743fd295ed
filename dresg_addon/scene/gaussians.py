"""The one in-memory Gaussian scene type.

Arrays are numpy, in the file's frame (OpenCV / COLMAP axes: x right, y down, z forward) and in
the stored (pre-activation) parametrisation of graphdeco 3DGS:

=================  ==========  ====================================================
field              shape       activation
=================  ==========  ====================================================
``means``          [N, 3] f32  none
``log_scales``     [N, 3] f32  ``exp``
``quats``          [N, 4] f32  normalise, (w, x, y, z) order
``opacity_logits`` [N] f32     ``sigmoid``
``sh_dc``          [N, 3] f32  ``0.5 + SH_C0 * sh_dc`` (clamped at >= 0)
``sh_rest``        [N, K, 3]   higher SH bands, K in {3, 8, 15}; ``None`` for degree 0
``normals``        [N, 3]      kept only for a lossless round trip; ``None`` when absent
=================  ==========  ====================================================

``extras`` holds any other per-splat property of a PLY (name -> [N] array), so that writing a scene
back keeps it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

SH_C0 = 0.28209479177387814
SH_REST_COUNTS = {0: 0, 1: 3, 2: 8, 3: 15}  # degree -> coefficients per channel beyond DC


@dataclass
class GaussianScene:
    means: np.ndarray  # [N, 3] float32
    log_scales: np.ndarray  # [N, 3] float32
    quats: np.ndarray  # [N, 4] float32, (w, x, y, z)
    opacity_logits: np.ndarray  # [N] float32
    sh_dc: np.ndarray  # [N, 3] float32
    sh_rest: np.ndarray | None = None  # [N, K, 3] float32
    normals: np.ndarray | None = None  # [N, 3] float32
    extras: dict[str, np.ndarray] = field(default_factory=dict)  # name -> [N]

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
            "sh_dc": (n, 3),
        }
        for name, shape in expected.items():
            actual = getattr(self, name).shape
            if actual != shape:
                raise ValueError(f"GaussianScene.{name} has shape {actual}, expected {shape}")
        if self.sh_rest is not None:
            if self.sh_rest.ndim != 3 or self.sh_rest.shape[0] != n or self.sh_rest.shape[2] != 3:
                raise ValueError(f"GaussianScene.sh_rest has shape {self.sh_rest.shape}, expected [{n}, K, 3]")
            if self.sh_rest.shape[1] not in (3, 8, 15):
                raise ValueError(f"GaussianScene.sh_rest has {self.sh_rest.shape[1]} coefficients, expected 3, 8 or 15")
        if self.normals is not None and self.normals.shape != (n, 3):
            raise ValueError(f"GaussianScene.normals has shape {self.normals.shape}, expected ({n}, 3)")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        if self.sh_rest is None:
            return 0
        return {3: 1, 8: 2, 15: 3}[self.sh_rest.shape[1]]

    # Activated views (read-only conveniences).
    @property
    def scales(self) -> np.ndarray:  # [N, 3]
        return np.exp(self.log_scales)

    @property
    def opacities(self) -> np.ndarray:  # [N]
        return 1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))

    @property
    def base_colors(self) -> np.ndarray:  # [N, 3], view-independent (DC) colour in [0, inf)
        return np.maximum(0.5 + SH_C0 * self.sh_dc, 0.0)

    def subset(self, index: np.ndarray) -> GaussianScene:
        """The scene restricted to ``index`` (a boolean mask or integer indices)."""
        return replace(
            self,
            means=self.means[index],
            log_scales=self.log_scales[index],
            quats=self.quats[index],
            opacity_logits=self.opacity_logits[index],
            sh_dc=self.sh_dc[index],
            sh_rest=None if self.sh_rest is None else self.sh_rest[index],
            normals=None if self.normals is None else self.normals[index],
            extras={k: v[index] for k, v in self.extras.items()},
        )

    def copy(self) -> GaussianScene:
        return replace(
            self,
            means=self.means.copy(),
            log_scales=self.log_scales.copy(),
            quats=self.quats.copy(),
            opacity_logits=self.opacity_logits.copy(),
            sh_dc=self.sh_dc.copy(),
            sh_rest=None if self.sh_rest is None else self.sh_rest.copy(),
            normals=None if self.normals is None else self.normals.copy(),
            extras={k: v.copy() for k, v in self.extras.items()},
        )

    def invalid_mask(self) -> np.ndarray:
        """[N] bool: splats with a non-finite value in any field."""
        bad = ~np.isfinite(self.means).all(1)
        bad |= ~np.isfinite(self.log_scales).all(1)
        bad |= ~np.isfinite(self.quats).all(1)
        bad |= ~np.isfinite(self.opacity_logits)
        bad |= ~np.isfinite(self.sh_dc).all(1)
        if self.sh_rest is not None:
            bad |= ~np.isfinite(self.sh_rest).all((1, 2))
        if self.normals is not None:
            bad |= ~np.isfinite(self.normals).all(1)
        for values in self.extras.values():  # every float property a file carries, written back as read
            if np.issubdtype(values.dtype, np.floating):
                bad |= ~np.isfinite(values)
        return bad

    def bounds(self, quantile: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds of the means; ``quantile`` > 0 gives robust bounds ignoring floaters."""
        if quantile <= 0.0:
            return self.means.min(0), self.means.max(0)
        return np.quantile(self.means, quantile, axis=0), np.quantile(self.means, 1.0 - quantile, axis=0)


def blend_coefficients(original: np.ndarray, stylized: np.ndarray, strength: float) -> np.ndarray:
    """(1 - strength) original + strength stylized, in float32 (exactly either at 0 and 1): the colour
    coefficients at a stylization strength in [0, 1]. Colours are linear in the SH coefficients, so every
    view's render blends alike."""
    if not (np.isfinite(strength) and 0.0 <= strength <= 1.0):
        raise ValueError(f"strength must be in [0, 1], got {strength}")
    weight = np.float32(strength)
    mixed = (np.float32(1) - weight) * np.asarray(original, np.float32) + weight * np.asarray(stylized, np.float32)
    return mixed.astype(np.float32)


def blend_colors(original: GaussianScene, stylized: GaussianScene, strength: float) -> GaussianScene:
    """``stylized`` with its colours (SH DC and rest bands) ``strength`` of the way from ``original``'s: 0 gives
    the original colours, 1 the stylized ones; geometry and opacity stay the stylized scene's."""
    if len(original) != len(stylized):
        raise ValueError(f"cannot blend {len(original)} splats with {len(stylized)}")
    rest_a, rest_b = original.sh_rest, stylized.sh_rest
    if rest_a is None and rest_b is None:
        sh_rest = None
    else:
        rest_a = np.zeros_like(rest_b) if rest_a is None else rest_a
        rest_b = np.zeros_like(rest_a) if rest_b is None else rest_b
        if rest_a.shape != rest_b.shape:
            raise ValueError(f"cannot blend SH bands of shapes {rest_a.shape} and {rest_b.shape}")
        sh_rest = blend_coefficients(rest_a, rest_b, strength)
    return replace(stylized, sh_dc=blend_coefficients(original.sh_dc, stylized.sh_dc, strength), sh_rest=sh_rest)
