"""Active-view selection by capped coverage (Eqs. 13-15)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from messages import names

from dresg_addon.method.views import (
    COVERAGE_REACHED,
    GAIN_BELOW_THRESHOLD,
    VIEW_LIMIT_REACHED,
    ViewSelectionSettings,
    capped_coverage,
    select_views,
    select_views_reference,
    target_support,
)
from dresg_addon.util.errors import CameraError, ConfigError, NumericalError


def _random_visibility(num_views: int, num_gaussians: int, seed: int) -> np.ndarray:
    """Views seeing overlapping windows of a ring of Gaussians, with random strengths (many zeros)."""
    rng = np.random.default_rng(seed)
    pos = np.arange(num_gaussians)
    w = np.zeros((num_views, num_gaussians), dtype=np.float32)
    for v, centre in enumerate(rng.uniform(0, num_gaussians, num_views)):
        d = np.abs((pos - centre + num_gaussians / 2) % num_gaussians - num_gaussians / 2)
        strength = rng.uniform(0, 1, num_gaussians) * np.exp(-d / (0.1 * num_gaussians))
        w[v] = np.where(d < 0.2 * num_gaussians, strength, 0.0)
    return w


def test_support_and_coverage_formulas():
    m_star = np.array([1.0, 2e-4, 1e-4])
    np.testing.assert_allclose(target_support(m_star, 1e-4, 0.98), [0.98, 1.96e-4, 1e-4])
    np.testing.assert_allclose(capped_coverage(np.array([0.49, 0.98, 2.0]), np.full(3, 0.98)), [0.5, 1.0, 1.0])


def test_hand_example_with_tie():
    w = np.array(
        [
            [1.0, 0.5, 0.0, 0.0],
            [0.0, 1.0, 1.0, 0.0],
            [0.0, 0.0, 0.2, 1.0],
        ]
    )
    # c({v}) rows: [1, .5102, 0, 0], [0, 1, 1, 0], [0, 0, .2041, 1]. View 1 first (gain 2);
    # then views 0 and 2 both gain 1: the lower index wins; view 2 completes the coverage.
    result = select_views(w)
    assert result.views == (1, 0, 2)
    np.testing.assert_allclose(result.coverage, [0.5, 0.75, 1.0])
    np.testing.assert_allclose(result.gains, [0.5, 0.25, 0.25])
    assert result.stop_reason == COVERAGE_REACHED
    assert result.num_targets == 4 and result.blind_views == ()


def test_rho_caps_the_needed_support():
    # 0.99 >= 0.98 * 1.0: the second-best view already covers the Gaussian completely.
    assert select_views(np.array([[0.99], [1.0]])).views == (0,)
    assert select_views(np.array([[0.97], [1.0]])).views == (1,)
    assert select_views(np.array([[0.97], [1.0]]), ViewSelectionSettings(target_fraction=0.97)).views == (0,)


def test_minimum_support_defines_the_target_set():
    w = np.array([[1.0, 5e-5, 2e-4, 0.0]])
    result = select_views(w)
    assert result.num_targets == 2  # 5e-5 < w_min and 0 are not targets
    assert result.coverage == (1.0,)


def test_gain_threshold_stops_before_a_useless_view():
    w = np.zeros((2, 1001))
    w[0, :1000] = 1.0
    w[1, 1000] = 1.0
    result = select_views(w)
    assert result.views == (0,)
    assert result.stop_reason == GAIN_BELOW_THRESHOLD
    assert result.coverage[0] == pytest.approx(1000 / 1001)
    # Without a gain threshold the last Gaussian gets its view.
    full = select_views(w, ViewSelectionSettings(min_gain=0.0))
    assert full.views == (0, 1) and full.coverage[-1] == 1.0 and full.stop_reason == COVERAGE_REACHED


def test_the_first_pick_is_always_made_and_view_limit():
    w = np.eye(5000)[:3]  # each view sees one Gaussian: gain 1/3 each... of |T| = 3
    assert select_views(w, ViewSelectionSettings(min_gain=0.5)).views == (0,)
    limited = select_views(_random_visibility(20, 500, 1), ViewSelectionSettings(max_views=4))
    assert len(limited.views) == 4 and limited.stop_reason == VIEW_LIMIT_REACHED


def test_blind_views_are_reported_and_cameras_seeing_nothing_raise():
    w = _random_visibility(6, 300, 2)
    w[3] = 0.0
    w[5] = np.where(w[:5].max(0) == 0, 1e-6, 0.0)  # sees only what nobody else sees, below w_min
    assert (w[5] > 0).any()
    result = select_views(w)
    assert result.blind_views == (3, 5)
    assert 3 not in result.views and 5 not in result.views
    with pytest.raises(CameraError) as error:
        select_views(np.zeros((2, 4)))
    names(error, "2 cameras", "4 Gaussians")
    with pytest.raises(CameraError):
        select_views(np.full((2, 4), 5e-5))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_lazy_greedy_equals_plain_greedy(seed):
    w = _random_visibility(30, 3000, seed)
    for settings in (
        ViewSelectionSettings(),
        ViewSelectionSettings(min_gain=0.0, coverage_stop=1.0),
        ViewSelectionSettings(target_fraction=0.5, min_gain=0.01),
    ):
        fast = select_views(w, settings)
        slow = select_views_reference(w, settings)
        assert fast.views == slow.views
        assert fast.stop_reason == slow.stop_reason
        assert fast.blind_views == slow.blind_views
        np.testing.assert_allclose(fast.coverage, slow.coverage, rtol=1e-5)
        np.testing.assert_allclose(fast.gains, slow.gains, rtol=1e-5, atol=1e-9)
        # Coverage only grows, gains only shrink (submodularity).
        assert all(a <= b for a, b in zip(fast.coverage, fast.coverage[1:]))
        assert all(a >= b - 1e-12 for a, b in zip(fast.gains, fast.gains[1:]))


def test_duplicate_views_tie_break_to_the_lowest_index():
    w = _random_visibility(5, 400, 4)
    w = np.concatenate([w[[2]], w, w[[2]]])  # views 0, 3 and 6 are identical
    result = select_views(w, ViewSelectionSettings(min_gain=0.0, coverage_stop=1.0))
    assert len(set(result.views)) == len(result.views)
    assert result.views == select_views_reference(w, ViewSelectionSettings(min_gain=0.0, coverage_stop=1.0)).views
    first_of_kind = [v for v in result.views if v in (0, 3, 6)]
    assert first_of_kind[0] == 0


@pytest.mark.filterwarnings("ignore:Sparse CSR tensor support is in beta state")
@pytest.mark.filterwarnings("ignore:Sparse invariant checks are implicitly disabled")
def test_dense_and_sparse_inputs_agree():
    w = _random_visibility(12, 1000, 5)
    expected = select_views(w)
    dense_torch = torch.from_numpy(w)
    assert select_views(dense_torch).views == expected.views
    assert select_views(dense_torch.double()).views == expected.views
    assert select_views(dense_torch.to_sparse_coo()).views == expected.views
    assert select_views(dense_torch.to_sparse_csr()).views == expected.views
    assert select_views(w.tolist()).views == expected.views
    # Uncoalesced COO with duplicates sums them, as a sparse matrix means.
    coo = dense_torch.to_sparse_coo()
    half = torch.sparse_coo_tensor(
        torch.cat([coo.indices(), coo.indices()], 1), torch.cat([coo.values(), coo.values()]) / 2, coo.shape
    )
    assert select_views(half).views == expected.views


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"\[V, N\]"):
        select_views(np.zeros(5))
    with pytest.raises(NumericalError):
        select_views(np.array([[1.0, np.nan]]))
    with pytest.raises(ValueError, match="negative"):
        select_views(np.array([[1.0, -0.5]]))
    with pytest.raises(CameraError, match="no candidate cameras"):
        select_views(np.zeros((0, 4)))
    with pytest.raises(ConfigError):
        ViewSelectionSettings(target_fraction=1.5)
    with pytest.raises(ConfigError):
        ViewSelectionSettings(min_support=0.0)
    with pytest.raises(ConfigError):
        ViewSelectionSettings(max_views=0)
