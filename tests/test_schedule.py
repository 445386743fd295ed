"""Scheduler quantities and residual-strength schedules (Sec. 4.2, Table tab:schedule-ablation)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from messages import names

from dresg_addon.method.schedule import (
    RESIDUAL_SCHEDULES,
    alphas_cumprod,
    ddim_timesteps,
    gamma_snr_balanced,
    gamma_snr_balanced_from_snr,
    gamma_timestep_cosine,
    gamma_triangle,
    residual_gamma,
    scaled_linear_betas,
    signal_to_noise,
    stage_gammas,
    stage_timesteps,
)
from dresg_addon.util.errors import ConfigError

# REFERENCE.md section 1: stage -> (t, abar, gamma) printed to 5 and 4 decimals.
GAMMA_TABLE = {
    1: (951, 0.00816, 1.0324),
    5: (751, 0.05572, 1.2105),
    10: (501, 0.27500, 1.7975),
    13: (351, 0.50482, 1.9999),
    15: (251, 0.67215, 1.8815),
    20: (1, 0.99830, 1.0068),
}


@pytest.fixture(scope="module")
def diffusers_ddim():
    diffusers = pytest.importorskip("diffusers")
    scheduler = diffusers.DDIMScheduler(
        num_train_timesteps=1000,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        steps_offset=1,
        timestep_spacing="leading",
        clip_sample=False,
        set_alpha_to_one=False,
    )
    scheduler.set_timesteps(200)
    return scheduler


def test_betas_and_alpha_bar_match_diffusers(diffusers_ddim):
    betas = scaled_linear_betas()
    assert betas.shape == (1000,)
    assert betas[0] == pytest.approx(0.00085, rel=1e-12)
    assert betas[-1] == pytest.approx(0.012, rel=1e-12)
    np.testing.assert_allclose(betas, diffusers_ddim.betas.double().numpy(), rtol=1e-6)
    # diffusers keeps float32; our float64 product agrees to float32 accuracy over 1000 factors.
    np.testing.assert_allclose(alphas_cumprod(), diffusers_ddim.alphas_cumprod.double().numpy(), rtol=2e-5)


def test_ddim_leading_timesteps_match_diffusers(diffusers_ddim):
    ours = ddim_timesteps(200)
    assert ours == diffusers_ddim.timesteps.tolist()
    assert ours[:3] == [996, 991, 986] and ours[-2:] == [6, 1] and len(ours) == 200
    for steps in (1, 7, 50, 333):
        diffusers_ddim.set_timesteps(steps)
        assert ddim_timesteps(steps) == diffusers_ddim.timesteps.tolist()
    diffusers_ddim.set_timesteps(200)


def test_paper_stages_match_reference_table():
    stages = stage_timesteps()
    assert len(stages) == 20
    assert [s.state for s in stages] == list(range(951, 0, -50))
    # 20 blocks of 10 use every DDIM timestep exactly once, in order.
    assert [t for s in stages for t in s.timesteps] == ddim_timesteps(200)
    assert all(len(s.timesteps) == 10 and s.timesteps[-1] == s.state for s in stages)
    gammas = stage_gammas("snr-balanced", stages)
    for n, (t, abar, gamma) in GAMMA_TABLE.items():
        stage = stages[n - 1]
        assert stage.index == n
        assert stage.state == t
        assert round(stage.alpha_bar, 5) == pytest.approx(abar, abs=1e-12)
        assert round(gammas[n - 1], 4) == pytest.approx(gamma, abs=1e-12)
    assert max(gammas) == gammas[12]  # peak at t = 351, closest to abar = 1/2


def test_fewer_stages_cover_the_same_noise_range():
    stages = stage_timesteps(num_stages=5, updates_per_stage=4)
    assert [s.timesteps for s in stages] == [
        (951, 901, 851, 801),
        (751, 701, 651, 601),
        (551, 501, 451, 401),
        (351, 301, 251, 201),
        (151, 101, 51, 1),
    ]
    # Uneven splits: blocks still tile the list, picks strictly decrease, the last state is t = 1.
    for num_stages, updates in ((3, 7), (7, 3), (1, 1), (200, 1), (13, 15)):
        stages = stage_timesteps(num_stages, updates)
        flat = [t for s in stages for t in s.timesteps]
        assert len(flat) == num_stages * updates
        assert all(a > b for a, b in zip(flat, flat[1:]))
        assert stages[-1].state == 1
        assert stages[0].timesteps[0] <= 996


def test_a_stage_knows_its_place_in_the_run():
    stages = stage_timesteps(4, 3)
    assert [(s.index, s.stages, s.updates) for s in stages] == [(n, 4, 3) for n in range(1, 5)]
    stage = stages[0]
    for bad in ({"index": 0}, {"index": 5}, {"timesteps": (), "state": 1}):
        with pytest.raises(ConfigError):
            replace(stage, **bad)


def test_stage_settings_are_checked():
    with pytest.raises(ConfigError) as error:
        stage_timesteps(21, 10)
    names(error, "210")  # the DDIM steps 21 stages of 10 updates need
    with pytest.raises(ConfigError):
        stage_timesteps(0, 10)
    with pytest.raises(ConfigError):
        stage_timesteps(5, 0)
    with pytest.raises(ConfigError):
        ddim_timesteps(1001)


def test_snr_balanced_extremes_and_symmetry():
    assert gamma_snr_balanced(0.0) == 1.0
    assert gamma_snr_balanced(1.0) == 1.0
    assert gamma_snr_balanced(0.5) == 2.0
    assert gamma_snr_balanced(0.25) == pytest.approx(1.75, abs=1e-15)
    abar = np.linspace(0.0, 1.0, 1001)
    gamma = gamma_snr_balanced(abar)
    assert np.isfinite(gamma).all() and gamma.min() == 1.0 and gamma.max() == 2.0
    # The SNR form is the same function, symmetric under SNR -> 1/SNR and exactly 1 at 0 and inf.
    snr = signal_to_noise(abar)
    assert snr[0] == 0.0 and snr[-1] == math.inf
    np.testing.assert_allclose(gamma_snr_balanced_from_snr(snr), gamma, rtol=0, atol=1e-12)
    s = np.logspace(-30, 30, 121)
    # 1 / (1 / s) is s only to within an ulp, so the symmetry holds to rounding, not bit for bit.
    np.testing.assert_allclose(gamma_snr_balanced_from_snr(s), gamma_snr_balanced_from_snr(1.0 / s), rtol=1e-15, atol=0)
    assert gamma_snr_balanced_from_snr(0.0) == 1.0
    assert gamma_snr_balanced_from_snr(math.inf) == 1.0
    assert gamma_snr_balanced_from_snr(1.0) == 2.0
    assert gamma_snr_balanced_from_snr(3.0) == pytest.approx(1.0 + 12.0 / 16.0)
    with pytest.raises(ValueError):
        gamma_snr_balanced_from_snr(-1.0)


def test_alternative_schedules():
    assert gamma_triangle(0.0) == 1.0 and gamma_triangle(1.0) == 1.0 and gamma_triangle(0.5) == 2.0
    assert gamma_triangle(0.25) == 1.5 and gamma_triangle(0.9) == pytest.approx(1.2)
    assert gamma_timestep_cosine(1, 1) == 1.0  # one stage: no division by F - 1 = 0
    assert gamma_timestep_cosine(1, 20) == 1.0
    assert gamma_timestep_cosine(20, 20) == pytest.approx(1.0, abs=1e-15)
    assert gamma_timestep_cosine(11, 21) == 2.0
    assert gamma_timestep_cosine(2, 3) == 2.0
    assert gamma_timestep_cosine(6, 21) == pytest.approx(1.5)
    with pytest.raises(ConfigError):
        gamma_timestep_cosine(0, 20)
    with pytest.raises(ConfigError):
        gamma_timestep_cosine(21, 20)


def test_dispatcher():
    assert set(RESIDUAL_SCHEDULES) == {"snr-balanced", "fixed-1", "fixed-2", "triangle", "timestep-cosine"}
    stages = stage_timesteps()
    assert stage_gammas("fixed-1", stages) == [1.0] * 20
    assert stage_gammas("fixed-2", stages) == [2.0] * 20
    assert residual_gamma("triangle", 0.75, 3, 20) == 1.5
    assert residual_gamma("snr-balanced", 0.75, 3, 20) == 1.75
    cosine = stage_gammas("timestep-cosine", stages)
    assert cosine[0] == 1.0 and cosine[-1] == pytest.approx(1.0) and max(cosine) < 2.0
    assert cosine[9] == pytest.approx(1.0 + math.sin(math.pi * 9 / 19) ** 2)
    for name in RESIDUAL_SCHEDULES:
        values = stage_gammas(name, stages)
        assert all(1.0 <= g <= 2.0 and math.isfinite(g) for g in values)
    with pytest.raises(ConfigError) as error:
        residual_gamma("cosine", 0.5, 1, 20)
    names(error, "'cosine'")
