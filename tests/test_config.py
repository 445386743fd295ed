"""The settings: typed groups named flat or dotted, presets as they were, and checkpoints of earlier versions."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from dresg_addon.method.config import (
    FLAT_NAMES,
    PRESETS,
    AblationSettings,
    ProposalSettings,
    SolveSettings,
    StylizeConfig,
    preset,
)
from dresg_addon.util.errors import ConfigError

DATA = Path(__file__).parent / "data"

# Every preset's settings as the flat StylizeConfig had them (commit b39286f), before the settings were grouped.
OLD_PAPER = {
    "stages": 20,
    "updates_per_stage": 10,
    "ddim_steps": 200,
    "schedule": "snr-balanced",
    "logit_space": True,
    "proposal": "synth",
    "model_path": "",
    "proposal_width": 448,
    "proposal_height": 320,
    "stroke_size": 1.0,
    "scene_weight": 0.5,
    "latent_lr": 0.05,
    "use_content_query": True,
    "use_style_keys": True,
    "use_style_values": True,
    "feedback": True,
    "guide_weight": 16.0,
    "color_fit": "solve",
    "fit_steps": 30,
    "post_steps": 50,
    "solve_tolerance": 0.005,
    "solve_rounds": 6,
    "solve_cg_iterations": 8,
    "robust_power": 2.0,
    "solve_anchor": 0.3,
    "layer_agreement": 0.0,
    "log_optimum": False,
    "color_lr": 0.05,
    "geometry_lr": 0.001,
    "optimize_geometry": True,
    "mean_bound": 0.05,
    "log_scale_bound": 0.05,
    "quat_bound": 0.02,
    "pcgrad": True,
    "pcgrad_eps": 1e-12,
    "lambda_ssim": 0.2,
    "lambda_tv": 0.01,
    "lambda_feature": 0.01,
    "dino_path": "",
    "render_scale": 1.0,
    "scene_extent": 0.0,
    "max_views": 0,
    "w_min": 0.0001,
    "rho": 0.98,
    "coverage_stop": 0.9999,
    "gain_threshold": 0.001,
    "early_stop": 0.0,
    "sh_rest": "zero",
    "background": (0.0, 0.0, 0.0),
    "near": 0.01,
    "seed": 0,
}
OLD_PRESETS = {
    "paper": {**OLD_PAPER, **{}},
    "cpu": {**OLD_PAPER, **{"optimize_geometry": False}},
    "standard": {
        **OLD_PAPER,
        **{
            "stages": 12,
            "updates_per_stage": 1,
            "stroke_size": 1.5,  # docs/decisions/002-stroke-size.md
            "post_steps": 0,
            "optimize_geometry": False,
            "max_views": 16,
            "early_stop": 0.01,
        },
    },
    "preview": {
        **OLD_PAPER,
        **{
            "stages": 6,
            "updates_per_stage": 1,
            "stroke_size": 1.5,  # as standard
            "fit_steps": 15,
            "post_steps": 0,
            "optimize_geometry": False,
            "max_views": 8,
            "early_stop": 0.01,
        },
    },
}
# Settings the flat config had that are gone, at the one value every preset had.
GONE = {"layer_agreement": 0.0, "robust_power": 2.0, "log_optimum": False}
# Settings added since, at each preset's value, and at the value that runs what the old code ran.
ADDED = {
    "standard": {"solve_start": "views", "solve_best_views": 4.0, "scene_light": 0.5, "medium": "auto"},
    "preview": {"solve_start": "views", "solve_best_views": 0.0, "scene_light": 0.5, "medium": "auto"},
    "paper": {"solve_start": "views", "solve_best_views": 0.0, "scene_light": 0.0, "medium": "paint"},
    "cpu": {"solve_start": "views", "solve_best_views": 0.0, "scene_light": 0.0, "medium": "paint"},
}
ADDED_AS_BEFORE = {"solve_start": "colors", "solve_best_views": 0.0, "scene_light": 0.0, "medium": "paint"}


@pytest.mark.parametrize("name", sorted(OLD_PRESETS))
def test_every_preset_has_every_setting_it_had(name):
    old = OLD_PRESETS[name]
    config = PRESETS[name]
    added = ADDED[name]
    assert config.to_dict() == {**{k: v for k, v in old.items() if k not in GONE}, **added}
    assert all(old[k] == v for k, v in GONE.items())
    # A run id hashes the old flat settings and the added ones that run otherwise than the old code; set to what
    # the old code ran, exactly the old settings, so earlier checkpoints resume where the run is the same.
    assert config.run_values() == {**old, **{k: v for k, v in added.items() if v != ADDED_AS_BEFORE[k]}}
    assert config.with_(**ADDED_AS_BEFORE).run_values() == old
    assert {k: type(v) for k, v in config.to_dict().items()} == {k: type({**old, **added}[k]) for k in config.to_dict()}


def test_settings_are_named_flat_or_dotted_and_land_in_their_group():
    config = preset("preview", stages=3, solve_anchor=1.0, **{"proposal.stroke_size": 3.0, "seed": 4})
    assert config.schedule.stages == 3 and config.solve.anchor == 1.0 and config.proposal.stroke_size == 3.0
    assert config.seed == 4 and config.value("solve_anchor") == config.value("solve.anchor") == 1.0
    assert config.fit == PRESETS["preview"].fit  # untouched groups are the preset's
    assert preset("standard", proposal="sd15", model_path="m").proposal.backend == "sd15"
    assert preset("standard", schedule="triangle").schedule.strength == "triangle"
    assert set(FLAT_NAMES) == set(StylizeConfig().to_dict())
    for name in ("no_such", "solve.no_such", "nothing.anchor", "solve.solve_anchor"):
        with pytest.raises(ConfigError, match="unknown setting"):
            preset("standard", **{name: 1})


def test_each_group_checks_its_own_settings():
    with pytest.raises(ConfigError, match="stroke_size must be in"):
        preset("standard", stroke_size=0.1)
    with pytest.raises(ConfigError, match="scene_weight must be in"):
        ProposalSettings(scene_weight=2.0)
    with pytest.raises(ConfigError, match="solve_anchor must be >= 0"):
        SolveSettings(anchor=-1.0)
    with pytest.raises(ConfigError, match="solve_best_views must be >= 0"):
        SolveSettings(best_views=float("nan"))
    with pytest.raises(ConfigError, match="exceeds ddim_steps"):
        preset("paper", stages=30)
    assert StylizeConfig(ablation=AblationSettings(feedback=False)).value("feedback") is False


def test_a_checkpoint_of_the_flat_config_resumes(tmp_path, monkeypatch):
    """tests/data/checkpoint_flat_config.pt: stage 1 of test_pipeline's TINY run, written by the flat config's code
    (commit b39286f). Its run id hashed the flat settings with the run's scene, cameras and images, which are
    bit-exact only on a CPU like the one that wrote it (numpy's and torch's vector paths differ between CPUs), so
    the id is rebuilt from the flat settings as that code had them and this machine's images. The grouped config
    still matches it, run as that code ran (the colour solve from the splats' own colours); run as now (from the
    views), it starts over."""
    from test_pipeline import TINY, run

    from dresg_addon.method import loop

    inputs = []
    real_run_id = loop.run_id
    monkeypatch.setattr(loop, "run_id", lambda values, *rest: inputs.append(rest) or real_run_id(values, *rest))
    run(config=TINY.with_(**ADDED_AS_BEFORE), checkpoint_dir=tmp_path / "probe")  # sees the run's inputs
    tiny_flat = {"stages": 2, "updates_per_stage": 2, "fit_steps": 3, "post_steps": 3, "proposal_width": 32}
    flat = {**OLD_PAPER, **tiny_flat, "proposal_height": 24, "optimize_geometry": False}
    checkpoint = torch.load(DATA / "checkpoint_flat_config.pt", weights_only=False)
    checkpoint["run_id"] = real_run_id(flat, *inputs[0])
    torch.save(checkpoint, tmp_path / "checkpoint.pt")
    messages = []
    result = run(config=TINY.with_(**ADDED_AS_BEFORE), checkpoint_dir=tmp_path, messages=messages.append)
    assert any(m.startswith("resuming after stage 1 from ") for m in messages), messages
    assert [e["stage"] for e in result.log] == [1, 2, "post"]
    torch.save(checkpoint, tmp_path / "checkpoint.pt")
    messages.clear()
    run(checkpoint_dir=tmp_path, messages=messages.append)
    assert not any(m.startswith("resuming") for m in messages), messages


def test_a_flat_config_checkpoint_of_other_settings_starts_over_in_one_line_naming_it(tmp_path):
    from test_pipeline import TINY, run

    shutil.copy(DATA / "checkpoint_flat_config.pt", tmp_path / "checkpoint.pt")
    messages = []
    run(config=TINY.with_(solve_anchor=0.5), checkpoint_dir=tmp_path, messages=messages.append)
    said = [m for m in messages if "checkpoint" in m]
    assert said == [
        f"the checkpoint {tmp_path / 'checkpoint.pt'} is from other settings, scene, cameras or style; starting over"
    ]


def test_quality_bench_rows_name_settings_flat_or_dotted():
    from quality import row_settings

    name, changes = row_settings("standard@stroke_size=3,solve.anchor=0.5,optimize_geometry=on,schedule=triangle")
    assert (name, changes) == (
        "standard",
        {"stroke_size": 3.0, "solve.anchor": 0.5, "optimize_geometry": True, "schedule": "triangle"},
    )
    assert preset(name, **changes).solve.anchor == 0.5
    with pytest.raises(SystemExit, match="not a StylizeConfig setting"):
        row_settings("standard@layer_agreement=0.5")
