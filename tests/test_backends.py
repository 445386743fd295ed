"""Issue 29, item 4: the proposal backends' registry, the one place a backend is added, and what reads it (the
config's choices, the CLI's choices and help, the loop's factory, the availability reasons, the cost note)."""

from __future__ import annotations

import importlib.util
import inspect
import math
from dataclasses import replace

import pytest
import torch
from messages import names

from dresg_addon import cli
from dresg_addon.method import backends
from dresg_addon.method.backends import (
    BACKENDS,
    SD15Costs,
    duration,
    estimate_cpu_seconds,
    slow_note,
    synth_content_weight,
)
from dresg_addon.method.config import StylizeConfig, check_run_settings, preset
from dresg_addon.method.proposal.synth import SynthBackend, SynthSettings
from dresg_addon.method.schedule import stage_timesteps
from dresg_addon.util.errors import ConfigError

# --- every backend declares itself ------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(BACKENDS))
def test_every_backend_declares_label_description_support_and_cost(name):
    entry = BACKENDS[name]
    assert entry.name == name and entry.label and entry.description and "\n" not in entry.description
    # the factory reads the run's settings, plan and scene brightness, and where a network runs
    assert len(inspect.signature(entry.build).parameters) == 4
    if entry.stroke_sigma is not None:
        assert entry.stroke_sigma(1.0) > 0 and entry.stroke_sigma(2.0) == pytest.approx(2 * entry.stroke_sigma(1.0))
    assert entry.ink_passes >= 0 and entry.proposal_cost >= 0 and entry.size_multiple >= 1
    paper = entry.cpu_seconds(16, 20, 10, 448, 320)
    assert math.isfinite(paper) and paper > 0
    assert entry.cpu_seconds(17, 20, 10, 448, 320) > paper and entry.cpu_seconds(16, 20, 10, 224, 160) < paper


def test_the_config_and_the_cli_offer_the_registered_backends(capsys):
    assert StylizeConfig().proposal == backends.DEFAULT_BACKEND and backends.DEFAULT_BACKEND in BACKENDS
    with pytest.raises(ConfigError) as error:
        StylizeConfig().with_(proposal="nope")
    names(error, "proposal", *BACKENDS)  # the setting and its choices
    with pytest.raises(SystemExit):
        cli.main(["stylize", "scene.ply", "--style", "s.png", "--out", "o.ply", "--proposal", "nope"])
    names(capsys.readouterr().err.strip().splitlines()[-1], "--proposal", "nope", *BACKENDS)
    with pytest.raises(SystemExit):
        cli.main(["stylize", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert f"--proposal {{{','.join(BACKENDS)}}}" in help_text
    for entry in BACKENDS.values():
        assert f"{entry.name}: {entry.description}" in help_text


# --- availability -----------------------------------------------------------------------------------------


def test_synth_is_always_available():
    assert BACKENDS["synth"].unavailable() is None


def test_sd15_without_a_model_path_says_so_in_one_line(tmp_path):
    sd15 = BACKENDS["sd15"]
    reason = sd15.unavailable("")
    names(reason, "model path")
    missing = tmp_path / "no-model"
    names(sd15.unavailable(str(missing)), str(missing))
    if importlib.util.find_spec("diffusers") is not None:
        assert sd15.unavailable(str(tmp_path)) is None  # a path on disk: whether it holds SD1.5 is the loader's


def test_sd15_without_diffusers_says_which_package_is_missing(tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "diffusers" else real(name, *a))
    reason = BACKENDS["sd15"].unavailable(str(tmp_path))
    names(reason, "sd15", "pip install diffusers")  # the backend and what to install
    with pytest.raises(ConfigError) as error:  # a run stops before any work
        check_run_settings(StylizeConfig().with_(proposal="sd15", model_path=str(tmp_path)))
    names(error, "diffusers")


def test_a_backend_size_multiple_is_checked_before_its_availability():
    with pytest.raises(ConfigError) as error:
        check_run_settings(StylizeConfig().with_(proposal="sd15", proposal_width=36, proposal_height=28))
    names(error, "sd15", "8")


def test_unknown_backend_names_the_choices():
    with pytest.raises(ConfigError) as error:
        backends.backend("sd21")
    names(error, "sd21", *BACKENDS)


# --- the loop builds the synth backend as before ------------------------------------------------------------


@pytest.mark.parametrize(
    "changes",
    [{}, {"stroke_size": 2.0, "scene_weight": 0.3, "seed": 3}, {"use_content_query": False, "scene_weight": 1.0}],
)
def test_the_synth_backend_gets_the_same_settings_and_proposes_the_same_pixels(changes):
    changes = dict(changes)
    content_query = changes.pop("use_content_query", True)
    config = preset("cpu", **changes)  # no scene light: the content fusion alone
    plan = config.plan().with_(use_content_query=content_query)
    built = BACKENDS["synth"].make(config, plan)
    # What the loop passed before the registry, written out.
    weight = synth_content_weight(config.scene_weight) if content_query else 0.0
    before = SynthBackend(
        seed=config.seed, content_weight=weight, content_sigma=SynthSettings.content_sigma * config.stroke_size
    )
    assert (
        built.settings
        == before.settings
        == replace(
            SynthSettings(), seed=config.seed, content_weight=weight, content_sigma=before.settings.content_sigma
        )
    )
    gen = torch.Generator().manual_seed(0)
    content, style = torch.rand(3, 24, 32, generator=gen), torch.rand(3, 24, 32, generator=gen)
    proposals = []
    for backend in (built, before):
        backend.prepare_stage([content], style, [content], [None])
        proposals.append(backend.propose(backend.encode(content), stage_timesteps(1, 2)[0], style, content)[0])
    assert torch.equal(proposals[0], proposals[1])


# --- what a run costs ---------------------------------------------------------------------------------------


def test_sd15_cpu_estimate_scales_with_work_and_warns_of_hours():
    paper = estimate_cpu_seconds(views=16)
    assert paper > 3 * 3600  # the paper's schedule is hours on a 2-core CPU
    assert estimate_cpu_seconds(views=17) > paper
    half = estimate_cpu_seconds(views=16, width=224, height=160)
    assert half == pytest.approx(paper / 4)
    costs = SD15Costs(unet_forward=1.0, unet_backward=1.0, vae_encode=0.0, vae_decode=0.0)
    assert costs.seconds_per_update == 3.0
    assert estimate_cpu_seconds(1, stages=1, updates_per_stage=1, costs=costs) == pytest.approx(3.0 + 1.0)
    with pytest.raises(ConfigError):
        estimate_cpu_seconds(views=-1)


def test_the_slow_note_is_for_gpu_backends_on_the_cpu_with_their_estimate():
    paper = preset("paper", proposal="sd15", model_path="x")
    note = slow_note(paper, "cpu")
    seconds = estimate_cpu_seconds(16, paper.stages, paper.plan().updates_per_stage, 448, 320)
    assert note == (
        f"sd15 on this CPU takes about {duration(seconds)} for this schedule (estimate); the synth backend takes minutes"
    )
    assert duration(seconds).endswith(" h") and duration(90.0) == "2 min"
    assert slow_note(paper.with_(max_views=4), "cpu") != note  # the views it runs
    assert slow_note(paper, "cuda") is None  # asked for a GPU: no note
    assert slow_note(preset("paper"), "cpu") is None  # synth runs on the CPU anyway
