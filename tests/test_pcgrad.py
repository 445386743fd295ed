"""Colour-gradient projection across views (Eqs. 17-20)."""

from __future__ import annotations

import pytest
import torch

from dresg_addon.method.pcgrad import pcgrad_fuse, pcgrad_fuse_reference, pcgrad_weights
from dresg_addon.util.errors import NumericalError


def _conflicting(num_views: int, n: int = 40, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    """[V, n, 3] gradients sharing a component but with strong view-specific opposing parts."""
    gen = torch.Generator().manual_seed(seed)
    shared = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    grads = 0.3 * shared + torch.randn(num_views, n, 3, generator=gen, dtype=torch.float64)
    return grads.to(dtype)


def test_two_vector_example_by_hand():
    # g1 = (1, 0), g2 = (-1, 1): g1.g2 = -1 < 0.
    # g1~ = g1 - (-1 / 2) g2 = (0.5, 0.5); g2~ = g2 - (-1 / 1) g1 = (0, 1); mean = (0.25, 0.75).
    grads = torch.tensor([[1.0, 0.0], [-1.0, 1.0]], dtype=torch.float64)
    fused = pcgrad_fuse(grads, eps=0.0)
    torch.testing.assert_close(fused.gradient, torch.tensor([0.25, 0.75], dtype=torch.float64))
    torch.testing.assert_close(fused.weights, torch.tensor([1.0, 0.75], dtype=torch.float64))
    assert fused.conflicts == 2
    torch.testing.assert_close(pcgrad_fuse_reference(grads, eps=0.0), fused.gradient)
    # The fused step conflicts with neither view (the PCGrad guarantee for two tasks).
    assert float(fused.gradient @ grads[0]) > 0 and float(fused.gradient @ grads[1]) > 0


def test_gram_weights_reproduce_the_projection_rule():
    grads = torch.tensor([[1.0, 0.0], [-1.0, 1.0]], dtype=torch.float64)
    weights, conflicts = pcgrad_weights(grads @ grads.T, eps=0.0)
    torch.testing.assert_close(weights, torch.tensor([1.0, 0.75], dtype=torch.float64))
    assert conflicts == 2


def test_matches_the_literal_loop_on_many_views():
    for seed, num_views in ((0, 3), (1, 5), (2, 8)):
        grads = _conflicting(num_views, seed=seed)
        fused = pcgrad_fuse(grads)
        assert fused.conflicts > 0
        torch.testing.assert_close(fused.gradient, pcgrad_fuse_reference(grads), rtol=1e-10, atol=1e-12)
        assert fused.gradient.shape == (40, 3)
        # Chunked dot products give the same result.
        torch.testing.assert_close(pcgrad_fuse(grads, chunk=7).gradient, fused.gradient, rtol=1e-12, atol=1e-14)


def test_float32_input_keeps_its_dtype_and_matches_float64():
    grads = _conflicting(4, seed=3, dtype=torch.float32)
    fused = pcgrad_fuse(grads)
    assert fused.gradient.dtype == torch.float32
    torch.testing.assert_close(fused.gradient, pcgrad_fuse(grads.double()).gradient.float(), rtol=1e-5, atol=1e-6)


def test_no_conflict_is_a_plain_mean():
    g = torch.randn(10, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    grads = torch.stack([g, 2.0 * g, 0.5 * g])  # parallel
    fused = pcgrad_fuse(grads)
    assert fused.conflicts == 0
    torch.testing.assert_close(fused.gradient, grads.mean(0))


def test_antiparallel_gradients_cancel():
    g = torch.randn(10, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    for factor in (1.0, 3.0, 1e-3):
        fused = pcgrad_fuse(torch.stack([g, -factor * g]))
        assert fused.conflicts == 2
        assert torch.isfinite(fused.gradient).all()
        # Each view loses the component along the other: nothing is left.
        assert fused.gradient.abs().max() < 1e-9 * g.abs().max()


def test_conflicting_component_is_removed_for_two_views():
    for seed in range(6):
        grads = _conflicting(2, seed=seed)
        if float((grads[0] * grads[1]).sum()) >= 0:
            grads[1] = -grads[1]
        fused = pcgrad_fuse(grads).gradient
        # With two views the fused step agrees with both, although they disagree with each other.
        assert float((fused * grads[0]).sum()) >= -1e-12
        assert float((fused * grads[1]).sum()) >= -1e-12
        # And equals the mean of g_u - (g_u.g_v / |g_v|^2) g_v, computed here directly.
        g0, g1 = grads[0].flatten(), grads[1].flatten()
        p0 = g0 - (g0 @ g1) / (g1 @ g1) * g1
        p1 = g1 - (g1 @ g0) / (g0 @ g0) * g0
        torch.testing.assert_close(fused.flatten(), (p0 + p1) / 2, rtol=1e-9, atol=1e-12)


def test_zero_and_single_view():
    zeros = torch.zeros(4, 6, 3)
    fused = pcgrad_fuse(zeros)
    assert torch.equal(fused.gradient, torch.zeros(6, 3)) and fused.conflicts == 0
    # One zero view among others: never a conflict (dot = 0), no 0/0.
    grads = _conflicting(3, seed=6)
    grads[1] = 0.0
    fused = pcgrad_fuse(grads)
    assert torch.isfinite(fused.gradient).all()
    torch.testing.assert_close(fused.gradient, pcgrad_fuse_reference(grads), rtol=1e-10, atol=1e-12)
    single = torch.randn(1, 5, 3)
    out = pcgrad_fuse(single)
    assert torch.equal(out.gradient, single[0]) and out.conflicts == 0
    assert out.gradient.data_ptr() != single.data_ptr()


@pytest.mark.parametrize("scale", [1e-30, 1e-20, 1e20, 1e30])
def test_extreme_magnitudes_are_scale_invariant(scale):
    grads = _conflicting(4, seed=7, dtype=torch.float32)
    reference = pcgrad_fuse(grads)
    fused = pcgrad_fuse(grads * scale)
    assert torch.isfinite(fused.gradient).all()
    assert fused.conflicts == reference.conflicts
    torch.testing.assert_close(fused.gradient / scale, reference.gradient, rtol=1e-4, atol=1e-5)


def test_deterministic_and_order_dependent():
    grads = _conflicting(5, seed=8)
    a = pcgrad_fuse(grads).gradient
    b = pcgrad_fuse(grads.clone()).gradient
    assert torch.equal(a, b)
    # The order is part of the method: a permutation is processed in that order (reference agrees).
    perm = torch.tensor([4, 2, 0, 3, 1])
    torch.testing.assert_close(pcgrad_fuse(grads[perm]).gradient, pcgrad_fuse_reference(grads[perm]))


def test_rejects_bad_input():
    bad = torch.zeros(2, 3)
    bad[0, 1] = float("inf")
    with pytest.raises(NumericalError):
        pcgrad_fuse(bad)
    with pytest.raises(ValueError, match="V >= 1"):
        pcgrad_fuse(torch.zeros(0, 3))
