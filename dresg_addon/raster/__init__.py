"""Pure-torch differentiable Gaussian rasterizer (CPU by default, the same code on CUDA).

One small function per stage (``projection``: EWA projection; ``rasterizer``: pairs, compositing, the
colour-only fast path; ``sh``: spherical harmonics), a slow float64 ``reference`` that defines it, and the
speed ``knobs`` the benchmark and the report measure. May import ``scene`` and ``util``.

Semantics (the definition, which :mod:`.reference` implements slowly in float64):

- EWA projection: the Jacobian's x/z and y/z are clamped to 1.3 tan(fov/2); the 2D covariance gets
  +0.3 on its diagonal; Gaussians with det <= 0, or with z <= ``near``, are skipped.
- A Gaussian contributes at every pixel centre where alpha = min(0.99, o exp(-d^T S^-1 d / 2)) >= 1/255,
  with no radius truncation (a speed knob, off by default).
- Front-to-back by depth; a sample with T (1 - alpha) < 1e-4 ends the pixel and is not added.
"""

from .rasterizer import (
    ColorOnlyRenderer,
    RasterSettings,
    RenderOutput,
    geometry_tensors,
    render,
    render_scene,
    scene_covariances,
)
from .sh import colors_from_sh

__all__ = [
    "ColorOnlyRenderer",
    "RasterSettings",
    "RenderOutput",
    "colors_from_sh",
    "geometry_tensors",
    "render",
    "render_scene",
    "scene_covariances",
]
