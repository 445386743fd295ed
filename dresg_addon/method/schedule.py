"""Scheduler quantities and residual-strength schedules, computed without any model weights.

Stable Diffusion v1.5 trains with 1000 steps of "scaled_linear" betas (linear in sqrt(beta) from
0.00085 to 0.012). DReSG walks the 200 DDIM timesteps of diffusers' "leading" spacing with
``steps_offset=1`` (t = 996, 991, ..., 6, 1) in blocks of S = 10 updates: each block is one feedback
stage, and its last timestep is the stage's scheduler state k (t = 951, 901, ..., 51, 1), which sets
the residual strength gamma_k of that stage (Sec. 4.2).

Equation numbers follow the order of the equations in the paper's source (``paper/DReSG.tex``);
each citation also names the LaTeX label.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..util.errors import ConfigError

SD15_BETA_START = 0.00085
SD15_BETA_END = 0.012
SD15_TRAIN_TIMESTEPS = 1000
DDIM_STEPS = 200  # the paper's N
UPDATES_PER_STAGE = 10  # the paper's S
NUM_STAGES = DDIM_STEPS // UPDATES_PER_STAGE  # F = N / S = 20


def scaled_linear_betas(
    num_train_timesteps: int = SD15_TRAIN_TIMESTEPS,
    beta_start: float = SD15_BETA_START,
    beta_end: float = SD15_BETA_END,
) -> np.ndarray:  # [T] float64
    """SD1.5 "scaled_linear" betas: beta_t = (sqrt(b0) + (sqrt(b1) - sqrt(b0)) t / (T - 1))^2, t = 0..T-1."""
    if num_train_timesteps < 2:
        raise ConfigError(f"num_train_timesteps must be at least 2, got {num_train_timesteps}")
    return np.linspace(math.sqrt(beta_start), math.sqrt(beta_end), num_train_timesteps, dtype=np.float64) ** 2


def alphas_cumprod(betas: np.ndarray | None = None) -> np.ndarray:  # [T] float64
    """Eq. 3 (``eq:diffusion-forward``): abar_t = prod_{i <= t} (1 - beta_i); SD1.5 betas by default."""
    if betas is None:
        betas = scaled_linear_betas()
    return np.cumprod(1.0 - np.asarray(betas, dtype=np.float64))


def signal_to_noise(alpha_bar):
    """Eq. 4 (``eq:diffusion-snr``): SNR = abar / (1 - abar); +inf at abar = 1."""
    abar = np.asarray(alpha_bar, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return _like_input(np.where(abar >= 1.0, np.inf, abar / np.maximum(1.0 - abar, 0.0)), alpha_bar)


def ddim_timesteps(
    num_inference_steps: int = DDIM_STEPS,
    num_train_timesteps: int = SD15_TRAIN_TIMESTEPS,
    steps_offset: int = 1,
) -> list[int]:
    """DDIM timesteps with diffusers' "leading" spacing, in denoising (descending) order.

    t_j = j * (T // N) + steps_offset for j = N-1, ..., 0; for SD1.5 (T = 1000, N = 200, offset 1):
    996, 991, ..., 6, 1, as ``DDIMScheduler.set_timesteps`` computes them.
    """
    if not 1 <= num_inference_steps <= num_train_timesteps:
        raise ConfigError(f"DDIM steps must be between 1 and {num_train_timesteps}, got {num_inference_steps}")
    step_ratio = num_train_timesteps // num_inference_steps
    return [j * step_ratio + steps_offset for j in range(num_inference_steps - 1, -1, -1)]


@dataclass(frozen=True)
class Stage:
    """One feedback stage n of F (Algorithm 1), as the loop hands it to a proposal backend.

    The paper's schedule is written in DDIM timesteps, which the sd15 backend runs; a backend with its own
    coarse-to-fine ladder (synth) reads only where the stage lies in the run: ``index`` of ``stages``, and
    its ``updates``.
    """

    index: int  # n, 1-based
    stages: int  # F, the run's number of stages
    timesteps: tuple[int, ...]  # the timesteps of the latent updates, in order
    state: int  # k_n, the last of ``timesteps``
    alpha_bar: float  # abar at k_n

    def __post_init__(self):
        if not 1 <= self.index <= self.stages:
            raise ConfigError(f"stage index {self.index} is outside 1..{self.stages}")
        if not self.timesteps:
            raise ConfigError(f"stage {self.index} has no updates")

    @property
    def updates(self) -> int:
        """S: the stage's proposal updates (latent steps, or synthesis passes)."""
        return len(self.timesteps)


def stage_timesteps(
    num_stages: int = NUM_STAGES,
    updates_per_stage: int = UPDATES_PER_STAGE,
    num_inference_steps: int = DDIM_STEPS,
    alpha_bar: np.ndarray | None = None,
) -> list[Stage]:
    """Split the DDIM timesteps into ``num_stages`` feedback stages (Algorithm 1, k = tau_{S(n-1)+j}).

    Stage n owns the contiguous block of DDIM indices [floor((n-1) N / F), floor(n N / F)) and runs
    ``updates_per_stage`` updates at timesteps picked uniformly inside that block, ending on the
    block's last timestep, which is the stage state k_n. With the paper's F = 20, S = 10, N = 200
    every timestep is used once and k_n = 951, 901, ..., 51, 1; fewer stages (previews) keep the same
    noise range, sampled more sparsely.
    """
    if num_stages < 1:
        raise ConfigError(f"the number of stages must be at least 1, got {num_stages}")
    if updates_per_stage < 1:
        raise ConfigError(f"updates per stage must be at least 1, got {updates_per_stage}")
    if num_stages * updates_per_stage > num_inference_steps:
        raise ConfigError(
            f"{num_stages} stages x {updates_per_stage} updates need at least {num_stages * updates_per_stage} "
            f"DDIM steps, but only {num_inference_steps} are set"
        )
    timesteps = ddim_timesteps(num_inference_steps)
    abar = alphas_cumprod() if alpha_bar is None else np.asarray(alpha_bar, dtype=np.float64)
    stages = []
    for n in range(num_stages):
        start = n * num_inference_steps // num_stages
        length = (n + 1) * num_inference_steps // num_stages - start
        # Integer floor keeps the picks strictly increasing (length >= updates_per_stage).
        picks = [start + (j + 1) * length // updates_per_stage - 1 for j in range(updates_per_stage)]
        block = tuple(timesteps[p] for p in picks)
        stages.append(
            Stage(index=n + 1, stages=num_stages, timesteps=block, state=block[-1], alpha_bar=float(abar[block[-1]]))
        )
    return stages


def gamma_snr_balanced(alpha_bar):
    """Eq. 11 (``eq:snr-residual-weight``), SNR-balanced schedule: gamma = 1 + 4 abar (1 - abar).

    Equal to 1 + 4 SNR / (1 + SNR)^2; bounded in [1, 2], peak 2 at abar = 1/2 (SNR = 1), gamma = 1 at
    abar = 0 and abar = 1. Inputs outside [0, 1] are clamped into it.
    """
    abar = np.clip(np.asarray(alpha_bar, dtype=np.float64), 0.0, 1.0)
    return _like_input(1.0 + 4.0 * abar * (1.0 - abar), alpha_bar)


def gamma_snr_balanced_from_snr(snr):
    """Eq. 11 (``eq:snr-residual-weight``) in SNR form: gamma = 1 + 4 SNR / (1 + SNR)^2.

    Written as 1 + 4 / (SNR + 2 + 1/SNR) for SNR >= 1 and with SNR for SNR < 1, so that SNR = 0 and
    SNR = +inf both give exactly 1 and the value is symmetric under SNR -> 1/SNR (to rounding).
    """
    s = np.asarray(snr, dtype=np.float64)
    if np.any(s < 0) or np.any(np.isnan(s)):
        raise ValueError("SNR must be non-negative")
    with np.errstate(divide="ignore", over="ignore"):
        r = np.where(s > 1.0, 1.0 / s, s)  # fold onto [0, 1]: the formula is symmetric in SNR <-> 1/SNR
        return _like_input(1.0 + 4.0 * r / (1.0 + r) ** 2, snr)


def gamma_fixed_one(alpha_bar):
    """Ablation "Fixed gamma = 1" (Table ``tab:schedule-ablation``): p = 0, the unamplified proposal."""
    return _like_input(np.ones_like(np.asarray(alpha_bar, dtype=np.float64)), alpha_bar)


def gamma_fixed_two(alpha_bar):
    """Ablation "Fixed gamma = 2" (Table ``tab:schedule-ablation``): p = 1 at every stage."""
    return _like_input(np.full_like(np.asarray(alpha_bar, dtype=np.float64), 2.0), alpha_bar)


def gamma_triangle(alpha_bar):
    """Ablation "Triangle" (Table ``tab:schedule-ablation``): gamma = 1 + p, p = 1 - |2 abar - 1|.

    Same range and peak as SNR-balanced, piecewise linear in abar.
    """
    abar = np.clip(np.asarray(alpha_bar, dtype=np.float64), 0.0, 1.0)
    return _like_input(2.0 - np.abs(2.0 * abar - 1.0), alpha_bar)


def gamma_timestep_cosine(stage_index: int, num_stages: int) -> float:
    """Ablation "Timestep cosine" (Table ``tab:schedule-ablation``): gamma = 1 + sin^2(pi (n - 1) / (F - 1)).

    Defined over the 1-based stage index n of F stages, peaking at the middle stage; with a single
    stage (F = 1) the profile has no interior and gamma is 1.
    """
    if num_stages < 1 or not 1 <= stage_index <= num_stages:
        raise ConfigError(f"stage index {stage_index} is outside 1..{num_stages}")
    if num_stages == 1:
        return 1.0
    return 1.0 + math.sin(math.pi * (stage_index - 1) / (num_stages - 1)) ** 2


# name -> gamma(alpha_bar at k_n, n, F); names are what settings, the CLI and the panel use.
RESIDUAL_SCHEDULES: dict[str, Callable[[float, int, int], float]] = {
    "snr-balanced": lambda abar, n, f: float(gamma_snr_balanced(abar)),
    "fixed-1": lambda abar, n, f: float(gamma_fixed_one(abar)),
    "fixed-2": lambda abar, n, f: float(gamma_fixed_two(abar)),
    "triangle": lambda abar, n, f: float(gamma_triangle(abar)),
    "timestep-cosine": lambda abar, n, f: gamma_timestep_cosine(n, f),
}


def residual_gamma(schedule: str, alpha_bar: float, stage_index: int, num_stages: int) -> float:
    """gamma_{k_n} = 1 + p_n of the named schedule (one of ``RESIDUAL_SCHEDULES``) at stage n of F."""
    try:
        fn = RESIDUAL_SCHEDULES[schedule]
    except KeyError:
        raise ConfigError(
            f"unknown residual schedule {schedule!r}; choose one of {', '.join(RESIDUAL_SCHEDULES)}"
        ) from None
    return fn(alpha_bar, stage_index, num_stages)


def stage_gammas(schedule: str, stages: list[Stage]) -> list[float]:
    """gamma of every stage of ``stages`` under the named schedule."""
    return [residual_gamma(schedule, s.alpha_bar, s.index, s.stages) for s in stages]


def _like_input(value: np.ndarray, reference):
    """A Python float for scalar input, an array otherwise."""
    return float(value) if np.ndim(reference) == 0 else value
