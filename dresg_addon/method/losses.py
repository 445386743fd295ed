"""The per-view fit loss of Sec. 4.3 and the image measures it is made of.

Eq. 16 (``eq:fit-loss``): L_fit = L1 + lambda_ssim DSSIM + lambda_tv TV + lambda_feat L_feat, each
averaged over pixels, with lambda = 0.2, 0.01, 0.01 as in the authors' release. Images are [3, H, W]
or [B, 3, H, W] in [0, 1]; SSIM is the 3DGS one (11 x 11 Gaussian window, sigma 1.5, zero padding,
C1 = 0.01^2, C2 = 0.03^2) and is public for reuse by metrics.

Equation numbers follow the order of the equations in ``paper/DReSG.tex``; each citation also names
the LaTeX label.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..util.errors import ConfigError

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@dataclass(frozen=True)
class FitLossWeights:
    l1: float = 1.0
    dssim: float = 0.2  # lambda_ssim
    tv: float = 0.01  # lambda_tv
    feature: float = 0.01  # lambda_dino: feature loss against the base render
    feature_distance: str = "l1"  # "l1" (mean absolute difference) or "cosine" (1 - cosine along channels)

    def __post_init__(self) -> None:
        for name in ("l1", "dssim", "tv", "feature"):
            value = getattr(self, name)
            if not value >= 0.0:
                raise ConfigError(f"fit loss weight {name} must be >= 0, got {value}")
        if self.feature_distance not in ("l1", "cosine"):
            raise ConfigError(f"feature distance must be 'l1' or 'cosine', got {self.feature_distance!r}")


@dataclass
class FitLossTerms:
    """The weighted total and the unweighted terms; scalars, or [B] with ``per_image=True``."""

    total: torch.Tensor
    l1: torch.Tensor
    dssim: torch.Tensor
    tv: torch.Tensor
    feature: torch.Tensor


def gaussian_window(
    size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, dtype=torch.float32, device=None
) -> torch.Tensor:
    """[size] normalised 1D Gaussian, g_k = exp(-(k - size // 2)^2 / (2 sigma^2)) / sum; its outer product is the 2D window."""
    k = torch.arange(size, dtype=torch.float64, device=device) - size // 2
    g = torch.exp(-(k**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype)


def _blur(x: torch.Tensor, window: torch.Tensor) -> torch.Tensor:  # x [B, C, H, W]
    """Separable depthwise Gaussian filter with zero padding (equal to the 2D window of 3DGS)."""
    c = x.shape[1]
    pad = window.numel() // 2
    x = F.conv2d(x, window.view(1, 1, 1, -1).expand(c, 1, 1, -1), padding=(0, pad), groups=c)
    return F.conv2d(x, window.view(1, 1, -1, 1).expand(c, 1, -1, 1), padding=(pad, 0), groups=c)


def ssim_map(
    x: torch.Tensor, y: torch.Tensor, window_size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA
) -> torch.Tensor:
    """Per-pixel SSIM of images x, y ([C, H, W] or [B, C, H, W]; the output has the input's shape).

    SSIM = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2)), with local
    means and (co)variances from an 11 x 11 Gaussian window (sigma 1.5, zero padding),
    C1 = 0.01^2, C2 = 0.03^2, as in 3DGS; variances are clamped at >= 0 against rounding.

    >>> x = torch.rand(3, 16, 16)
    >>> bool(torch.allclose(ssim_map(x, x), torch.ones(3, 16, 16)))
    True
    """
    xb, yb = _as_batch(x, y)
    window = gaussian_window(window_size, sigma, xb.dtype, xb.device)
    mu_x, mu_y = _blur(xb, window), _blur(yb, window)
    # E[x^2] - mu^2 can round below 0 on flat regions; a negative variance could zero the denominator.
    var_x = (_blur(xb * xb, window) - mu_x**2).clamp_min(0.0)
    var_y = (_blur(yb * yb, window) - mu_y**2).clamp_min(0.0)
    cov = _blur(xb * yb, window) - mu_x * mu_y
    num = (2.0 * mu_x * mu_y + SSIM_C1) * (2.0 * cov + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    out = num / den
    return out if x.ndim == 4 else out[0]


FEATURE_PATCH = 4  # side of a feature's patch, in pooled pixels
FEATURE_CONTRAST_FLOOR = 0.05  # keeps flat patches from being blown up by contrast normalisation


def stride_patches(image: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Patches on a grid of step ``stride``: area-pool ``image`` [B, 3, H, W] by stride/2, take 4x4 patches at step 2.

    Returns (raw, normalised), each [B, 3, 16, h, w] with h = max(1, H // stride) (w alike).
    ``normalised`` is (patch - its mean colour) / (its RMS contrast + FEATURE_CONTRAST_FLOOR).
    """
    b, _, height, width = image.shape
    gh, gw = max(1, height // stride), max(1, width // stride)
    pooled = F.interpolate(image, size=(2 * gh, 2 * gw), mode="area")
    pooled = F.pad(pooled, (1, 1, 1, 1), mode="replicate")
    raw = F.unfold(pooled, FEATURE_PATCH, stride=2).reshape(b, 3, FEATURE_PATCH * FEATURE_PATCH, gh, gw)
    centred = raw - raw.mean(2, keepdim=True)
    contrast = centred.pow(2).mean((1, 2), keepdim=True).add(1e-8).sqrt()
    return raw, centred / (contrast + FEATURE_CONTRAST_FLOOR)


def patch_feature_maps(image: torch.Tensor) -> torch.Tensor:  # image [B, 3, H, W] -> [B, 96, h, w]
    """Fixed, weight-free structure features for the fit loss's feature term when no DINO weights are given.

    The contrast-normalised 4x4 colour patches on grids of step 8 and 16 (the step-16 grid upsampled to
    the step-8 one; h = max(1, H // 8), w alike), differentiable in ``image``. Invariant to a colour
    offset, so they describe local structure rather than the palette: a stylized render whose edges and
    layout stay keeps them near the base render's.

    >>> patch_feature_maps(torch.rand(2, 3, 64, 48)).shape
    torch.Size([2, 96, 8, 6])
    """
    if image.dim() != 4 or image.shape[1] != 3:
        raise ValueError(f"patch_feature_maps expects [B, 3, H, W], got {list(image.shape)}")
    _, fine = stride_patches(image, 8)
    _, coarse = stride_patches(image, 16)
    fine = fine.flatten(1, 2)
    coarse = F.interpolate(coarse.flatten(1, 2), size=fine.shape[-2:], mode="nearest")
    return torch.cat([fine, coarse], 1)


def fit_loss(
    render: torch.Tensor,  # [3, H, W] or [B, 3, H, W]
    target: torch.Tensor,  # same shape
    base_features: torch.Tensor | None = None,  # [B, C, ...] features of the base render, detached
    render_features: torch.Tensor | None = None,  # [B, C, ...] features of ``render``
    weights: FitLossWeights | None = None,
    per_image: bool = False,
) -> FitLossTerms:
    """Eq. 16 (``eq:fit-loss``): L_fit = w_l1 L1 + w_ssim DSSIM + w_tv TV(render) + w_feat L_feat.

    L1 and DSSIM compare the render with the stage target, TV smooths the render, and the feature
    term keeps the render's features near the base render's (skipped when either is None or its
    weight is 0). Every term is a mean over pixels; ``per_image=True`` returns [B] values (one loss
    per view, for per-view gradients), otherwise their mean.
    """
    weights = weights or FitLossWeights()
    rb, tb = _as_batch(render, target)
    l1 = (rb - tb).abs().flatten(1).mean(1)
    ds = (1.0 - ssim_map(rb, tb).flatten(1).mean(1)) / 2.0
    tv = _per_image_tv(rb)
    feature = torch.zeros_like(l1)
    if base_features is not None and render_features is not None and weights.feature > 0.0:
        feature = _per_image_feature(render_features, base_features.detach(), weights.feature_distance)
        if feature.shape != l1.shape:
            raise ValueError(f"features have batch {feature.shape[0]} but the images have batch {l1.shape[0]}")
    total = weights.l1 * l1 + weights.dssim * ds + weights.tv * tv + weights.feature * feature
    terms = FitLossTerms(total, l1, ds, tv, feature)
    if per_image:
        return terms
    return FitLossTerms(*(t.mean() for t in (terms.total, terms.l1, terms.dssim, terms.tv, terms.feature)))


def _per_image_tv(x: torch.Tensor) -> torch.Tensor:  # x [B, C, H, W] -> [B]
    """Anisotropic TV: mean |x[h+1, w] - x[h, w]| + mean |x[h, w+1] - x[h, w]|; an axis one pixel long adds 0."""
    tv = x.new_zeros(x.shape[0])
    if x.shape[2] > 1:
        tv = tv + (x[:, :, 1:] - x[:, :, :-1]).abs().flatten(1).mean(1)
    if x.shape[3] > 1:
        tv = tv + (x[:, :, :, 1:] - x[:, :, :, :-1]).abs().flatten(1).mean(1)
    return tv


def _per_image_feature(a: torch.Tensor, b: torch.Tensor, distance: str) -> torch.Tensor:  # -> [B]
    """Distance "l1": mean |a - b|; "cosine": mean over positions of 1 - cos(a, b) along dim 1 (zero vectors: 1)."""
    if a.shape != b.shape or a.ndim < 2:
        raise ValueError(f"feature shapes {tuple(a.shape)} and {tuple(b.shape)} must match and be [B, C, ...]")
    if distance == "l1":
        return (a - b).abs().flatten(1).mean(1)
    if distance == "cosine":
        return (1.0 - F.cosine_similarity(a, b, dim=1, eps=1e-8)).reshape(a.shape[0], -1).mean(1)
    raise ConfigError(f"feature distance must be 'l1' or 'cosine', got {distance!r}")


def _as_batch(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as [B, C, H, W]; checks that the shapes match and are 3D or 4D."""
    if x.shape != y.shape:
        raise ValueError(f"images have different shapes {tuple(x.shape)} and {tuple(y.shape)}")
    if x.ndim == 3:
        return x.unsqueeze(0), y.unsqueeze(0)
    if x.ndim == 4:
        return x, y
    raise ValueError(f"images must be [C, H, W] or [B, C, H, W], got shape {tuple(x.shape)}")
