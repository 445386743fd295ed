"""Covariance (affine) colour transfer of renders toward the style: the final post colour stage.

One affine map x' = A (x - mu_r) + mu_s is fitted to all renders jointly (so the views stay
consistent with each other) and matches their RGB mean and covariance to the style's:
A = Sigma_s^{1/2} Sigma_r^{-1/2}, with symmetric matrix square roots, gives A Sigma_r A^T = Sigma_s.
Eigenvalues are floored before the inverse root, so flat or grey renders and flat styles stay finite.
The same map applies to Gaussian colours (``ColorTransform.apply_to_colors``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from ..scene.gaussians import SH_C0, GaussianScene
from ..util.errors import CameraError, ImageError, NumericalError
from .style_distance import empirical_quantiles, sort_rows

LUMINANCE = (0.2126, 0.7152, 0.0722)  # Rec. 709
EIGEN_FLOOR = 1e-6  # variance floor (std 1e-3, a quarter of an 8-bit level) for the inverse root
COVERAGE_LOW, COVERAGE_HIGH = 0.25, 0.75  # alpha range over which a pixel goes from kept to recoloured


@dataclass(frozen=True)
class ColorTransform:
    """x' = matrix @ x + offset on RGB colours (float64)."""

    matrix: torch.Tensor  # [3, 3]
    offset: torch.Tensor  # [3]

    def apply_to_colors(self, colors: torch.Tensor) -> torch.Tensor:  # [..., 3] -> [..., 3]
        """The map on colours with RGB in the last axis (e.g. Gaussian base colours [N, 3]); not clamped."""
        m = self.matrix.to(colors.dtype).to(colors.device)
        return colors @ m.T + self.offset.to(colors.dtype).to(colors.device)

    def apply_to_images(self, images: torch.Tensor) -> torch.Tensor:  # [..., 3, H, W] -> same; not clamped
        """The map on images with RGB in axis -3."""
        return self.apply_to_colors(images.movedim(-3, -1)).movedim(-1, -3)


def luminance(image: torch.Tensor) -> torch.Tensor:  # [B, 3, H, W] -> [B, 1, H, W]
    """Rec. 709 luminance 0.2126 R + 0.7152 G + 0.0722 B (:data:`LUMINANCE`) of each image."""
    weights = torch.tensor(LUMINANCE, dtype=image.dtype, device=image.device).view(1, 3, 1, 1)
    return (image * weights).sum(1, keepdim=True)


def coverage_weight(alpha: torch.Tensor) -> torch.Tensor:  # [..., H, W] -> same
    """How much of a restyled image a pixel of a render takes: smoothstep of its alpha from COVERAGE_LOW to
    COVERAGE_HIGH. Background (alpha 0) and faint floaters over it (a few percent) keep the render's
    colour; silhouettes blend."""
    t = ((alpha - COVERAGE_LOW) / (COVERAGE_HIGH - COVERAGE_LOW)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def symmetric_sqrt(cov: torch.Tensor, floor: float = 0.0, inverse: bool = False) -> torch.Tensor:  # [3, 3]
    """Sigma^{1/2} (or Sigma^{-1/2}) = U diag(max(lambda, floor))^{+-1/2} U^T for symmetric Sigma = U diag(lambda) U^T."""
    eigvals, eigvecs = torch.linalg.eigh((cov + cov.T) / 2.0)
    eigvals = eigvals.clamp_min(floor)
    roots = eigvals.rsqrt() if inverse else eigvals.sqrt()
    return (eigvecs * roots) @ eigvecs.T


def color_moments(pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # [M, 3] -> [3], [3, 3]
    """Mean mu = E[x] and covariance Sigma = E[(x - mu)(x - mu)^T] of RGB pixels, in float64."""
    x = pixels.to(torch.float64)
    mean = x.mean(0)
    centred = x - mean
    return mean, centred.T @ centred / x.shape[0]


def covariance_color_transform(
    renders: torch.Tensor,  # [V, 3, H, W] or [3, H, W]
    style: torch.Tensor,  # [3, Hs, Ws]
    render_mask: torch.Tensor | None = None,  # [V, 1, H, W], [V, H, W] (or unbatched); bool or alpha
    style_mask: torch.Tensor | None = None,  # [1, Hs, Ws] or [Hs, Ws]; bool or alpha
    mask_threshold: float = 0.5,
    eigen_floor: float = EIGEN_FLOOR,
) -> ColorTransform:
    """The affine map A x + b with A = Sigma_s^{1/2} Sigma_r^{-1/2}, b = mu_s - A mu_r.

    Statistics are taken over the pixels of all renders together (and of the style), restricted to
    mask > ``mask_threshold`` where a mask is given. Sigma_r's eigenvalues are floored at
    ``eigen_floor`` before the inverse root; Sigma_s's at 0.
    """
    render_pixels = _masked_pixels(renders, render_mask, mask_threshold, "render")
    style_pixels = _masked_pixels(style, style_mask, mask_threshold, "style")
    mu_r, cov_r = color_moments(render_pixels)
    mu_s, cov_s = color_moments(style_pixels)
    matrix = symmetric_sqrt(cov_s) @ symmetric_sqrt(cov_r, floor=eigen_floor, inverse=True)
    offset = mu_s - matrix @ mu_r
    if not (torch.isfinite(matrix).all() and torch.isfinite(offset).all()):
        raise NumericalError("the colour transfer produced non-finite values")
    return ColorTransform(matrix, offset)


def color_transfer(
    renders: torch.Tensor,  # [V, 3, H, W] or [3, H, W]
    style: torch.Tensor,  # [3, Hs, Ws]
    render_mask: torch.Tensor | None = None,
    style_mask: torch.Tensor | None = None,
    mask_threshold: float = 0.5,
    clamp: bool = True,
) -> tuple[torch.Tensor, ColorTransform]:
    """Renders recoloured by ``covariance_color_transform`` (all pixels, clamped to [0, 1] by default), and the map."""
    transform = covariance_color_transform(renders, style, render_mask, style_mask, mask_threshold)
    out = transform.apply_to_images(renders)
    return (out.clamp(0.0, 1.0) if clamp else out), transform


def _masked_pixels(images: torch.Tensor, mask: torch.Tensor | None, threshold: float, what: str) -> torch.Tensor:
    """[M, 3] pixels of [..., 3, H, W] images where mask > threshold (all pixels without a mask)."""
    if images.ndim not in (3, 4) or images.shape[-3] != 3:
        raise ValueError(f"{what} images must be [3, H, W] or [V, 3, H, W], got shape {tuple(images.shape)}")
    if not torch.isfinite(images).all():
        raise NumericalError(f"the {what} image has non-finite values")
    pixels = images.detach().movedim(-3, -1).reshape(-1, 3)
    if mask is not None:
        keep = mask.detach()
        if keep.dtype != torch.bool:
            keep = keep > threshold
        expected = images.shape[:-3] + images.shape[-2:]
        if keep.ndim == images.ndim:  # channel axis of size 1
            keep = keep.squeeze(-3)
        if keep.shape != expected:
            raise ValueError(
                f"{what} mask has shape {tuple(mask.shape)}, expected {tuple(expected)} (with or without a channel axis)"
            )
        pixels = pixels[keep.reshape(-1)]
    if pixels.shape[0] == 0:
        if what == "render":
            raise CameraError("no render pixel is covered by the scene (empty mask); the cameras see nothing")
        raise ImageError("the style image mask keeps no pixel")
    return pixels


@dataclass(frozen=True)
class StyleQuantiles:
    """A style's colours on its colour principal axes, sorted axis by axis: what :func:`match_color_histograms`
    matches to. Sorting them is most of a match's time for a large style, so a caller that matches many images to
    one style sorts them once."""

    mean: torch.Tensor  # [3] float64
    axes: torch.Tensor  # [3, 3] float64, the eigenvectors of the style's colour covariance as columns
    sorted: torch.Tensor  # [3, K] float64: the style's pixels along each axis, increasing

    @classmethod
    def of(cls, style_pixels: torch.Tensor) -> StyleQuantiles:  # [K, 3]
        if style_pixels.ndim != 2 or style_pixels.shape[1] != 3:
            raise ValueError(f"expected [K, 3] style pixels, got {list(style_pixels.shape)}")
        if style_pixels.shape[0] == 0:
            raise ImageError("the style image has no pixels to match colour histograms to")
        mean, cov = color_moments(style_pixels)
        axes = torch.linalg.eigh((cov + cov.T) / 2.0).eigenvectors
        projected = (style_pixels.to(torch.float64) - mean) @ axes
        return cls(mean, axes, sort_rows(projected.T.contiguous()))


def match_color_histograms(pixels: torch.Tensor, style: torch.Tensor | StyleQuantiles) -> torch.Tensor:  # [M, 3]
    """Exact 1-D histogram matching of ``pixels`` to the style's pixels ([K, 3], or their :class:`StyleQuantiles`)
    along the style's colour principal axes.

    Both sets are expressed in the eigenbasis of the style's colour covariance; along each axis the
    pixel of rank i takes the style's quantile (i + 0.5) / M (linear interpolation between sorted style
    values); the result goes back to RGB. Ties keep their order (stable sort), so a flat input maps to
    the style's quantiles in pixel order. Float64 inside; the output is not clamped.
    """
    if pixels.ndim != 2 or pixels.shape[1] != 3:
        raise ValueError(f"expected [M, 3] pixels, got {list(pixels.shape)}")
    if not isinstance(style, StyleQuantiles) and (style.ndim != 2 or style.shape[1] != 3):
        raise ValueError(f"expected [K, 3] style pixels, got {list(style.shape)}")
    if pixels.shape[0] == 0:
        return pixels.clone()
    quantiles = style if isinstance(style, StyleQuantiles) else StyleQuantiles.of(style)
    x = (pixels.to(torch.float64) - quantiles.mean) @ quantiles.axes
    ranked = empirical_quantiles(quantiles.sorted, x.shape[0]).T  # [M, 3], per axis, by rank
    order = torch.sort(x, dim=0, stable=True).indices  # [M, 3]
    matched = torch.empty_like(x)
    matched.scatter_(0, order, ranked)
    return (matched @ quantiles.axes.T + quantiles.mean).to(pixels.dtype)


def transfer_scene_colors(
    scene: GaussianScene,
    renders: torch.Tensor,  # [V, 3, H, W] base renders of the scene
    alphas: torch.Tensor,  # [V, H, W] their coverage
    style: torch.Tensor,  # [3, Hs, Ws]
) -> GaussianScene:
    """The colour-only stylization: one covariance map from the covered pixels of ``renders`` to the style,
    applied to every splat's base colour (clamped to [0, 1]); view-dependent SH bands are dropped.

    It is the paper's post stage on its own, and the baseline a stylization must beat: a per-splat colour
    change, so its cross-view consistency is the scene's own. ``scene`` is not modified.
    """
    transform = covariance_color_transform(renders, style, render_mask=alphas)
    colors = torch.from_numpy(np.maximum(0.5 + SH_C0 * scene.sh_dc.astype(np.float64), 0.0))
    mapped = transform.apply_to_colors(colors).clamp(0.0, 1.0).numpy()
    out = replace(scene, sh_dc=((mapped - 0.5) / SH_C0).astype(np.float32))
    return out if scene.sh_rest is None else replace(out, sh_rest=np.zeros_like(scene.sh_rest))


HISTOGRAM_QUANTILES = 257  # knots of a ColorMap's per-axis curves


@dataclass(frozen=True)
class ColorMap:
    """One function of colour, the same for every image it is applied to: the covariance transfer, then one
    monotone piecewise-linear curve per principal colour axis of the style that takes the fitted pixels'
    histogram along that axis to the style's (``fit_color_map``).

    Fitted on the covered pixels of all the views at once, it recolours each view the same way, so a
    surface seen by two views gets the same colour in both (per-image statistics would not).
    """

    transform: ColorTransform
    origin: torch.Tensor  # [3] the style's mean colour, origin of the axes
    axes: torch.Tensor  # [3, 3] the style's colour principal axes (columns)
    source: torch.Tensor | None  # [3, K] sorted knots: quantiles of the transferred pixels along each axis
    target: torch.Tensor | None  # [3, K] the style's quantiles at the same levels

    def apply_to_images(self, images: torch.Tensor) -> torch.Tensor:  # [..., 3, H, W] -> same; not clamped
        x = self.transform.apply_to_images(images.to(torch.float64))
        if self.source is None:
            return x.to(images.dtype)
        y = (x.movedim(-3, -1) - self.origin) @ self.axes  # [..., H, W, 3]
        for c in range(3):
            y[..., c] = _monotone_curve(y[..., c], self.source[c], self.target[c])
        return (y @ self.axes.T + self.origin).movedim(-1, -3).to(images.dtype)


def _monotone_curve(x: torch.Tensor, knots: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear y(x) through (knots, values) (both non-decreasing), continued with slope 1 outside.

    Flat runs of knots (a repeated value) take the mean of their values, so the curve is a function.
    """
    shape = x.shape
    x = x.contiguous().reshape(-1)
    k = knots.numel()
    index = torch.searchsorted(knots, x).clamp(1, k - 1)  # knots[index - 1] <= x < knots[index] inside
    x0, x1 = knots[index - 1], knots[index]
    y0, y1 = values[index - 1], values[index]
    span = x1 - x0
    t = torch.where(span > 0, (x - x0) / torch.where(span > 0, span, 1.0), 0.5)
    y = y0 + t.clamp(0.0, 1.0) * (y1 - y0)
    y = torch.where(x < knots[0], values[0] + (x - knots[0]), y)
    y = torch.where(x > knots[-1], values[-1] + (x - knots[-1]), y)
    return y.reshape(shape)


def fit_color_map(
    images,  # [V, 3, H, W] or a list of [3, H, W] (sizes may differ)
    style: torch.Tensor,  # [3, Hs, Ws]
    masks=None,  # [V, H, W] or a list of [H, W] (bool or alpha); None: every pixel
    histogram: bool = True,
    mask_threshold: float = 0.5,
) -> ColorMap:
    """The :class:`ColorMap` of ``images`` (their covered pixels pooled) to ``style``.

    Covariance transfer (``covariance_color_transform``) of the pooled pixels, then, when ``histogram``,
    HISTOGRAM_QUANTILES matched quantiles per style colour axis: the pooled pixels' histogram along each
    axis goes to the style's, as ``match_color_histograms`` does for one set, but as a curve that maps
    any colour.
    """
    images = list(images)
    if masks is None:
        masks = [None] * len(images)
    pooled = []
    for image, mask in zip(images, masks):
        try:
            pooled.append(_masked_pixels(image, mask, mask_threshold, "render"))
        except CameraError:
            continue  # a view that sees nothing adds nothing; all of them empty is an error below
    if not pooled:
        raise CameraError("no render pixel is covered by the scene (empty masks); the cameras see nothing")
    pixels = torch.cat(pooled)
    stack = pixels.T.reshape(3, -1, 1)  # a [3, M, 1] image of the pooled pixels
    transform = covariance_color_transform(stack, style)
    mu_s, cov_s = color_moments(_masked_pixels(style, None, mask_threshold, "style"))
    axes = torch.linalg.eigh((cov_s + cov_s.T) / 2.0).eigenvectors
    if not histogram:
        return ColorMap(transform, mu_s, axes, None, None)
    levels = torch.linspace(0.0, 1.0, HISTOGRAM_QUANTILES, dtype=torch.float64)  # min and max included
    mapped = (transform.apply_to_colors(pixels.to(torch.float64)) - mu_s) @ axes
    reference = (style.detach().reshape(3, -1).T.to(torch.float64) - mu_s) @ axes
    return ColorMap(transform, mu_s, axes, _column_quantiles(mapped, levels), _column_quantiles(reference, levels))


def _column_quantiles(samples: torch.Tensor, levels: torch.Tensor) -> torch.Tensor:  # [M, 3], [K] -> [3, K]
    """Quantiles of each column at ``levels`` in [0, 1] (0: the minimum, 1: the maximum), linear between
    order statistics."""
    ordered = torch.sort(samples, dim=0).values  # [M, 3]
    position = levels * (samples.shape[0] - 1)
    low = position.floor().long()
    high = (low + 1).clamp_max(samples.shape[0] - 1)
    frac = (position - low)[:, None]
    return (ordered[low] * (1.0 - frac) + ordered[high] * frac).T.contiguous()
