"""Weight-free evaluation metrics: style, content, cross-view consistency and efficiency.

The paper's metrics (CLIP-S, DINO-C, RAFT-aligned RMSE; REFERENCE.md section 2) need weights that
are not always at hand. These stand in for them, and :mod:`.clip_dino` computes the real CLIP-S and
DINO-C when the user has local weights.

=======================================  =========  ==================================================
metric                                   better     compares
=======================================  =========  ==================================================
:func:`sliced_wasserstein_colors`        lower      colour distribution of a render and the style image (masks)
:func:`sliced_wasserstein_patches`       lower      7 x 7 patch distribution, render and style image (masks)
:func:`ssim_per_image`                   higher     stylized and base render from the same camera (mask)
:func:`gradient_structure_similarity`    higher     stylized and base render from the same camera (mask)
:func:`texture_kept`                     lower      fine texture of the stylized and base render (mask)
:func:`shape_similarity`                 higher     blurred forms of the stylized and base render (mask)
:func:`forms_similarity`                 higher     blurred forms' structure alone, stylized and base render (mask)
:func:`mark_contrast`                    near 1     the render's own marks, three bands, against the painting's (mask)
:func:`consistency_rmse`                 lower      a render warped exactly into a later view, and that view
:func:`measure_render`                   higher FPS render speed and peak memory of a scene
:func:`read_stylize_log`                 lower      optimisation time and peak memory from the stylizer's log
=======================================  =========  ==================================================

Images are torch [3, H, W] or [B, 3, H, W] in [0, 1] (``warp_to`` takes renders as [H, W, 3], the
rasterizer's layout). Functions work in float32 and float64 and never return NaN: degenerate inputs
(flat images, empty views) have defined values, and a consistency pair without valid pixels reports
``None`` with a coverage of 0.

The style and content metrics take optional coverage masks, [H, W] per image: bool, or alpha in
[0, 1] where alpha > ``ALPHA_THRESHOLD`` counts as covered. An object rendered on a black background
is then measured on the pixels it covers, not on the background. An image whose mask covers nothing
is measured as if unmasked (all pixels), so the value stays defined.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from ..method.color_transfer import luminance
from ..method.losses import SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, _blur, gaussian_window, ssim_map
from ..method.style_distance import (
    ALPHA_THRESHOLD,
    empirical_quantiles,
    sliced_wasserstein,
    sliced_wasserstein_colors,
    sliced_wasserstein_patches,
    sorted_projections,
)
from ..scene.camera import Camera
from ..scene.warp import DEPTH_TOLERANCE, warp_to
from ..util.errors import ConfigError, with_path
from ..util.machine import peak_rss_mb

GRADIENT_FLOOR = 1e-3  # the gradient magnitude (per pixel, [0, 1] images) below which an image is flat
TEXTURE_FLOOR = 1e-4  # the RMS luminance high-pass ([0, 1] images) at or below which an image has no texture
# Mark contrast's luminance bands: differences of Gaussians of these sigmas (px of the fit size), fine to coarse.
MARK_BANDS = (("marks_fine", 0.6, 1.2), ("marks_mid", 1.2, 2.4), ("marks_coarse", 2.4, 4.8))

# The style distances are the method's own (it stops its stages on them); they are metrics here too.
__all__ = [
    "ALPHA_THRESHOLD",
    "ConsistencyResult",
    "PairConsistency",
    "RenderBenchmark",
    "StylizeLogSummary",
    "consistency_rmse",
    "empirical_quantiles",
    "forms_similarity",
    "gaussian_blur",
    "gradient_structure_similarity",
    "luminance",
    "mark_band_scales",
    "mark_contrast",
    "mark_length",
    "masked_rmse",
    "measure_render",
    "peak_rss_mb",
    "read_stylize_log",
    "shape_similarity",
    "sliced_wasserstein",
    "sliced_wasserstein_colors",
    "sliced_wasserstein_patches",
    "sobel_gradients",
    "sorted_projections",
    "ssim_per_image",
    "texture_kept",
    "warp_to",
]


# ----------------------------------------------------------------------------------------------------
# Content: SSIM and gradient structure to the base render


def _pair_batch(a: torch.Tensor, b: torch.Tensor, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    if a.shape != b.shape or a.ndim not in (3, 4) or a.shape[-3] != 3:
        raise ValueError(
            f"{name}: images must both be [3, H, W] or [B, 3, H, W], got {tuple(a.shape)}, {tuple(b.shape)}"
        )
    return (a[None], b[None]) if a.ndim == 3 else (a, b)


def _pair_mask(mask, batch: torch.Tensor, name: str) -> torch.Tensor | None:  # -> [B, H, W] bool
    """[H, W] (every pair) or [B, H, W] mask as bool (alpha > ``ALPHA_THRESHOLD``); an empty one covers all."""
    if mask is None:
        return None
    b, _, h, w = batch.shape
    mask = torch.as_tensor(mask, device=batch.device)
    if tuple(mask.shape) not in ((h, w), (b, h, w)):
        raise ValueError(f"{name}: mask must be [H, W] or [B, H, W] = {[b, h, w]}, got shape {tuple(mask.shape)}")
    covered = (mask if mask.dtype == torch.bool else mask > ALPHA_THRESHOLD).expand(b, h, w)
    return covered | ~covered.flatten(1).any(1)[:, None, None]


def ssim_per_image(
    a: torch.Tensor,  # [3, H, W] or [B, 3, H, W]
    b: torch.Tensor,  # same shape
    mask=None,  # [H, W] or [B, H, W]: bool, or alpha
) -> torch.Tensor:  # scalar or [B]
    """Mean SSIM of each image pair (the 3DGS SSIM of :func:`dresg_addon.method.losses.ssim_map`).

    With ``mask`` (bool, or alpha > ``ALPHA_THRESHOLD``): both images are set to 0 outside it (as on
    a black background, so the background cannot change the value), and SSIM = sum_{p covered, c}
    SSIM_c(p) / (3 |covered|). An empty mask counts as covering every pixel.

    >>> x = torch.rand(2, 3, 16, 16)
    >>> ssim_per_image(x, x).tolist()
    [1.0, 1.0]
    >>> covered = torch.arange(16) < 8  # left half; the right halves differ
    >>> round(float(ssim_per_image(x[0], x[1] * ~covered + x[0] * covered, covered.expand(16, 16))), 6)
    1.0
    """
    ab, bb = _pair_batch(a, b, "ssim_per_image")
    covered = _pair_mask(mask, ab, "ssim_per_image")
    if covered is None:
        out = ssim_map(ab, bb).flatten(1).mean(1)
    else:
        keep = covered[:, None]
        smap = ssim_map(torch.where(keep, ab, 0.0), torch.where(keep, bb, 0.0))
        out = torch.where(keep, smap, 0.0).flatten(1).sum(1) / (3 * covered.flatten(1).sum(1)).to(smap.dtype)
    return out if a.ndim == 4 else out[0]


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:  # [B, C, H, W] -> [B, C, H, W]
    """Separable Gaussian blur of standard deviation ``sigma`` pixels, replicated border.

    The kernel is :func:`dresg_addon.method.losses.gaussian_window` over 2 ceil(3 sigma) + 1 taps (at
    least 3), normalised to sum 1, so a constant image stays constant; the filter is the SSIM window's
    (:func:`dresg_addon.method.losses._blur`) on the image padded by replicating its edge pixels, so the
    image border does not darken. Each channel is blurred on its own.

    >>> x = torch.rand(1, 1, 12, 12)
    >>> bool(torch.allclose(gaussian_blur(torch.full_like(x, 0.3), 2.0), torch.full_like(x, 0.3)))
    True
    """
    if not (math.isfinite(sigma) and sigma > 0.0):
        raise ValueError(f"gaussian_blur: sigma must be a positive number of pixels, got {sigma!r}")
    radius = max(1, math.ceil(3.0 * sigma))
    window = gaussian_window(2 * radius + 1, sigma, x.dtype, x.device)
    blurred = _blur(F.pad(x, (radius, radius, radius, radius), mode="replicate"), window)
    return blurred[..., radius:-radius, radius:-radius]


def sobel_gradients(image: torch.Tensor) -> torch.Tensor:  # [B, 3, H, W] -> [B, 2, H, W]
    """Sobel gradient (d/dx, d/dy) of the Rec. 709 luminance, kernels divided by 8, replicate padding.

    With the 1/8 normalisation a linear ramp of slope s per pixel has gradient exactly s; replicate
    padding keeps the image border from looking like an edge.
    """
    luma = luminance(image)
    kx = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=image.dtype, device=image.device)
    kernels = torch.stack([kx, kx.T])[:, None] / 8.0  # [2, 1, 3, 3]
    return F.conv2d(F.pad(luma, (1, 1, 1, 1), mode="replicate"), kernels)


def gradient_structure_similarity(
    a: torch.Tensor,  # [3, H, W] or [B, 3, H, W]
    b: torch.Tensor,  # same shape
    floor: float = GRADIENT_FLOOR,
    mask=None,  # [H, W] or [B, H, W]: bool, or alpha
) -> torch.Tensor:  # scalar or [B]
    """Gradient-structure similarity of two images, in [0, 1]; 1 for the same edges.

    GS = (sum_p |g_a(p) . g_b(p)| + C) / sqrt((sum_p |g_a(p)|^2 + C)(sum_p |g_b(p)|^2 + C)), with g the
    :func:`sobel_gradients` of the luminance and C = P floor^2 (P pixels). It is a magnitude-weighted
    mean of |cos| between the gradient directions: strong edges count most, a global contrast change
    and a per-pixel polarity flip (stylization remaps colours) do not lower it, and edges missing in
    one image do. Cauchy-Schwarz bounds it by 1, reached (up to C) iff g_b = +-k g_a pixelwise, one k > 0.
    Two flat images give 1; a flat image against a textured one gives about
    sqrt(C / sum |g|^2), near 0.

    With ``mask`` (bool, or alpha > ``ALPHA_THRESHOLD``): both images are set to 0 outside it (as on
    a black background), and the sums run over the covered pixels only, with C = |covered| floor^2.
    An empty mask counts as covering every pixel.

    >>> x = torch.rand(3, 32, 32, dtype=torch.float64)
    >>> round(float(gradient_structure_similarity(x, 0.2 + 0.5 * x)), 3)  # contrast change
    1.0
    >>> float(gradient_structure_similarity(x, torch.full_like(x, 0.5))) < 0.05  # structure gone
    True
    """
    ab, bb = _pair_batch(a, b, "gradient_structure_similarity")
    covered = _pair_mask(mask, ab, "gradient_structure_similarity")
    if covered is None:
        ga, gb = sobel_gradients(ab), sobel_gradients(bb)
        c = ab.shape[-1] * ab.shape[-2] * floor**2
        dot = (ga * gb).sum(1).abs().flatten(1).sum(1)
        norm_a = (ga * ga).flatten(1).sum(1)
        norm_b = (gb * gb).flatten(1).sum(1)
    else:
        keep = covered[:, None]
        ga, gb = sobel_gradients(torch.where(keep, ab, 0.0)), sobel_gradients(torch.where(keep, bb, 0.0))
        c = covered.flatten(1).sum(1).to(ga.dtype) * floor**2
        dot = torch.where(covered, (ga * gb).sum(1).abs(), 0.0).flatten(1).sum(1)
        norm_a = torch.where(covered, (ga * ga).sum(1), 0.0).flatten(1).sum(1)
        norm_b = torch.where(covered, (gb * gb).sum(1), 0.0).flatten(1).sum(1)
    out = ((dot + c) / torch.sqrt((norm_a + c) * (norm_b + c))).clamp(0.0, 1.0)
    return out if a.ndim == 4 else out[0]


def _check_erode(erode, name: str) -> None:
    if isinstance(erode, bool) or not isinstance(erode, int) or erode < 0:
        raise ValueError(f"{name}: erode must be an integer >= 0 pixels, got {erode!r}")


def _eroded(covered: torch.Tensor | None, erode: int, like: torch.Tensor) -> torch.Tensor:  # -> [B, H, W] bool
    """The pixels every pixel within ``erode`` px of which is covered (all of ``like``'s [B, H, W] without a mask)."""
    if covered is None:
        return torch.ones(like.shape[0], *like.shape[-2:], dtype=torch.bool, device=like.device)
    if erode == 0:
        return covered
    # max-pooling pads with -inf: pixels off the image are not uncovered
    uncovered = (~covered)[:, None].to(like.dtype)
    return F.max_pool2d(uncovered, 2 * erode + 1, stride=1, padding=erode)[:, 0] == 0


def _covered_luminance(ab: torch.Tensor, covered: torch.Tensor | None) -> torch.Tensor:  # -> [B, 1, H, W]
    """The :func:`luminance` of each image, 0 outside ``covered`` (as on a black background)."""
    luma = luminance(ab)
    return luma if covered is None else torch.where(covered[:, None], luma, 0.0)


def texture_kept(
    image: torch.Tensor,  # [3, H, W] or [B, 3, H, W]: the stylized render
    base: torch.Tensor,  # same shape: the unstylized render from the same camera
    mask=None,  # [H, W] or [B, H, W]: bool, or alpha
    sigma: float = 2.0,
    erode: int = 4,
) -> torch.Tensor:  # scalar or [B]
    """How much of the base render's fine texture the image still has: a correlation in [-1, 1].

    With Y the :func:`luminance` and h = Y - :func:`gaussian_blur` (Y, ``sigma``) its high-pass (detail
    finer than about ``sigma`` px), the value is the Pearson correlation of h_image and h_base over the
    counted pixels P: sum_P (h_i - mean_P h_i)(h_b - mean_P h_b) / sqrt(sum_P (h_i - mean_P h_i)^2
    sum_P (h_b - mean_P h_b)^2). 1: the capture's own fine texture is all still there (up to a contrast
    gain); about 0: it was replaced (a painting's marks, noise, or nothing); negative: inverted.

    Counted pixels: with ``mask`` (bool, or alpha > ``ALPHA_THRESHOLD``; an empty mask counts as
    covering every pixel), both images are set to 0 outside it (as on a black background, so the
    background cannot change the value) and a pixel counts only if every pixel within ``erode`` px
    (the (2 erode + 1)^2 square around it; pixels off the image do not count against it) is covered,
    so the silhouette's own edge, shared by both renders, is left out. Without a mask every pixel counts.

    Degenerate cases give 0.0, never NaN: no pixel left after the erosion, or either image without
    texture on the counted pixels (RMS of h_i - mean_P h_i at most :data:`TEXTURE_FLOOR`, e.g. a
    flat image: there is no texture to keep, or none was kept).

    >>> x = torch.rand(2, 3, 24, 24)
    >>> [round(v, 6) for v in texture_kept(x, x).tolist()]
    [1.0, 1.0]
    >>> float(texture_kept(x[0], torch.full_like(x[0], 0.5)))  # a flat base: nothing to keep
    0.0
    """
    ab, bb = _pair_batch(image, base, "texture_kept")
    _check_erode(erode, "texture_kept")
    covered = _pair_mask(mask, ab, "texture_kept")
    luma_a, luma_b = _covered_luminance(ab, covered), _covered_luminance(bb, covered)
    high_a = (luma_a - gaussian_blur(luma_a, sigma))[:, 0]  # [B, H, W]
    high_b = (luma_b - gaussian_blur(luma_b, sigma))[:, 0]
    weight = _eroded(covered, erode, high_a).to(high_a.dtype)
    count = weight.flatten(1).sum(1).clamp_min(1.0)[:, None, None]  # [B, 1, 1]
    da = (high_a - (high_a * weight).flatten(1).sum(1)[:, None, None] / count) * weight
    db = (high_b - (high_b * weight).flatten(1).sum(1)[:, None, None] / count) * weight
    var_a = (da * da).flatten(1).sum(1) / count[:, 0, 0]
    var_b = (db * db).flatten(1).sum(1) / count[:, 0, 0]
    cov = (da * db).flatten(1).sum(1) / count[:, 0, 0]
    flat = (var_a <= TEXTURE_FLOOR**2) | (var_b <= TEXTURE_FLOOR**2)  # also: no counted pixel (both 0)
    scale = torch.sqrt(torch.where(flat, 1.0, var_a * var_b))
    out = torch.where(flat, 0.0, cov / scale).clamp(-1.0, 1.0)
    return out if image.ndim == 4 else out[0]


def shape_similarity(
    image: torch.Tensor,  # [3, H, W] or [B, 3, H, W]: the stylized render
    base: torch.Tensor,  # same shape: the unstylized render from the same camera
    mask=None,  # [H, W] or [B, H, W]: bool, or alpha
    sigma: float = 3.0,
) -> torch.Tensor:  # scalar or [B]
    """Shapes: SSIM of the forms, with the fine texture blurred away; 1 for the same forms.

    :func:`ssim_per_image` of :func:`gaussian_blur` (Y, ``sigma``) of the image against that of the
    base, Y the :func:`luminance`: brush marks, noise and texture finer than about ``sigma`` px
    (the Gaussian's sigma) do not lower it, changed or missing forms and a changed tone layout do.

    With ``mask`` (bool, or alpha > ``ALPHA_THRESHOLD``; an empty one counts as covering every pixel):
    the luminance is set to 0 outside it before the blur (as on a black background, so the background
    cannot change the value) and the SSIM is the mean over the covered pixels, as in
    :func:`ssim_per_image`. Flat images have a defined value (SSIM's constants), never NaN.

    >>> x = torch.rand(3, 24, 24)
    >>> round(float(shape_similarity(x, x)), 6)
    1.0
    """
    ab, bb = _pair_batch(image, base, "shape_similarity")
    covered = _pair_mask(mask, ab, "shape_similarity")
    forms_a = gaussian_blur(_covered_luminance(ab, covered), sigma).expand(-1, 3, -1, -1)
    forms_b = gaussian_blur(_covered_luminance(bb, covered), sigma).expand(-1, 3, -1, -1)
    out = ssim_per_image(forms_a, forms_b, mask=covered)
    return out if image.ndim == 4 else out[0]


def _covered_blur(x: torch.Tensor, weight: torch.Tensor | None, sigma: float) -> torch.Tensor:  # [B, C, H, W]
    """:func:`gaussian_blur` over the covered pixels alone, blur(x w) / blur(w) (a normalised convolution): the
    background and the silhouette's edge do not reach the covered pixels; 0 where nothing covered is near."""
    if weight is None:
        return gaussian_blur(x, sigma)
    den = gaussian_blur(weight, sigma)
    return torch.where(den > 1e-6, gaussian_blur(x * weight, sigma) / den.clamp_min(1e-6), 0.0)


def luminance_bands(
    luma: torch.Tensor,  # [B, 1, H, W]
    weight: torch.Tensor | None = None,  # [B, 1, H, W]: 1 covered, 0 not; None: every pixel
    bands=MARK_BANDS,  # (name, inner sigma, outer sigma) px
) -> torch.Tensor:  # [B, len(bands), H, W]
    """Band-passes of the luminance: differences of Gaussians, blur(Y, inner) - blur(Y, outer), each blur over the
    covered pixels alone (:func:`_covered_blur`)."""
    sigmas = sorted({sigma for _, inner, outer in bands for sigma in (inner, outer)})
    blurred = {sigma: _covered_blur(luma, weight, sigma) for sigma in sigmas}
    return torch.cat([blurred[inner] - blurred[outer] for _, inner, outer in bands], 1)


def mark_band_scales(painting: torch.Tensor) -> torch.Tensor:  # [3, h, w] -> [len(MARK_BANDS)] float64
    """The standard deviation of each :data:`MARK_BANDS` band of the painting's luminance, over the whole painting
    (given at the view's scale: resampled to the view's size x Stroke Size)."""
    if painting.ndim != 3 or painting.shape[0] != 3:
        raise ValueError(f"mark_band_scales: the painting must be [3, H, W], got {tuple(painting.shape)}")
    bands = luminance_bands(luminance(painting[None].to(torch.float64)))[0]
    return (bands - bands.mean((1, 2), keepdim=True)).square().mean((1, 2)).sqrt()


def mark_contrast(
    image: torch.Tensor,  # [3, H, W] or [B, 3, H, W]: the stylized render
    base: torch.Tensor,  # same shape: the unstylized render from the same camera
    painting: torch.Tensor,  # [3, h, w]: the painting at the view's scale (the view's size x Stroke Size)
    mask=None,  # [H, W] or [B, H, W]: bool, or alpha
    erode: int = 4,
) -> torch.Tensor:  # [3] or [B, 3]: fine, mid, coarse
    """The render's own marks against the painting's, per luminance band of :data:`MARK_BANDS`: 1 as strong as the
    painting's, about 0 none.

    In each band (:func:`luminance_bands`, a difference of Gaussians at sigma 0.6/1.2, 1.2/2.4 and 2.4/4.8 px) the
    image's band a is regressed on the base's band b over the counted pixels P, and what the capture's texture
    explains taken out: r = (a - mean_P a) - beta (b - mean_P b), beta = cov_P(a, b) / var_P(b) (0 for a flat b).
    The value is sqrt(mean_P r^2) over the painting's own band standard deviation (:func:`mark_band_scales`): the
    painting itself over a flat base gives 1, a blurred copy of it about 0, the base itself (or any contrast of its
    texture) 0, and the base plus the painting's band about 1.

    With ``mask`` (bool, or alpha > ``ALPHA_THRESHOLD``; an empty one counts as covering every pixel) the blurs run
    over the covered pixels alone, so the background and the silhouette's edge do not make marks, and a pixel counts
    only if every pixel within ``erode`` px is covered (as in :func:`texture_kept`). Degenerate cases give 0.0,
    never NaN: a flat painting (a band's deviation at most :data:`TEXTURE_FLOOR`), no counted pixel.

    >>> painting = torch.rand(3, 24, 32)
    >>> [round(v, 6) for v in mark_contrast(painting, torch.full_like(painting, 0.5), painting).tolist()]
    [1.0, 1.0, 1.0]
    >>> mark_contrast(painting, painting, painting).tolist()
    [0.0, 0.0, 0.0]
    """
    ab, bb = _pair_batch(image, base, "mark_contrast")
    _check_erode(erode, "mark_contrast")
    covered = _pair_mask(mask, ab, "mark_contrast")
    scales = mark_band_scales(painting).to(ab.device)  # [n]
    weight = None if covered is None else covered[:, None].to(torch.float64)
    band_a = luminance_bands(luminance(ab.to(torch.float64)), weight)  # [B, n, H, W]
    band_b = luminance_bands(luminance(bb.to(torch.float64)), weight)
    counted = _eroded(covered, erode, ab)[:, None].to(torch.float64)  # [B, 1, H, W]
    count = counted.sum((2, 3), keepdim=True).clamp_min(1.0)

    def centred(band: torch.Tensor) -> torch.Tensor:
        return (band - (band * counted).sum((2, 3), keepdim=True) / count) * counted

    da, db = centred(band_a), centred(band_b)
    var_b = (db * db).sum((2, 3), keepdim=True) / count
    cov = (da * db).sum((2, 3), keepdim=True) / count
    beta = torch.where(var_b > TEXTURE_FLOOR**2, cov / var_b.clamp_min(TEXTURE_FLOOR**2), 0.0)
    spread = ((da - beta * db).square().sum((2, 3)) / count[:, :, 0, 0]).sqrt()  # [B, n]
    out = torch.where(scales > TEXTURE_FLOOR, spread / scales.clamp_min(TEXTURE_FLOOR), 0.0).to(ab.dtype)
    return out if image.ndim == 4 else out[0]


MARK_LENGTH_BAND = 0  # the band of MARK_BANDS whose marks are followed (the fine one: a stroke's bristles)
MARK_LENGTH_REACH = 32  # px: the longest shift the correlation is followed to (a longer mark counts as this)
ORIENTATION_SIGMA = 4.0  # px: the structure tensor's window, the scale at which a mark has one direction


def mark_length(
    image: torch.Tensor,  # [3, H, W]
    mask=None,  # [H, W]: bool, or alpha
    erode: int = 4,
) -> tuple[float, float]:  # (along, across) in px
    """How far the marks run: the distance at which the luminance band's correlation with itself, shifted along the
    local mark direction, falls to a half (``along``), and the same across it (``across``).

    The band is :data:`MARK_BANDS`' fine one (a difference of Gaussians at sigma 0.6/1.2 px: a stroke's bristles and
    edges); the direction at each pixel is the structure tensor's (gradients of the band, summed over a Gaussian
    window of :data:`ORIENTATION_SIGMA` px), the mark running across its strongest gradient, so swirling strokes are
    followed round. The correlation is over the counted pixels (every pixel within ``erode`` px covered) whose
    shifted place is counted too, shifts by bilinear sampling, at whole pixels up to :data:`MARK_LENGTH_REACH` (the
    half crossing linearly interpolated; a mark longer than the reach counts as the reach). Long bristled strokes give
    a long ``along`` and an ``across`` of about a pixel; strokes cut into short pieces a short ``along``; noise about
    half a pixel both ways; a flat image 0.0. A blur lengthens both (the band of a smooth image correlates far every
    way), so ``along / across``, the marks' elongation, is the measure to compare: blobs give about 2, the demo's
    painting about 5.5."""
    ab = image[None].to(torch.float64)
    covered = _pair_mask(mask, ab, "mark_length")
    _check_erode(erode, "mark_length")
    weight = None if covered is None else covered[:, None].to(torch.float64)
    _, inner, outer = MARK_BANDS[MARK_LENGTH_BAND]
    band = luminance_bands(luminance(ab), weight, ((None, inner, outer),))  # [1, 1, H, W]
    counted = _eroded(covered, erode, ab)[:, None].to(torch.float64)
    gy = torch.zeros_like(band)
    gx = torch.zeros_like(band)
    gy[..., 1:-1, :] = (band[..., 2:, :] - band[..., :-2, :]) / 2.0
    gx[..., :, 1:-1] = (band[..., :, 2:] - band[..., :, :-2]) / 2.0
    tensor = gaussian_blur(torch.cat([gx * gx, gx * gy, gy * gy], 1) * counted, ORIENTATION_SIGMA)
    gradient = 0.5 * torch.atan2(2.0 * tensor[:, 1], tensor[:, 0] - tensor[:, 2])  # [1, H, W]: strongest gradient
    height, width = band.shape[-2:]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    values = band[0, 0][counted[0, 0] > 0]
    if values.numel() < 2 or float(values.std()) <= TEXTURE_FLOOR:
        return 0.0, 0.0

    def length(angle: torch.Tensor) -> float:
        dx, dy = torch.cos(angle[0]), torch.sin(angle[0])
        previous = 1.0
        for step in range(1, MARK_LENGTH_REACH + 1):
            grid = torch.stack(
                [(xs + step * dx) * 2.0 / (width - 1) - 1.0, (ys + step * dy) * 2.0 / (height - 1) - 1.0], -1
            )[None]
            moved = F.grid_sample(torch.cat([band, counted], 1), grid, align_corners=True, padding_mode="zeros")
            pair = (counted[0, 0] > 0) & (moved[0, 1] > 0.999)
            if int(pair.sum()) < 2:
                return float(step)
            a, b = band[0, 0][pair], moved[0, 0][pair]
            a, b = a - a.mean(), b - b.mean()
            rho = float((a * b).sum() / ((a.square().sum() * b.square().sum()).sqrt().clamp_min(1e-30)))
            if rho < 0.5:
                return step - 1 + (previous - 0.5) / max(previous - rho, 1e-12)
            previous = rho
        return float(MARK_LENGTH_REACH)

    return length(gradient + math.pi / 2), length(gradient)


def forms_similarity(
    image: torch.Tensor,  # [3, H, W] or [B, 3, H, W]: the stylized render
    base: torch.Tensor,  # same shape: the unstylized render from the same camera
    mask=None,  # [H, W] or [B, H, W]: bool, or alpha
    sigma: float = 3.0,
) -> torch.Tensor:  # scalar or [B]
    """Forms: SSIM's structure term alone on the blurred luminance, in [-1, 1]; 1 for the same forms at any
    brightness and contrast.

    With f = :func:`gaussian_blur` (Y, ``sigma``) of each :func:`luminance`, the local means, deviations and
    covariance over SSIM's 11 x 11 Gaussian window (sigma 1.5) give s = (cov + C3) / (sd_image sd_base + C3),
    C3 = C2 / 2 = 0.03^2 / 2, averaged over the covered pixels: changed or missing forms lower it, a palette that
    is brighter, darker or of other contrast than the capture does not (SSIM's luminance and contrast terms are
    left out: :func:`shape_similarity` keeps them). Marks on a flat part of the base (sd_base near 0) cost little.

    With ``mask`` (bool, or alpha > ``ALPHA_THRESHOLD``; an empty one counts as covering every pixel) the blur and
    the window run over the covered pixels alone (normalised convolutions), so the silhouette is no shared form.
    Flat images give 1 (both) or about C3 / (sd sd + C3); never NaN.

    >>> x = torch.rand(3, 24, 24)
    >>> round(float(forms_similarity(0.2 + 0.5 * x, x)), 6)
    1.0
    """
    ab, bb = _pair_batch(image, base, "forms_similarity")
    covered = _pair_mask(mask, ab, "forms_similarity")
    weight = (
        torch.ones(ab.shape[0], 1, *ab.shape[2:], dtype=torch.float64, device=ab.device)
        if covered is None
        else covered[:, None].to(torch.float64)
    )
    forms_a = _covered_blur(luminance(ab.to(torch.float64)), weight, sigma)
    forms_b = _covered_blur(luminance(bb.to(torch.float64)), weight, sigma)
    window = gaussian_window(SSIM_WINDOW, SSIM_SIGMA, torch.float64, ab.device)
    den = _blur(weight, window).clamp_min(1e-6)

    def local(x: torch.Tensor) -> torch.Tensor:  # the window's weighted mean over the covered pixels
        return _blur(x * weight, window) / den

    mu_a, mu_b = local(forms_a), local(forms_b)
    var_a = (local(forms_a * forms_a) - mu_a**2).clamp_min(0.0)
    var_b = (local(forms_b * forms_b) - mu_b**2).clamp_min(0.0)
    cov = local(forms_a * forms_b) - mu_a * mu_b
    c3 = SSIM_C2 / 2.0
    structure = ((cov + c3) / (torch.sqrt(var_a * var_b) + c3)).clamp(-1.0, 1.0)
    out = ((structure * weight).sum((1, 2, 3)) / weight.sum((1, 2, 3))).to(ab.dtype)
    return out if image.ndim == 4 else out[0]


# ----------------------------------------------------------------------------------------------------
# Cross-view consistency: exact reprojection with rendered depth


def masked_rmse(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float | None:  # [H, W, 3] x2, [H, W]
    """sqrt(sum_{p in mask} |a(p) - b(p)|^2 / (3 |mask|)), or None when the mask is empty."""
    count = int(mask.sum())
    if count == 0:
        return None
    diff = (a.to(torch.float64) - b.to(torch.float64))[mask]
    return float(torch.sqrt((diff**2).sum() / (3 * count)))


@dataclass
class PairConsistency:
    source: int
    target: int
    rmse: float | None  # None: no valid pixel
    coverage: float  # fraction of the target's pixels that are valid


@dataclass
class ConsistencyResult:
    gap: int
    rmse: float | None  # mean over the pairs with valid pixels; None when there are none
    coverage: float  # mean coverage over all pairs (0 when there are no pairs)
    pairs: list[PairConsistency]

    def as_dict(self) -> dict:
        return {
            "gap": self.gap,
            "rmse": self.rmse,
            "coverage": self.coverage,
            "pairs": [vars(p).copy() for p in self.pairs],
        }


def consistency_rmse(
    renders,  # N x [H, W, 3]
    depths,  # N x [H, W]
    alphas,  # N x [H, W] (or None: no alpha test)
    cameras: list[Camera],
    gap: int,
    depth_tolerance: float = DEPTH_TOLERANCE,
    alpha_threshold: float = ALPHA_THRESHOLD,
) -> ConsistencyResult:
    """Cross-view drift along an ordered camera path: warp view i into view i + gap, masked RMSE.

    RMSE_gap = mean over pairs (i, i + gap), i = 0 .. N - gap - 1, of the :func:`masked_rmse` between
    :func:`warp_to` (view i -> view i + gap) and view i + gap, over the valid mask. Short-term
    consistency uses gap 1, long-term gap N // 2 (the paper's protocol with an exact warp for RAFT
    flow). Pairs without valid pixels are left out of the mean; with none at all the RMSE is None.

    >>> import numpy as np
    >>> cams = [Camera(8, 6, 10.0, 10.0, 4.0, 3.0, np.eye(4))] * 3
    >>> rgb, depth = torch.rand(6, 8, 3), torch.full((6, 8), 2.0)
    >>> result = consistency_rmse([rgb] * 3, [depth] * 3, None, cams, gap=1)
    >>> result.rmse, result.coverage, len(result.pairs)
    (0.0, 1.0, 2)
    """
    n = len(cameras)
    if len(renders) != n or len(depths) != n or (alphas is not None and len(alphas) != n):
        raise ValueError(f"consistency_rmse: {n} cameras but {len(renders)} renders and {len(depths)} depths")
    if isinstance(gap, bool) or not isinstance(gap, int) or gap < 1:
        raise ValueError(f"consistency_rmse: gap must be a positive integer, got {gap!r}")
    pairs = []
    for i in range(n - gap):
        j = i + gap
        warped, valid = warp_to(
            renders[i],
            depths[i],
            cameras[i],
            cameras[j],
            depths[j],
            None if alphas is None else alphas[i],
            None if alphas is None else alphas[j],
            depth_tolerance,
            alpha_threshold,
        )
        pairs.append(PairConsistency(i, j, masked_rmse(warped, renders[j], valid), float(valid.float().mean())))
    values = [p.rmse for p in pairs if p.rmse is not None]
    rmse = sum(values) / len(values) if values else None
    coverage = sum(p.coverage for p in pairs) / len(pairs) if pairs else 0.0
    return ConsistencyResult(gap, rmse, coverage, pairs)


# ----------------------------------------------------------------------------------------------------
# Efficiency


@dataclass
class StylizeLogSummary:
    optimisation_seconds: float | None  # cumulative "seconds" at the end (summed over resumed runs)
    peaks: dict[str, float]  # the largest value of each numeric "peak_*" key (peak_rss_mb, ...)
    stages: list  # distinct "stage" values in order of appearance
    records: int  # lines read
    skipped: int  # lines that were not a JSON object (e.g. a line cut short by a killed run)

    def as_dict(self) -> dict:
        return {
            "optimisation_seconds": self.optimisation_seconds,
            **self.peaks,
            "stages": self.stages,
            "records": self.records,
            "skipped_lines": self.skipped,
        }


def _finite_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def read_stylize_log(path: str | os.PathLike) -> StylizeLogSummary:
    """Total optimisation time and peak memory from a stylize log (JSON lines).

    Each line is a dict written by the stylizer, with "stage", "seconds" (cumulative wall time) and
    "peak_rss_mb" among its keys. Missing keys and non-numeric values are ignored; unreadable lines
    are counted in ``skipped``. Time = the last "seconds" of each run, summed: a resumed run restarts
    its clock, which shows as "seconds" going down. Each "peak_*" key = its max.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(with_path(path, "stylize log not found")) from None
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(with_path(path, f"cannot read the stylize log ({error.__class__.__name__})")) from None
    finished, current, peaks, stages, records, skipped = 0.0, None, {}, [], 0, 0
    for line in text.splitlines():
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            record = None
        if not isinstance(record, dict):
            skipped += 1
            continue
        records += 1
        if _finite_number(record.get("seconds")):
            value = float(record["seconds"])
            if current is not None and value < current:  # a resumed run: its clock started again
                finished += current
            current = value
        for key, value in record.items():
            if key.startswith("peak_") and _finite_number(value):
                peaks[key] = max(peaks.get(key, float("-inf")), float(value))
        stage = record.get("stage")
        if isinstance(stage, str | int) and not isinstance(stage, bool) and stage not in stages:
            stages.append(stage)
    seconds = None if current is None else finished + current
    return StylizeLogSummary(seconds, peaks, stages, records, skipped)


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter of this process (Linux); False where that is not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


@dataclass
class RenderBenchmark:
    fps: float
    frames: int
    seconds: float
    peak_rss_mb: float  # process peak during the benchmark (whole-process peak where no reset exists)
    peak_cuda_mb: float | None  # torch's peak allocation on CUDA; None on the CPU
    rss_reset: bool  # whether peak_rss_mb covers only the benchmark

    def as_dict(self) -> dict:
        return vars(self).copy()


def measure_render(scene, cameras: list[Camera], settings=None, repeats: int = 2, device="cpu") -> RenderBenchmark:
    """Render FPS and peak memory of ``scene`` with the project's rasterizer.

    Renders every camera ``repeats`` times after one warm-up frame; FPS = frames / wall seconds
    (synchronised on CUDA). Memory: peak RSS of the process during the loop (Linux resets the
    counter first) and, on CUDA, torch's peak allocation.
    """
    from ..raster import RasterSettings, render_scene

    if repeats < 1 or not cameras:
        raise ValueError(f"measure_render needs cameras and repeats >= 1, got {len(cameras)} cameras, {repeats}")
    settings = settings or RasterSettings()
    cuda = torch.device(device).type == "cuda"
    render_scene(scene, cameras[0], settings, device=device)
    if cuda:
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
    reset = _reset_peak_rss()
    frames = 0
    start = time.perf_counter()
    for _ in range(repeats):
        for camera in cameras:
            render_scene(scene, camera, settings, device=device)
            frames += 1
    if cuda:
        torch.cuda.synchronize(device)
    seconds = max(time.perf_counter() - start, 1e-9)
    peak_cuda = torch.cuda.max_memory_allocated(device) / 2**20 if cuda else None
    return RenderBenchmark(frames / seconds, frames, seconds, peak_rss_mb(), peak_cuda, reset)
