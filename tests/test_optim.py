"""Fit optimiser: Adam groups, huge gradients, geometry offset bounds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dresg_addon.method.optim import (
    FitOptimizerSettings,
    GeometryBounds,
    check_finite_gradients,
    make_fit_optimizer,
    project_geometry_offsets_,
    scene_extent,
)
from dresg_addon.util.errors import ConfigError, NumericalError


def test_adam_with_huge_gradients_moves_by_about_the_learning_rate():
    colors = torch.zeros(1000, 3, requires_grad=True)
    offsets = torch.zeros(1000, 3, requires_grad=True)
    optimizer = make_fit_optimizer([colors], [offsets])
    assert [g["lr"] for g in optimizer.param_groups] == [0.05, 1e-3]
    signs = torch.where(torch.arange(3000).reshape(1000, 3) % 2 == 0, 1.0, -1.0)
    for _ in range(5):
        before = colors.detach().clone()
        optimizer.zero_grad()
        colors.grad = 1e6 * signs
        offsets.grad = -1e6 * torch.ones(1000, 3)
        optimizer.step()
        assert torch.isfinite(colors).all() and torch.isfinite(offsets).all()
        # A constant gradient gives m / sqrt(v) = 1: each step moves exactly lr against the gradient.
        torch.testing.assert_close(colors.detach() - before, -0.05 * signs, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(offsets.detach(), torch.full((1000, 3), 5 * 1e-3), rtol=1e-4, atol=1e-7)


def test_geometry_offsets_are_projected_onto_their_boxes():
    means = torch.tensor([[0.2, -0.2, 0.01]])
    log_scales = torch.tensor([[0.06, -0.04, -1.0]])
    quats = torch.tensor([[0.5, -0.01, 0.03, -0.03]])
    project_geometry_offsets_(means, log_scales, quats)
    assert means[0].tolist() == pytest.approx([0.05, -0.05, 0.01])
    assert log_scales[0].tolist() == pytest.approx([0.05, -0.04, -0.05])
    assert quats[0].tolist() == pytest.approx([0.02, -0.01, 0.02, -0.02])
    # Works on leaf parameters that require grad, and with a missing group.
    param = torch.nn.Parameter(torch.full((4, 3), 1.0))
    project_geometry_offsets_(param, None, None, GeometryBounds(means=0.1))
    assert torch.equal(param.detach(), torch.full((4, 3), 0.1))


def test_non_finite_gradients_are_refused():
    p = torch.zeros(3, requires_grad=True)
    p.grad = torch.tensor([0.0, float("nan"), 1.0])
    with pytest.raises(NumericalError, match="colour"):
        check_finite_gradients([p], "colour")
    p.grad = torch.ones(3)
    check_finite_gradients([p, torch.zeros(2, requires_grad=True)])


def test_settings_are_checked():
    with pytest.raises(ConfigError):
        FitOptimizerSettings(color_lr=0.0)
    with pytest.raises(ConfigError):
        GeometryBounds(quats=-0.1)
    frozen_geometry = make_fit_optimizer(
        [torch.zeros(2, requires_grad=True)],
        [torch.zeros(2, requires_grad=True)],
        FitOptimizerSettings(geometry_lr=0.0),
    )
    assert len(frozen_geometry.param_groups) == 1


def test_scene_extent_is_a_robust_radius_that_scales_with_the_scene():
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(1000, 3))
    means = 2.0 * directions / np.linalg.norm(directions, axis=1, keepdims=True)  # a sphere of radius 2
    assert scene_extent(means) == pytest.approx(2.0, rel=0.1)
    # Exactly proportional to a scale, unchanged by a translation, about the same after a rotation.
    for factor in (1e-4, 1e4):
        assert scene_extent(factor * means) == pytest.approx(factor * scene_extent(means), rel=1e-12)
    assert scene_extent(means + [100.0, -5.0, 3.0]) == pytest.approx(scene_extent(means), rel=1e-9)
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    assert scene_extent(means @ rotation.T) == pytest.approx(scene_extent(means), rel=0.05)
    # The farthest few percent (floaters, far background) do not count.
    floaters = np.concatenate([means, rng.normal(1e4, 1.0, (50, 3))])
    assert scene_extent(floaters) == pytest.approx(scene_extent(means), rel=0.05)
    # One point: the splat size; nothing to go on: 1.
    assert scene_extent(np.zeros((1, 3)), np.log([[0.1, 3.0, 0.2]])) == pytest.approx(3.0)
    assert scene_extent(np.zeros((0, 3))) == 1.0


def test_the_mean_lr_and_bound_scale_with_the_extent():
    settings = FitOptimizerSettings(extent=1e-4)
    assert settings.mean_lr == pytest.approx(1e-7)
    assert settings.scene_bounds == GeometryBounds(means=0.05 * 1e-4)
    assert FitOptimizerSettings().scene_bounds == GeometryBounds()  # extent 1: the paper's numbers
    colors, means, rest = (torch.zeros(4, 3, requires_grad=True) for _ in range(3))
    optimizer = make_fit_optimizer([colors], [rest], settings, mean_params=[means])
    assert [(g["name"], g["lr"]) for g in optimizer.param_groups] == [
        ("color", 0.05),
        ("means", pytest.approx(1e-7)),
        ("geometry", 1e-3),
    ]
    with pytest.raises(ConfigError):
        FitOptimizerSettings(extent=0.0)


@pytest.mark.parametrize("factor", [1e-4, 1e4])
def test_mean_offsets_of_a_scaled_scene_are_the_scaled_offsets(factor):
    """A scene scaled by s: its mean gradients are divided by s, its extent multiplied by s; Adam with the
    scaled lr and bound then gives s times the offsets of the unscaled scene."""
    gradients = torch.randn(80, 8, 3, generator=torch.Generator().manual_seed(0))
    gradients[:, :, 0] = gradients[:, :, 0].abs() + 1.0  # these offsets run into the bound

    def fit(extent: float, scale: float) -> torch.Tensor:
        settings = FitOptimizerSettings(extent=extent)
        offsets = torch.zeros(8, 3, dtype=torch.float64, requires_grad=True)
        optimizer = make_fit_optimizer([torch.zeros(1, requires_grad=True)], [], settings, mean_params=[offsets])
        for g in gradients:
            offsets.grad = (g / scale).double()
            optimizer.step()
            project_geometry_offsets_(offsets, None, None, settings.scene_bounds)
        return offsets.detach()

    base = fit(1.3, 1.0)
    assert base.abs().max() == pytest.approx(0.05 * 1.3)  # at the bound
    torch.testing.assert_close(fit(1.3 * factor, factor) / factor, base, rtol=0, atol=1e-6 * 0.05 * 1.3)
