"""Optimiser pieces of the Gaussian fit (Sec. 4.3): Adam groups, the geometry offset bounds, the scene extent.

Colours are fitted with Adam at lr 0.05, the geometry offsets (means, log-scales, quaternions)
at 1e-3; after each update the offsets are projected back to their preset ranges (means +-0.05,
log-scales +-0.05, quaternions +-0.02), and opacity is never optimised.

Units. Log-scale and quaternion offsets are scale-free. Mean offsets are lengths: the paper's numbers
(lr 1e-3, bound +-0.05) are for its scenes, whose content is about a unit to a few units across. As
3DGS does for its position learning rate (graphdeco multiplies it by the camera extent), the mean
offsets' learning rate and bound are multiplied by the scene extent of :func:`scene_extent` (the
reference extent is 1): on a scene of extent 1 the paper's numbers hold as they are, and a scene
scaled by s gets mean offsets scaled by s.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ..util.errors import ConfigError, NumericalError


@dataclass(frozen=True)
class GeometryBounds:
    """Half-widths of the boxes the geometry offsets are projected onto after each update.

    ``means`` is in units of the scene extent (:func:`scene_extent`); :meth:`in_scene_units` gives the
    bounds :func:`project_geometry_offsets_` applies.
    """

    means: float = 0.05  # x the scene extent
    log_scales: float = 0.05
    quats: float = 0.02  # per quaternion component, before normalisation

    def __post_init__(self) -> None:
        for name in ("means", "log_scales", "quats"):
            if not getattr(self, name) >= 0.0:
                raise ConfigError(f"geometry bound {name} must be >= 0, got {getattr(self, name)}")

    def in_scene_units(self, extent: float) -> GeometryBounds:
        """The bounds for a scene of extent ``extent``: the mean bound times the extent, the rest as they are."""
        return replace(self, means=self.means * extent)


SCENE_EXTENT_QUANTILE = 0.9


def scene_extent(
    means: np.ndarray,  # [N, 3] Gaussian centres (the Gaussians being fitted)
    log_scales: np.ndarray | None = None,  # [N, 3], for the one-point fallback
) -> float:
    """The scene's extent, the length the mean offsets' learning rate and bound are relative to.

    A robust radius: the 90th percentile of the centres' distances from their per-axis median,
    ``quantile_0.9 ||mu_i - median(mu)||`` (per-axis median). It scales exactly with the scene, does not
    change when the scene is translated (and little when it is rotated: the median is per axis), and ignores
    the farthest tenth of the splats (floaters, far background).
    When every centre is at one point (a single Gaussian) it falls back to the median splat size
    ``median_i max_k exp(log_scale_ik)``, and to 1 when that is not positive and finite either.

    >>> round(scene_extent(np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])), 6)
    1.0
    """
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    extent = 0.0
    if len(means):
        distances = np.linalg.norm(means - np.median(means, axis=0), axis=1)
        extent = float(np.quantile(distances, SCENE_EXTENT_QUANTILE))
    if not (math.isfinite(extent) and extent > 0.0) and log_scales is not None and len(log_scales):
        extent = float(np.median(np.exp(np.asarray(log_scales, dtype=np.float64).reshape(-1, 3).max(axis=1))))
    return extent if math.isfinite(extent) and extent > 0.0 else 1.0


@dataclass(frozen=True)
class FitOptimizerSettings:
    color_lr: float = 0.05
    geometry_lr: float = 1e-3  # the mean offsets' lr is this times the extent
    adam_eps: float = 1e-15  # as 3DGS: tiny, so steps stay ~lr even for tiny gradients
    bounds: GeometryBounds = field(default_factory=GeometryBounds)  # the mean bound in units of the extent
    extent: float = 1.0  # the scene extent (scene_extent) the mean offsets are relative to

    def __post_init__(self) -> None:
        if not (self.color_lr > 0.0 and self.geometry_lr >= 0.0 and self.adam_eps > 0.0):
            raise ConfigError(
                f"learning rates must be positive (colour {self.color_lr}, geometry {self.geometry_lr}) "
                f"and Adam eps > 0 (got {self.adam_eps})"
            )
        if not (math.isfinite(self.extent) and self.extent > 0.0):
            raise ConfigError(f"the scene extent must be positive and finite, got {self.extent}")

    @property
    def mean_lr(self) -> float:
        """The mean offsets' learning rate in scene units: ``geometry_lr x extent``."""
        return self.geometry_lr * self.extent

    @property
    def scene_bounds(self) -> GeometryBounds:
        """The bounds in scene units (the mean bound times the extent), for :func:`project_geometry_offsets_`."""
        return self.bounds.in_scene_units(self.extent)


def make_fit_optimizer(
    color_params: Iterable[torch.Tensor],
    geometry_params: Iterable[torch.Tensor] = (),
    settings: FitOptimizerSettings | None = None,
    mean_params: Iterable[torch.Tensor] = (),
) -> torch.optim.Adam:
    """Adam with up to three groups: colours at ``color_lr``, the mean offsets (``mean_params``) at
    ``geometry_lr x extent`` and the other geometry offsets (log-scales, quaternions) at ``geometry_lr``."""
    settings = settings or FitOptimizerSettings()
    groups = [{"params": list(color_params), "lr": settings.color_lr, "name": "color"}]
    if settings.geometry_lr > 0.0:
        for name, params, lr in (
            ("means", list(mean_params), settings.mean_lr),
            ("geometry", list(geometry_params), settings.geometry_lr),
        ):
            if params:
                groups.append({"params": params, "lr": lr, "name": name})
    return torch.optim.Adam(groups, eps=settings.adam_eps)


@torch.no_grad()
def project_geometry_offsets_(
    mean_offsets: torch.Tensor | None,  # [N, 3]
    log_scale_offsets: torch.Tensor | None,  # [N, 3]
    quat_offsets: torch.Tensor | None,  # [N, 4]
    bounds: GeometryBounds | None = None,  # in scene units (FitOptimizerSettings.scene_bounds)
) -> None:
    """Project the offsets in place onto their boxes: d <- clamp(d, -b, b), per component."""
    bounds = bounds or GeometryBounds()
    for offsets, bound in (
        (mean_offsets, bounds.means),
        (log_scale_offsets, bounds.log_scales),
        (quat_offsets, bounds.quats),
    ):
        if offsets is not None:
            offsets.clamp_(-bound, bound)


def check_finite_gradients(params: Iterable[torch.Tensor], what: str = "Gaussian") -> None:
    """Raise NumericalError when a parameter's gradient has NaN or Inf (before the optimiser step)."""
    for p in params:
        if p.grad is not None and not torch.isfinite(p.grad).all():
            raise NumericalError(f"non-finite gradient on the {what} parameters; the step was not applied")
