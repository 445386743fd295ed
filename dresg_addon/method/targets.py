"""Render-relative residual targets (Sec. 4.2).

The proposal-render residual dI = D(z*) - I_r (Eq. 10) is turned into the stage's fitting target by
extrapolating from the current render toward the proposal with strength gamma_k, in RGB-logit space
(the method) or directly in image space (the paper's ablation). Targets carry no gradient.

Equation numbers follow the order of the equations in ``paper/DReSG.tex``; each citation also names
the LaTeX label.
"""

from __future__ import annotations

import torch

from ..util.errors import ConfigError, NumericalError

LOGIT_EPS = 1e-4  # clamp inside the logit, as the authors' release does


def proposal_residual(proposal: torch.Tensor, render: torch.Tensor) -> torch.Tensor:
    """Eq. 10 (``eq:diffusion-residual``): dI = D_VAE(z*) - I_r, for images of equal shape in [0, 1]."""
    _check_same_shape(proposal, render, "proposal", "render")
    return (proposal - render).detach()


def logit(image: torch.Tensor, eps: float = LOGIT_EPS) -> torch.Tensor:
    """Channel-wise RGB logit l(I) = log(I / (1 - I)), with I clamped to [eps, 1 - eps] first."""
    x = image.clamp(eps, 1.0 - eps)
    return torch.log(x) - torch.log1p(-x)


def logit_residual_target(
    render: torch.Tensor,  # [..., 3, H, W] in [0, 1]
    residual: torch.Tensor,  # same shape as render
    gamma: float | torch.Tensor,  # scalar, or broadcastable to render (e.g. [V, 1, 1, 1] per view)
    eps: float = LOGIT_EPS,
) -> torch.Tensor:
    """Eq. 12 (``eq:residual-target``), RGB-logit residual target.

    I_t = sigmoid(l(I_r) + gamma (l(I_r + dI) - l(I_r))), with both logit arguments clamped to
    [eps, 1 - eps]. gamma = 1 gives back the clamped proposal I_r + dI; the result always lies in
    (0, 1) and is monotone in gamma. Computed in float32 or wider, returned detached in the render's dtype.
    """
    _check_same_shape(residual, render, "residual", "render")
    dtype = torch.promote_types(render.dtype, torch.float32)
    r = render.detach().to(dtype)
    gamma = torch.as_tensor(gamma, dtype=dtype, device=r.device)
    base = logit(r, eps)
    target = torch.sigmoid(base + gamma * (logit(r + residual.detach().to(dtype), eps) - base))
    return target.to(render.dtype)


def image_residual_target(
    render: torch.Tensor,  # [..., 3, H, W] in [0, 1]
    residual: torch.Tensor,  # same shape as render
    gamma: float | torch.Tensor,  # scalar, or broadcastable to render
) -> torch.Tensor:
    """Image-space ablation of Eq. 12 ("w/o RGB-logit"): I_t = clamp(I_r + gamma dI, 0, 1), detached."""
    _check_same_shape(residual, render, "residual", "render")
    gamma = torch.as_tensor(gamma, dtype=render.dtype, device=render.device)
    return (render.detach() + gamma * residual.detach()).clamp(0.0, 1.0)


def residual_target(
    render: torch.Tensor, residual: torch.Tensor, gamma: float | torch.Tensor, space: str = "logit"
) -> torch.Tensor:
    """The stage target in the chosen ``space``: "logit" (the method, Eq. 12) or "image" (ablation)."""
    if space == "logit":
        return logit_residual_target(render, residual, gamma)
    if space == "image":
        return image_residual_target(render, residual, gamma)
    raise ConfigError(f"unknown target space {space!r}; choose 'logit' or 'image'")


def _check_same_shape(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{name_a} has shape {tuple(a.shape)} but {name_b} has shape {tuple(b.shape)}")
    for t, name in ((a, name_a), (b, name_b)):
        if not torch.isfinite(t).all():
            raise NumericalError(f"the {name} image has non-finite values")
