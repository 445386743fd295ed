"""The fit loss (Eq. 16) and its image measures."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from dresg_addon.method.losses import (
    SSIM_C1,
    SSIM_C2,
    FitLossWeights,
    fit_loss,
    gaussian_window,
    ssim_map,
)
from dresg_addon.util.errors import ConfigError


def _rand(*shape, seed=0, dtype=torch.float32):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _ssim_map_2d_reference(x, y):
    """3DGS's formulation: one 2D 11x11 window (outer product), conv2d with zero padding 5."""
    g = gaussian_window(11, 1.5, torch.float64)
    window = (g[:, None] @ g[None, :]).expand(x.shape[1], 1, 11, 11).to(x.dtype)
    c = x.shape[1]
    mu_x, mu_y = F.conv2d(x, window, padding=5, groups=c), F.conv2d(y, window, padding=5, groups=c)
    s_xx = F.conv2d(x * x, window, padding=5, groups=c) - mu_x**2
    s_yy = F.conv2d(y * y, window, padding=5, groups=c) - mu_y**2
    s_xy = F.conv2d(x * y, window, padding=5, groups=c) - mu_x * mu_y
    return ((2 * mu_x * mu_y + SSIM_C1) * (2 * s_xy + SSIM_C2)) / (
        (mu_x**2 + mu_y**2 + SSIM_C1) * (s_xx + s_yy + SSIM_C2)
    )


def _tv_reference(x):
    """Anisotropic TV for images at least 2 pixels tall and wide: mean |vertical step| + mean |horizontal step|."""
    return (x[..., 1:, :] - x[..., :-1, :]).abs().mean() + (x[..., 1:] - x[..., :-1]).abs().mean()


def test_gaussian_window():
    g = gaussian_window(11, 1.5, torch.float64)
    assert g.shape == (11,) and float(g.sum()) == pytest.approx(1.0, abs=1e-15)
    assert float(g[5] / g[6]) == pytest.approx(torch.exp(torch.tensor(1 / 4.5, dtype=torch.float64)).item())
    assert torch.equal(g, g.flip(0))


def test_ssim_matches_the_2d_window_formulation():
    x, y = _rand(2, 3, 20, 17, seed=1, dtype=torch.float64), _rand(2, 3, 20, 17, seed=2, dtype=torch.float64)
    torch.testing.assert_close(ssim_map(x, y), _ssim_map_2d_reference(x, y), rtol=1e-10, atol=1e-12)
    assert ssim_map(x[0], y[0]).shape == (3, 20, 17)  # unbatched in, unbatched out
    dssim = (1 - _ssim_map_2d_reference(x[:1], y[:1]).mean()) / 2
    torch.testing.assert_close(fit_loss(x[0], y[0]).dssim, dssim, rtol=1e-10, atol=1e-12)


def test_ssim_of_flat_images_has_the_closed_form():
    a, b = 0.3, 0.7
    x, y = torch.full((1, 3, 32, 32), a, dtype=torch.float64), torch.full((1, 3, 32, 32), b, dtype=torch.float64)
    m = ssim_map(x, y)
    # Away from the zero-padded border the variances vanish: SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    expected = (2 * a * b + SSIM_C1) / (a * a + b * b + SSIM_C1)
    torch.testing.assert_close(m[..., 5:-5, 5:-5], torch.full_like(m[..., 5:-5, 5:-5], expected))
    assert torch.isfinite(m).all()


def test_identical_images():
    for image in (_rand(3, 24, 24), torch.zeros(3, 24, 24), torch.ones(3, 24, 24), torch.full((3, 9, 5), 0.42)):
        terms = fit_loss(image, image.clone())
        assert float(ssim_map(image, image).mean()) == pytest.approx(1.0, abs=1e-5)
        assert float(terms.dssim) == pytest.approx(0.0, abs=1e-5) and float(terms.l1) == 0.0
    flat = torch.full((2, 3, 16, 16), 0.5)
    terms = fit_loss(flat, flat.clone())
    assert float(terms.total) == pytest.approx(0.0, abs=1e-6)
    image = _rand(3, 16, 16, seed=3)
    terms = fit_loss(image, image.clone())
    assert float(terms.l1) == 0.0 and float(terms.dssim) == pytest.approx(0.0, abs=1e-6)
    # TV is a smoothness term on the render alone: the only non-zero part.
    assert float(terms.total) == pytest.approx(0.01 * float(_tv_reference(image)), abs=1e-6)


def test_ssim_gradcheck_float64():
    x = _rand(1, 3, 8, 7, seed=4, dtype=torch.float64).requires_grad_()
    y = _rand(1, 3, 8, 7, seed=5, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: ssim_map(a, b).mean(), (x, y))
    assert torch.autograd.gradcheck(lambda a: fit_loss(a, y.detach()).total, (x,))


def test_flat_and_extreme_images_stay_finite():
    for value_x, value_y in ((0.0, 0.0), (0.0, 1.0), (1.0, 1.0), (1e4, 0.0), (1e4, 1e4 + 1.0)):
        x = torch.full((1, 3, 12, 12), value_x, requires_grad=True)
        y = torch.full((1, 3, 12, 12), value_y)
        loss = fit_loss(x, y).total
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(x.grad).all()
        assert torch.isfinite(ssim_map(x.detach(), y)).all()
    noisy = (torch.rand(1, 3, 12, 12) * 1e4).requires_grad_()
    only_dssim = FitLossWeights(l1=0.0, dssim=1.0, tv=0.0, feature=0.0)
    fit_loss(noisy, torch.zeros_like(noisy), weights=only_dssim).total.backward()
    assert torch.isfinite(noisy.grad).all()


def test_l1_and_total_variation_values():
    x = torch.zeros(3, 4, 5)
    assert float(fit_loss(x, x + 0.25).l1) == pytest.approx(0.25)

    def tv(image):
        return float(fit_loss(image, image).tv)

    ramp = (0.1 * torch.arange(5.0)).expand(3, 4, 5)  # steps of 0.1 along the width, none along the height
    assert tv(ramp) == pytest.approx(0.1)
    checker = (torch.arange(4)[:, None] + torch.arange(4)[None, :]) % 2
    assert tv(checker.float().expand(2, 3, 4, 4)) == pytest.approx(2.0)
    row = torch.rand(3, 1, 7)  # one pixel tall: only horizontal differences
    assert tv(row) == pytest.approx(float((row[..., 1:] - row[..., :-1]).abs().mean()))
    assert tv(torch.rand(3, 1, 1)) == 0.0


def test_feature_distances():
    image = torch.rand(1, 3, 4, 4)

    def feature(render_features, base_features, distance):
        weights = FitLossWeights(feature_distance=distance)
        return fit_loss(image, image, base_features, render_features, weights).feature

    a = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])  # [B=1, C=2, T=2] (channels at dim 1)
    b = torch.tensor([[[0.0, 0.0], [1.0, 1.0]]])
    # Position 0: (1, 0) vs (0, 1) -> orthogonal, 1. Position 1: (0, 1) vs (0, 1) -> 0.
    assert float(feature(a, b, "cosine")) == pytest.approx(0.5)
    assert float(feature(a, -a, "cosine")) == pytest.approx(2.0)
    assert float(feature(a, b, "l1")) == pytest.approx(0.5)
    zero = torch.zeros(1, 4, 3, 3, requires_grad=True)
    loss = feature(zero, torch.rand(1, 4, 3, 3), "cosine")
    loss.backward()
    assert float(loss.detach()) == pytest.approx(1.0) and torch.isfinite(zero.grad).all()
    with pytest.raises(ValueError, match="must match"):
        feature(a, b[:, :1], "l1")


def test_fit_loss_combines_the_weighted_terms():
    render = _rand(2, 3, 16, 12, seed=6).requires_grad_()
    target = _rand(2, 3, 16, 12, seed=7)
    base_features = _rand(2, 8, 4, 3, seed=8)
    render_features = render.mean(1, keepdim=True).expand(2, 8, 16, 12)[:, :, ::4, ::4]
    terms = fit_loss(render, target, base_features, render_features)
    dssim = (1 - _ssim_map_2d_reference(render, target).mean()) / 2
    expected = (
        (render - target).abs().mean()
        + 0.2 * dssim
        + 0.01 * _tv_reference(render)
        + 0.01 * (render_features - base_features).abs().mean()
    )
    torch.testing.assert_close(terms.total, expected)
    assert float(terms.feature.detach()) > 0
    per_image = fit_loss(render, target, base_features, render_features, per_image=True)
    assert per_image.total.shape == (2,)
    torch.testing.assert_close(per_image.total.mean(), terms.total)
    torch.testing.assert_close(
        per_image.total[0], fit_loss(render[:1], target[:1], base_features[:1], render_features[:1]).total
    )
    # Per-view gradients: view 1's loss does not touch view 0's pixels.
    (grad,) = torch.autograd.grad(per_image.total[1], render)
    assert float(grad[0].abs().max()) == 0.0 and float(grad[1].abs().max()) > 0.0
    # No features or a zero weight: the term is skipped.
    assert float(fit_loss(render, target).feature.detach()) == 0.0
    custom = FitLossWeights(l1=0.0, dssim=1.0, tv=0.0, feature=0.0)
    torch.testing.assert_close(fit_loss(render, target, base_features, render_features, custom).total, dssim)
    cosine = FitLossWeights(feature_distance="cosine")
    cos_terms = fit_loss(render, target, base_features, render_features, cosine)
    cosine_distance = 1 - F.cosine_similarity(render_features, base_features, dim=1)
    torch.testing.assert_close(cos_terms.feature, cosine_distance.mean())


def test_bad_inputs():
    with pytest.raises(ValueError, match="different shapes"):
        fit_loss(torch.rand(3, 4, 4), torch.rand(3, 4, 5))
    with pytest.raises(ValueError, match=r"\[C, H, W\] or \[B, C, H, W\]"):
        ssim_map(torch.rand(4, 4), torch.rand(4, 4))
    with pytest.raises(ConfigError):
        FitLossWeights(dssim=-1.0)
    with pytest.raises(ConfigError):
        FitLossWeights(feature_distance="l2")


def test_patch_feature_maps_describe_structure_not_palette():
    from dresg_addon.method.losses import patch_feature_maps

    g = torch.Generator().manual_seed(0)
    ramp = torch.linspace(0, 1, 64)
    image = (0.5 + 0.3 * torch.sin(8 * ramp)[None, None, :] * torch.cos(5 * ramp)[None, :48, None]).expand(3, 48, 64)
    image = (image + 0.05 * torch.rand(3, 48, 64, generator=g))[None] * 0.8
    feats = patch_feature_maps(image)
    assert feats.shape == (1, 96, 48 // 8, 64 // 8)
    shifted = patch_feature_maps(image + torch.tensor([0.1, -0.05, 0.15])[None, :, None, None])
    assert torch.allclose(feats, shifted, atol=1e-4)  # a colour offset leaves structure unchanged
    assert float((patch_feature_maps(image.flip(-1)) - feats).abs().mean()) > 0.1
    batch = torch.cat([image, torch.rand(1, 3, 48, 64, generator=g)]).requires_grad_(True)
    out = patch_feature_maps(batch)
    assert out.shape[0] == 2 and torch.allclose(out[:1], feats, atol=1e-6)
    out.abs().sum().backward()
    assert torch.isfinite(batch.grad).all() and float(batch.grad.abs().sum()) > 0
    with pytest.raises(ValueError, match=r"\[B, 3, H, W\]"):
        patch_feature_maps(torch.zeros(3, 8, 8))
