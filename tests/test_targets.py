"""Render-relative residual targets (Eqs. 10 and 12) and the image-space ablation."""

from __future__ import annotations

import pytest
import torch

from dresg_addon.method.targets import (
    LOGIT_EPS,
    image_residual_target,
    logit,
    logit_residual_target,
    proposal_residual,
    residual_target,
)
from dresg_addon.util.errors import ConfigError, NumericalError

EDGES = torch.tensor([0.0, 1e-6, LOGIT_EPS, 0.25, 0.5, 0.75, 1.0 - LOGIT_EPS, 1.0 - 1e-6, 1.0])


def _grid():
    """Every (render, proposal) pair of edge and interior values, as [3, H, W] images."""
    render, proposal = torch.meshgrid(EDGES, EDGES, indexing="ij")
    return render.expand(3, -1, -1).clone(), proposal.expand(3, -1, -1).clone()


def test_residual_is_proposal_minus_render():
    render, proposal = _grid()
    residual = proposal_residual(proposal, render)
    assert torch.equal(residual, proposal - render)
    assert not residual.requires_grad
    with pytest.raises(ValueError, match="shape"):
        proposal_residual(proposal, render[:, :2])


def test_logit_matches_formula_and_is_clamped():
    x = torch.tensor([0.0, 0.2, 0.5, 0.9, 1.0], dtype=torch.float64)
    odds = [LOGIT_EPS / (1 - LOGIT_EPS), 0.25, 1.0, 9.0, (1 - LOGIT_EPS) / LOGIT_EPS]
    torch.testing.assert_close(logit(x), torch.log(torch.tensor(odds, dtype=torch.float64)))
    assert logit(torch.tensor(0.0)) == pytest.approx(-9.21024, abs=1e-4)
    assert logit(torch.tensor(1.0)) == pytest.approx(9.21024, abs=1e-3)  # float32 1 - eps is inexact


def test_gamma_one_gives_the_clamped_proposal_everywhere():
    render, proposal = _grid()
    target = logit_residual_target(render, proposal - render, 1.0)
    torch.testing.assert_close(target, proposal.clamp(LOGIT_EPS, 1 - LOGIT_EPS), atol=2e-7, rtol=0)


def test_targets_are_finite_bounded_and_monotone_in_gamma():
    render, proposal = _grid()
    residual = proposal - render
    clamped_render = render.clamp(LOGIT_EPS, 1 - LOGIT_EPS)
    previous = None
    for gamma in (0.0, 0.5, 1.0, 1.5, 2.0, 4.0, 1e6):
        target = logit_residual_target(render, residual, gamma)
        assert torch.isfinite(target).all()
        assert target.min() >= 0.0 and target.max() <= 1.0
        if gamma == 0.0:
            torch.testing.assert_close(target, clamped_render, atol=2e-7, rtol=0)
        if previous is not None:
            # Moving further toward the proposal: never back across the render, never backwards.
            step = (target - previous) * torch.sign(residual)
            assert (step >= -1e-7).all()
        previous = target
    # Amplification pushes beyond the proposal, in logit space: render 0.25, proposal 0.5, gamma 2.
    r = torch.full((3, 1, 1), 0.25)
    t = logit_residual_target(r, torch.full_like(r, 0.25), 2.0)
    assert t[0, 0, 0].item() == pytest.approx(0.75, abs=1e-6)  # logit 0.25 = -ln 3, 2 steps of +ln 3 -> ln 3


def test_per_view_gamma_broadcasts_and_float64_is_kept():
    render = torch.rand(2, 3, 4, 5, dtype=torch.float64)
    residual = torch.rand_like(render) - render
    gamma = torch.tensor([1.0, 2.0], dtype=torch.float64).view(2, 1, 1, 1)
    target = logit_residual_target(render, residual, gamma)
    assert target.dtype == torch.float64
    torch.testing.assert_close(target[0], logit_residual_target(render[0], residual[0], 1.0))
    torch.testing.assert_close(target[1], logit_residual_target(render[1], residual[1], 2.0))


def test_targets_are_detached():
    render = torch.rand(3, 4, 4, requires_grad=True)
    residual = torch.rand(3, 4, 4) - 0.5
    assert not logit_residual_target(render, residual, 1.5).requires_grad
    assert not image_residual_target(render, residual, 1.5).requires_grad


def test_image_space_ablation():
    render, proposal = _grid()
    residual = proposal - render
    torch.testing.assert_close(image_residual_target(render, residual, 1.0), proposal)
    target = image_residual_target(render, residual, 2.0)
    torch.testing.assert_close(target, (2 * proposal - render).clamp(0, 1))
    assert target.min() == 0.0 and target.max() == 1.0  # saturates, unlike the logit target
    assert torch.equal(residual_target(render, residual, 2.0, space="image"), target)
    assert torch.equal(residual_target(render, residual, 2.0), logit_residual_target(render, residual, 2.0))
    with pytest.raises(ConfigError):
        residual_target(render, residual, 2.0, space="lab")


def test_non_finite_inputs_are_refused():
    render = torch.rand(3, 2, 2)
    residual = torch.zeros(3, 2, 2)
    residual[0, 0, 0] = float("nan")
    with pytest.raises(NumericalError):
        logit_residual_target(render, residual, 1.0)
    with pytest.raises(NumericalError):
        image_residual_target(render, residual, 1.0)
