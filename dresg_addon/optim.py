"""Optimiser pieces of the Gaussian fit (Sec. 4.3): Adam groups and the geometry offset bounds.

Colours are fitted with Adam at lr 0.05, the geometry offsets (means, log-scales, quaternions)
at 1e-3; after each update the offsets are projected back to their preset ranges (means +-0.05,
log-scales +-0.05, quaternions +-0.02), and opacity is never optimised.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import torch

from .errors import ConfigError, NumericalError


@dataclass(frozen=True)
class GeometryBounds:
    """Half-widths of the boxes the geometry offsets are projected onto after each update."""

    means: float = 0.05  # scene units
    log_scales: float = 0.05
    quats: float = 0.02  # per quaternion component, before normalisation

    def __post_init__(self) -> None:
        for name in ("means", "log_scales", "quats"):
            if not getattr(self, name) >= 0.0:
                raise ConfigError(f"geometry bound {name} must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class FitOptimizerSettings:
    color_lr: float = 0.05
    geometry_lr: float = 1e-3
    adam_eps: float = 1e-15  # as 3DGS: tiny, so steps stay ~lr even for tiny gradients
    bounds: GeometryBounds = field(default_factory=GeometryBounds)

    def __post_init__(self) -> None:
        if not (self.color_lr > 0.0 and self.geometry_lr >= 0.0 and self.adam_eps > 0.0):
            raise ConfigError(
                f"learning rates must be positive (colour {self.color_lr}, geometry {self.geometry_lr}) "
                f"and Adam eps > 0 (got {self.adam_eps})"
            )


def make_fit_optimizer(
    color_params: Iterable[torch.Tensor],
    geometry_params: Iterable[torch.Tensor] = (),
    settings: FitOptimizerSettings | None = None,
) -> torch.optim.Adam:
    """Adam with two groups: colours at ``color_lr`` and geometry offsets at ``geometry_lr``."""
    settings = settings or FitOptimizerSettings()
    groups = [{"params": list(color_params), "lr": settings.color_lr, "name": "color"}]
    geometry = list(geometry_params)
    if geometry and settings.geometry_lr > 0.0:
        groups.append({"params": geometry, "lr": settings.geometry_lr, "name": "geometry"})
    return torch.optim.Adam(groups, eps=settings.adam_eps)


@torch.no_grad()
def project_geometry_offsets_(
    mean_offsets: torch.Tensor | None,  # [N, 3]
    log_scale_offsets: torch.Tensor | None,  # [N, 3]
    quat_offsets: torch.Tensor | None,  # [N, 4]
    bounds: GeometryBounds | None = None,
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
