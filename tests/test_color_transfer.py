"""Covariance (affine) colour transfer of renders toward the style."""

from __future__ import annotations

import pytest
import torch

from dresg_addon.method.color_transfer import (
    HISTOGRAM_QUANTILES,
    StyleQuantiles,
    color_moments,
    color_transfer,
    covariance_color_transform,
    coverage_weight,
    fit_color_map,
    match_color_histograms,
    symmetric_sqrt,
    transfer_scene_colors,
)
from dresg_addon.util.errors import CameraError, ImageError, NumericalError


def _correlated_images(batch, h, w, mix, mean, seed):
    """[batch, 3, h, w] float64 images with colour covariance mix mix^T around ``mean``."""
    gen = torch.Generator().manual_seed(seed)
    noise = torch.randn(batch, h, w, 3, generator=gen, dtype=torch.float64)
    pixels = noise @ torch.tensor(mix, dtype=torch.float64).T + torch.tensor(mean, dtype=torch.float64)
    return pixels.permute(0, 3, 1, 2).contiguous()


def _moments(images, mask=None):
    pixels = images.movedim(-3, -1).reshape(-1, 3)
    if mask is not None:
        pixels = pixels[mask.reshape(-1)]
    return color_moments(pixels)


RENDER_MIX = [[0.10, 0.02, 0.00], [0.03, 0.08, 0.01], [0.00, 0.02, 0.05]]
STYLE_MIX = [[0.05, 0.00, 0.04], [0.00, 0.12, 0.00], [0.02, 0.03, 0.06]]


def test_symmetric_sqrt():
    a = torch.tensor([[2.0, 0.5, 0.1], [0.5, 1.0, 0.2], [0.1, 0.2, 0.5]], dtype=torch.float64)
    root = symmetric_sqrt(a)
    torch.testing.assert_close(root @ root, a)
    torch.testing.assert_close(root, root.T)
    inv = symmetric_sqrt(a, inverse=True)
    torch.testing.assert_close(inv @ a @ inv, torch.eye(3, dtype=torch.float64))
    # A singular matrix: the floor keeps the inverse root finite and bounded by floor^-1/2.
    singular = torch.zeros(3, 3, dtype=torch.float64)
    singular[0, 0] = 1.0
    inv = symmetric_sqrt(singular, floor=1e-6, inverse=True)
    torch.testing.assert_close(torch.diagonal(inv), torch.tensor([1.0, 1e3, 1e3], dtype=torch.float64))


def test_renders_get_the_style_mean_and_covariance():
    renders = _correlated_images(3, 20, 24, RENDER_MIX, [0.4, 0.5, 0.3], seed=0)
    style = _correlated_images(1, 30, 17, STYLE_MIX, [0.6, 0.3, 0.5], seed=1)[0]
    out, transform = color_transfer(renders, style, clamp=False)
    mu_out, cov_out = _moments(out)
    mu_s, cov_s = _moments(style)
    torch.testing.assert_close(mu_out, mu_s, atol=1e-10, rtol=0)
    torch.testing.assert_close(cov_out, cov_s, atol=1e-10, rtol=1e-8)
    # One map for all views (views stay consistent), also usable on Gaussian colours [N, 3].
    torch.testing.assert_close(out[2], transform.apply_to_images(renders[2]))
    colors = renders[0].movedim(0, -1).reshape(-1, 3)
    torch.testing.assert_close(transform.apply_to_colors(colors), out[0].movedim(0, -1).reshape(-1, 3))
    clamped, _ = color_transfer(renders, style)
    assert clamped.min() >= 0.0 and clamped.max() <= 1.0
    assert torch.equal(clamped, out.clamp(0, 1))


def test_identity_when_the_statistics_already_match():
    renders = _correlated_images(2, 16, 16, RENDER_MIX, [0.5, 0.4, 0.6], seed=2)
    style = renders.permute(1, 0, 2, 3).reshape(3, 32, 16)  # the same pixels, rearranged
    out, transform = color_transfer(renders, style, clamp=False)
    torch.testing.assert_close(transform.matrix, torch.eye(3, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(transform.offset, torch.zeros(3, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(out, renders, atol=1e-9, rtol=0)


def test_flat_style_and_flat_render_stay_finite():
    renders = _correlated_images(2, 10, 10, RENDER_MIX, [0.5, 0.5, 0.5], seed=3)
    flat_style = torch.zeros(3, 8, 8) + torch.tensor([0.2, 0.7, 0.1]).view(3, 1, 1)
    out, _ = color_transfer(renders, flat_style.double(), clamp=False)
    # A flat style has zero covariance: every pixel becomes its colour.
    torch.testing.assert_close(out, flat_style.double()[:, :1, :1].expand_as(out).contiguous(), atol=1e-9, rtol=0)
    flat_render = torch.full((2, 3, 6, 6), 0.3)
    style = _correlated_images(1, 12, 12, STYLE_MIX, [0.6, 0.3, 0.5], seed=4)[0].float()
    out, transform = color_transfer(flat_render, style, clamp=False)
    assert torch.isfinite(out).all() and torch.isfinite(transform.matrix).all()
    torch.testing.assert_close(out, style.mean((1, 2)).view(1, 3, 1, 1).expand_as(out), atol=1e-5, rtol=0)
    # A grey render (rank-1 colour covariance) keeps its mean match and stays finite.
    grey = _correlated_images(1, 10, 10, RENDER_MIX, [0.5, 0.5, 0.5], seed=5)[:, :1].expand(2, 3, 10, 10)
    out, _ = color_transfer(grey, style.double(), clamp=False)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(_moments(out)[0], _moments(style.double())[0], atol=1e-8, rtol=0)


def test_masks_restrict_the_statistics():
    renders = _correlated_images(2, 12, 12, RENDER_MIX, [0.4, 0.5, 0.3], seed=6)
    alpha = torch.zeros(2, 1, 12, 12, dtype=torch.float64)
    alpha[:, :, 2:10, 3:11] = 0.9
    renders = torch.where(alpha > 0.5, renders, torch.tensor(5.0, dtype=torch.float64))  # wild background
    style = _correlated_images(1, 14, 14, STYLE_MIX, [0.6, 0.3, 0.5], seed=7)[0]
    style_alpha = torch.ones(14, 14, dtype=torch.float64)
    style_alpha[:3] = 0.0
    style_wild = style.clone()
    style_wild[:, :3] = -4.0
    out, _ = color_transfer(renders, style_wild, render_mask=alpha, style_mask=style_alpha, clamp=False)
    keep = (alpha > 0.5).squeeze(1)
    mu_out, cov_out = _moments(out, keep)
    mu_s, cov_s = _moments(style[:, 3:])
    torch.testing.assert_close(mu_out, mu_s, atol=1e-10, rtol=0)
    torch.testing.assert_close(cov_out, cov_s, atol=1e-10, rtol=1e-8)
    # Boolean masks without a channel axis mean the same.
    out_bool, _ = color_transfer(renders, style_wild, render_mask=keep, style_mask=style_alpha > 0.5, clamp=False)
    torch.testing.assert_close(out_bool, out)


def test_bad_inputs():
    renders = torch.rand(2, 3, 4, 4)
    style = torch.rand(3, 5, 5)
    with pytest.raises(CameraError, match="no render pixel"):
        covariance_color_transform(renders, style, render_mask=torch.zeros(2, 4, 4))
    with pytest.raises(ImageError, match="mask"):
        covariance_color_transform(renders, style, style_mask=torch.zeros(5, 5))
    with pytest.raises(ValueError, match="mask has shape"):
        covariance_color_transform(renders, style, render_mask=torch.ones(2, 4, 5))
    with pytest.raises(ValueError, match=r"\[3, H, W\] or \[V, 3, H, W\]"):
        covariance_color_transform(torch.rand(2, 4, 4, 4), style)
    bad = style.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(NumericalError):
        covariance_color_transform(renders, bad)


def _style_axes(style_pixels):
    mu_s, cov_s = color_moments(style_pixels)
    return mu_s, torch.linalg.eigh(cov_s).eigenvectors


def test_match_color_histograms_takes_the_style_marginals_along_its_axes():
    pixels = _correlated_images(1, 20, 25, RENDER_MIX, [0.4, 0.5, 0.3], seed=8)[0].reshape(3, -1).T
    style = _correlated_images(1, 25, 20, STYLE_MIX, [0.6, 0.3, 0.5], seed=9)[0].reshape(3, -1).T
    out = match_color_histograms(pixels, style)
    assert out.shape == pixels.shape and out.dtype == pixels.dtype
    mu_s, axes = _style_axes(style)
    projected, target = (out - mu_s) @ axes, (style - mu_s) @ axes
    # Equal counts: along each axis the sorted values are exactly the style's.
    torch.testing.assert_close(projected.sort(0).values, target.sort(0).values, atol=1e-12, rtol=0)
    # The order of the pixels along each axis is kept (a monotone map per axis).
    assert torch.equal(projected.argsort(0), ((pixels - mu_s) @ axes).argsort(0))
    torch.testing.assert_close(out.mean(0), style.mean(0), atol=1e-12, rtol=0)


def test_match_color_histograms_to_sorted_quantiles_is_the_same_match():
    pixels = _correlated_images(1, 10, 30, RENDER_MIX, [0.4, 0.5, 0.3], seed=10)[0].reshape(3, -1).T.float()
    style = _correlated_images(1, 35, 20, STYLE_MIX, [0.6, 0.3, 0.5], seed=11)[0].reshape(3, -1).T
    quantiles = StyleQuantiles.of(style)
    assert bool((quantiles.sorted.diff(dim=1) >= 0).all())
    assert torch.equal(match_color_histograms(pixels, quantiles), match_color_histograms(pixels, style))
    with pytest.raises(ImageError):
        StyleQuantiles.of(torch.zeros(0, 3))


def test_match_color_histograms_with_unequal_counts():
    pixels = _correlated_images(1, 10, 30, RENDER_MIX, [0.4, 0.5, 0.3], seed=10)[0].reshape(3, -1).T
    style = _correlated_images(1, 35, 20, STYLE_MIX, [0.6, 0.3, 0.5], seed=11)[0].reshape(3, -1).T
    out = match_color_histograms(pixels.float(), style)
    assert out.dtype == torch.float32 and bool(torch.isfinite(out).all())
    mu_s, axes = _style_axes(style)
    projected, target = (out.double() - mu_s) @ axes, (style - mu_s) @ axes
    assert bool((projected >= target.min(0).values - 1e-5).all()) and bool(
        (projected <= target.max(0).values + 1e-5).all()
    )
    torch.testing.assert_close(out.double().mean(0), style.mean(0), atol=0.01, rtol=0)


def test_match_color_histograms_flat_empty_and_bad_inputs():
    style = _correlated_images(1, 12, 12, STYLE_MIX, [0.6, 0.3, 0.5], seed=12)[0].reshape(3, -1).T
    flat = torch.full((50, 3), 0.4, dtype=torch.float64)
    out = match_color_histograms(flat, style)
    assert out.shape == (50, 3) and bool(torch.isfinite(out).all())
    flat_style = torch.tensor([[0.2, 0.7, 0.1]], dtype=torch.float64).expand(30, 3)
    out = match_color_histograms(style, flat_style)
    torch.testing.assert_close(out, flat_style[:1].expand_as(out), atol=1e-12, rtol=0)
    empty = match_color_histograms(torch.zeros(0, 3), style)
    assert empty.shape == (0, 3)
    for bad_pixels, bad_style in (
        (torch.rand(5, 4), style),
        (torch.rand(5), style),
        (torch.rand(2, 5, 3), style),
        (torch.rand(5, 3), torch.rand(5, 2)),
        (torch.rand(5, 3), torch.rand(3, 4, 4)),
    ):
        with pytest.raises(ValueError):
            match_color_histograms(bad_pixels, bad_style)
    with pytest.raises(ImageError):
        match_color_histograms(torch.rand(5, 3), torch.zeros(0, 3))


def test_coverage_weight_is_a_smoothstep():
    alpha = torch.linspace(-0.5, 1.5, 2001, dtype=torch.float64)
    weight = coverage_weight(alpha)
    assert bool((weight[alpha <= 0.25] == 0).all()) and bool((weight[alpha >= 0.75] == 1).all())
    assert bool((weight.diff() >= 0).all())
    step = float(alpha[1] - alpha[0])
    assert float(weight.diff().max()) <= 3.0 * step * (1 + 1e-9)  # slope at most 1.5 / 0.5: no jump
    torch.testing.assert_close(
        coverage_weight(torch.tensor(0.5, dtype=torch.float64)), torch.tensor(0.5, dtype=torch.float64)
    )
    # Flat at both ends (continuous derivative): a small step in alpha gives a quadratically small change.
    near = coverage_weight(torch.tensor([0.25 + 1e-3, 0.75 - 1e-3], dtype=torch.float64))
    assert float(near[0]) < 1e-4 and float(1 - near[1]) < 1e-4
    image = torch.rand(2, 5, 7)
    assert coverage_weight(image).shape == image.shape


def _views(seed: int = 0) -> list[torch.Tensor]:
    """Two differently sized views of one warm, noisy scene."""
    g = torch.Generator().manual_seed(seed)
    base = torch.tensor([0.7, 0.4, 0.2]).view(3, 1, 1)
    return [(base + 0.15 * torch.randn(3, h, w, generator=g)).clamp(0, 1) for h, w in ((20, 30), (24, 16))]


def _style(seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.tensor([0.1, 0.3, 0.8]).view(3, 1, 1) + 0.2 * torch.randn(3, 18, 22, generator=g)).clamp(0, 1)


@pytest.mark.parametrize("histogram", [False, True])
def test_color_map_is_one_function_of_colour_for_every_view(histogram):
    views, style = _views(), _style()
    color_map = fit_color_map(views, style, histogram=histogram)
    together = color_map.apply_to_images(torch.cat([v.reshape(3, -1, 1) for v in views], 1))
    apart = torch.cat([color_map.apply_to_images(v).reshape(3, -1, 1) for v in views], 1)
    torch.testing.assert_close(together, apart)  # a pixel's new colour depends on its colour alone
    same = torch.full((3, 4, 4), 0.5)
    torch.testing.assert_close(color_map.apply_to_images(same), color_map.apply_to_images(same.clone()))


def test_color_map_takes_the_pooled_views_to_the_style_histogram():
    views, style = _views(), _style()
    color_map = fit_color_map(views, style)
    pooled = torch.cat([color_map.apply_to_images(v).reshape(3, -1) for v in views], 1).T.double()
    reference = style.reshape(3, -1).T.double()
    axes, origin = color_map.axes, color_map.origin
    levels = torch.linspace(0.05, 0.95, 7, dtype=torch.float64)
    for c in range(3):
        ours = torch.quantile((pooled - origin) @ axes[:, c], levels)
        theirs = torch.quantile((reference - origin) @ axes[:, c], levels)
        torch.testing.assert_close(ours, theirs, atol=0.02, rtol=0)
    assert color_map.source.shape == (3, HISTOGRAM_QUANTILES)


def test_color_map_masks_flat_inputs_and_extrapolation():
    views, style = _views(), _style()
    masks = [torch.zeros(v.shape[1:]) for v in views]
    masks[0][:, :10] = 1.0
    masked = fit_color_map(views, style, masks)
    cropped = fit_color_map([views[0][:, :, :10]], style)
    torch.testing.assert_close(masked.source, cropped.source)  # only the covered pixels count
    flat = fit_color_map([torch.full((3, 5, 5), 0.3)], torch.full((3, 4, 4), 0.6))
    out = flat.apply_to_images(torch.rand(3, 6, 6))
    assert bool(torch.isfinite(out).all())
    extreme = masked.apply_to_images(torch.tensor([-5.0, 0.5, 7.0]).view(3, 1, 1))  # beyond every knot
    assert bool(torch.isfinite(extreme).all())
    with pytest.raises(CameraError):
        fit_color_map(views, style, [torch.zeros(v.shape[1:]) for v in views])


def test_transfer_scene_colors_recolours_every_splat_by_one_map():
    import numpy as np

    from dresg_addon.scene.gaussians import SH_C0, GaussianScene

    n = 5
    colors = np.linspace(0.2, 0.8, 3 * n).reshape(n, 3)
    scene = GaussianScene(
        means=np.zeros((n, 3), np.float32),
        log_scales=np.zeros((n, 3), np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        opacity_logits=np.zeros(n, np.float32),
        sh_dc=((colors - 0.5) / SH_C0).astype(np.float32),
        sh_rest=np.ones((n, 3, 3), np.float32),
    )
    views = _views()[:1]
    out = transfer_scene_colors(scene, views[0][None], torch.ones(1, *views[0].shape[1:]), _style())
    transform = covariance_color_transform(views[0], _style())
    expected = transform.apply_to_colors(torch.from_numpy(colors)).clamp(0, 1).numpy()
    np.testing.assert_allclose(0.5 + SH_C0 * out.sh_dc, expected, atol=1e-5)
    assert not out.sh_rest.any() and scene.sh_rest.all()  # view-dependent bands dropped; the input untouched
