"""Colour-gradient projection across views (Sec. 4.3, after gradient surgery, Yu et al. 2020).

Each active view v gives a gradient g_v of its fit loss on the shared colours (Eq. 17). Views are
processed in their fixed order; the gradient of view u is projected, one other view at a time, off
every ORIGINAL g_v it conflicts with (Eqs. 18-19), and the projected gradients are averaged (Eq. 20).

Every projected gradient is a linear combination of the original ones, so the whole procedure runs
on the V x V Gram matrix in float64 and the result is one weighted sum of the inputs: memory stays at
the size of the inputs and the V^2 dot products are the only pass over them. ``pcgrad_fuse_reference``
is the literal loop, kept to test the fast path against.

Equation numbers follow the order of the equations in ``paper/DReSG.tex``; each citation also names
the LaTeX label.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..util.errors import NumericalError

PCGRAD_EPS = 1e-20  # relative to the squared largest gradient entry (see pcgrad_fuse)


@dataclass(frozen=True)
class FusedGradient:
    gradient: torch.Tensor  # [...] the fused colour gradient, the inputs' shape without the view axis
    weights: torch.Tensor  # [V] float64: gradient = sum_v weights[v] g_v
    conflicts: int  # how many (u, v) projections were applied


def pcgrad_weights(gram: torch.Tensor, eps: float) -> tuple[torch.Tensor, int]:  # gram [V, V] float64
    """Eqs. 18-20 on the Gram matrix G_uv = g_u . g_v: the weights beta with g_bar = sum_v beta_v g_v.

    Row u of C holds g~_u = sum_w C_uw g_w, starting from C = I. For v != u in order, when
    g~_u . g_v = (C G)_uv < 0 (Eq. 18, ``eq:gradient-conflict``), Eq. 19 (``eq:gradient-projection``)
    g~_u <- g~_u - (g~_u . g_v) / (||g_v||^2 + eps) g_v becomes C_uv -= (C G)_uv / (G_vv + eps).
    Eq. 20 (``eq:fused-gradient``): beta = mean_u C_u. Returns (beta, number of projections).
    """
    num_views = gram.shape[0]
    coeffs = torch.eye(num_views, dtype=torch.float64)
    conflicts = 0
    for u in range(num_views):
        for v in range(num_views):
            if v == u:
                continue
            dot = torch.dot(coeffs[u], gram[:, v])
            if dot < 0:
                coeffs[u, v] -= dot / (gram[v, v] + eps)
                conflicts += 1
    return coeffs.mean(0), conflicts


def pcgrad_fuse(grads: torch.Tensor, eps: float = PCGRAD_EPS, chunk: int = 1 << 16) -> FusedGradient:
    """Eqs. 17-20: project conflicting per-view colour gradients, then average them.

    ``grads`` is [V, ...] (e.g. [V, N, 3]), one gradient per view in the deterministic active-view
    order. The projection is invariant to a common scale of the gradients, so they are divided by
    their largest absolute entry s before the float64 dot products; ``eps`` therefore acts as
    eps * s^2 in Eq. 19 and gradients of any magnitude (1e-30 or 1e30) are treated alike. One view
    is returned unchanged; all-zero gradients give zero. Non-finite gradients raise NumericalError.
    Work is done in column chunks of ``chunk`` so the float64 copies stay small (cache-sized).
    """
    if grads.ndim < 1 or grads.shape[0] < 1 or grads.numel() == 0:
        raise ValueError(f"per-view gradients must be [V, ...] with V >= 1, got shape {tuple(grads.shape)}")
    num_views = grads.shape[0]
    flat = grads.detach().reshape(num_views, -1)
    low, high = torch.aminmax(flat)  # one pass; NaN propagates, so this is also the finiteness check
    low, high = float(low), float(high)
    if not (math.isfinite(low) and math.isfinite(high)):
        raise NumericalError("a per-view colour gradient has non-finite values")
    if num_views == 1:
        return FusedGradient(grads[0].detach().clone(), torch.ones(1, dtype=torch.float64), 0)
    scale = max(-low, high)
    if scale == 0.0:
        uniform = torch.full((num_views,), 1.0 / num_views, dtype=torch.float64)
        return FusedGradient(torch.zeros_like(grads[0]), uniform, 0)
    gram = torch.zeros(num_views, num_views, dtype=torch.float64, device=flat.device)
    for start in range(0, flat.shape[1], chunk):
        part = flat[:, start : start + chunk].to(torch.float64) * (1.0 / scale)
        gram += part @ part.T
    weights, conflicts = pcgrad_weights(gram.cpu(), eps)
    fused = torch.empty(flat.shape[1], dtype=grads.dtype, device=flat.device)
    w = weights.to(flat.device)
    for start in range(0, flat.shape[1], chunk):
        fused[start : start + chunk] = w @ flat[:, start : start + chunk].to(torch.float64)
    return FusedGradient(fused.reshape(grads.shape[1:]), weights, conflicts)


def pcgrad_fuse_reference(grads: torch.Tensor, eps: float = PCGRAD_EPS) -> torch.Tensor:
    """The literal Eqs. 18-20 loop on explicit float64 vectors (slow; the test reference for pcgrad_fuse).

    Uses the same scale normalisation as ``pcgrad_fuse``.
    """
    flat = grads.detach().reshape(grads.shape[0], -1).to(torch.float64)
    scale = float(flat.abs().max())
    if scale == 0.0 or grads.shape[0] == 1:
        return flat.mean(0).to(grads.dtype).reshape(grads.shape[1:])
    flat = flat / scale
    projected = []
    for u in range(flat.shape[0]):
        g = flat[u].clone()
        for v in range(flat.shape[0]):
            if v != u:
                dot = torch.dot(g, flat[v])
                if dot < 0:
                    g = g - dot / (torch.dot(flat[v], flat[v]) + eps) * flat[v]
        projected.append(g)
    return (torch.stack(projected).mean(0) * scale).to(grads.dtype).reshape(grads.shape[1:])
