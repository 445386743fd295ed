"""Fit optimiser: Adam groups, huge gradients, geometry offset bounds."""

from __future__ import annotations

import pytest
import torch

from dresg_addon.errors import ConfigError, NumericalError
from dresg_addon.optim import (
    FitOptimizerSettings,
    GeometryBounds,
    check_finite_gradients,
    make_fit_optimizer,
    project_geometry_offsets_,
)


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
