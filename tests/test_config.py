"""The settings: what the artist sets, the presets' plans, and checkpoints of earlier versions."""

from __future__ import annotations

import shutil
from dataclasses import asdict, fields
from pathlib import Path

import pytest

from dresg_addon.method.config import (
    PLANS,
    PRESETS,
    SETTINGS,
    Ablation,
    Plan,
    StylizeConfig,
    check_run_settings,
    preset,
    preset_run,
)
from dresg_addon.util.errors import ConfigError

DATA = Path(__file__).parent / "data"

# Every preset as the grouped config had it (the settings that are still the user's, and the plan's).
LOOKS = {
    "paper": {"stages": 20, "max_views": 0, "stroke_size": 1.0, "scene_light": 0.0, "medium": "paint", "geometry": True},
    "cpu": {"stages": 20, "max_views": 0, "stroke_size": 1.0, "scene_light": 0.0, "medium": "paint", "geometry": False},
    "standard": {"stages": 12, "max_views": 16, "stroke_size": 1.5, "scene_light": 0.5, "medium": "auto", "geometry": False},
    "preview": {"stages": 6, "max_views": 8, "stroke_size": 1.5, "scene_light": 0.5, "medium": "auto", "geometry": False},
}  # fmt: skip
STEPS = {  # updates per stage, fit steps, post steps, early stop, best views
    "paper": (10, 30, 50, 0.0, 0.0),
    "cpu": (10, 30, 50, 0.0, 0.0),
    "standard": (1, 30, 0, 0.01, 4.0),
    "preview": (1, 15, 0, 0.01, 0.0),
}


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_runs_the_settings_and_plan_it_ran(name):
    config, plan = PRESETS[name], PLANS[name]
    look = LOOKS[name]
    assert config.preset == name and config.plan() is plan
    assert (config.stages, config.max_views, config.stroke_size, config.scene_light, config.medium) == (
        look["stages"],
        look["max_views"],
        look["stroke_size"],
        look["scene_light"],
        look["medium"],
    )
    assert config.optimize_geometry is look["geometry"]
    assert (config.proposal_width, config.proposal_height, config.scene_weight, config.proposal) == (
        448,
        320,
        0.5,
        "synth",
    )
    assert (plan.updates_per_stage, plan.fit_steps, plan.post_steps, plan.early_stop, plan.best_views) == STEPS[name]
    assert plan.schedule == "snr-balanced" and plan.ablation == Ablation()


def test_the_public_settings_are_the_artist_s_and_at_most_fifteen():
    assert len(SETTINGS) <= 15
    assert StylizeConfig() == PRESETS["standard"]  # the defaults are the default preset's
    internals = {f.name for f in fields(Plan)} | {f.name for f in fields(Ablation)}
    assert not internals & set(SETTINGS)
    assert set(StylizeConfig().to_dict()) == set(SETTINGS)


def test_settings_change_by_name_and_unknown_ones_are_refused():
    config = preset("preview", stages=3, stroke_size=3.0, seed=4)
    assert (config.stages, config.stroke_size, config.seed, config.max_views) == (3, 3.0, 4, 8)
    for name in ("no_such", "fit_steps", "solve_anchor", "guide_weight", "render_scale"):
        with pytest.raises(ConfigError, match=f"unknown setting '{name}'"):
            preset("standard", **{name: 1})
    with pytest.raises(ConfigError, match="unknown preset"):
        preset("fast")


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"stroke_size": 0.1}, "stroke_size"),
        ({"stroke_size": float("nan")}, "stroke_size"),
        ({"scene_weight": 2.0}, "scene_weight"),
        ({"scene_light": -0.1}, "scene_light"),
        ({"medium": "oil"}, "medium"),
        ({"proposal": "sd21"}, "proposal"),
        ({"stages": 0}, "stages"),
        ({"max_views": -1}, "max_views"),
        ({"proposal_width": 4}, "proposal size"),
        ({"sh_rest": "half"}, "sh_rest"),
        ({"background": (0.0, float("inf"), 0.0)}, "background"),
    ],
)
def test_a_bad_setting_names_itself(changes, field):
    with pytest.raises(ConfigError, match=field):
        preset("standard", **changes)


def test_a_plan_checks_its_fields_and_takes_the_ablation_flags_by_name():
    plan = PLANS["preview"].with_(feedback=False, fit_steps=2)
    assert plan.ablation.feedback is False and plan.fit_steps == 2 and plan.ablation.pcgrad is True
    for bad in (
        {"updates_per_stage": 0},
        {"schedule": "linear"},
        {"early_stop": 1.0},
        {"best_views": float("nan")},
        {"split_floor": -1},
        {"split_floor": 0.5},
        {"marks_emphasis": -1.0},
        {"emphasis_width": 0.0},
        {"emphasis_width": float("inf")},
    ):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            Plan(**bad)
    with pytest.raises(ConfigError, match="exceed"):
        check_run_settings(preset("paper", stages=30))  # 30 x 10 updates: more than the schedule's 200 steps


def test_preset_run_splits_settings_from_plan_fields():
    config, plan = preset_run("cpu", stages=2, post_steps=3, pcgrad=False, stroke_size=2.0)
    assert (config.preset, config.stages, config.stroke_size) == ("cpu", 2, 2.0)
    assert plan.post_steps == 3 and plan.ablation.pcgrad is False and plan.fit_steps == PLANS["cpu"].fit_steps
    assert asdict(preset_run("standard")[1]) == asdict(PLANS["standard"])


def test_a_checkpoint_of_an_earlier_version_starts_over_in_one_line_naming_it(tmp_path):
    """tests/data/checkpoint_flat_config.pt was written before checkpoints carried a schema version."""
    from test_pipeline import TINY, run

    shutil.copy(DATA / "checkpoint_flat_config.pt", tmp_path / "checkpoint.pt")
    messages = []
    result = run(config=TINY, checkpoint_dir=tmp_path, messages=messages.append)
    said = [m for m in messages if "checkpoint" in m]
    assert len(said) == 1 and str(tmp_path / "checkpoint.pt") in said[0] and "starting over" in said[0]
    assert [e["stage"] for e in result.log] == [1, 2, "post"]


def test_quality_bench_rows_name_settings_and_plan_fields():
    from quality import row_settings

    name, changes, plan_changes = row_settings("standard@stroke_size=3,optimize_geometry=on,schedule=triangle")
    assert (name, changes, plan_changes) == (
        "standard",
        {"stroke_size": 3.0, "optimize_geometry": True},
        {"schedule": "triangle"},
    )
    with pytest.raises(SystemExit, match="neither a StylizeConfig setting nor a Plan field"):
        row_settings("standard@layer_agreement=0.5")


def test_a_bad_choice_names_the_value_given():
    for name, value in (("proposal", "sd21"), ("medium", "oil"), ("sh_rest", "half"), ("preset", "fast")):
        with pytest.raises(ConfigError, match=f"got '{value}'"):
            StylizeConfig().with_(**{name: value})
