"""``bench/quality.py``'s measurements and tables on a tiny scene (the benchmark itself is not run)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import quality  # bench/, on pytest's pythonpath

from dresg_addon.evaluation.stability import tiny_scene
from dresg_addon.evaluation.views import base_views, evaluate_views
from dresg_addon.scene.orbit import orbit_cameras

NEW_COLUMNS = {"texture_kept": "texture kept ↓", "shapes": "shapes ↑"}


@pytest.fixture(scope="module")
def case():
    scene = tiny_scene(120)
    cameras = orbit_cameras(scene, 4, width=48, height=32)
    style = np.random.default_rng(0).uniform(0, 1, (40, 56, 3)).astype(np.float32)
    return scene, cameras, style


def test_quality_columns_include_texture_kept_and_shapes():
    labels = {key: label for key, label, _ in quality.COLUMNS}
    for key, label in NEW_COLUMNS.items():
        assert labels[key] == label
    assert "texture kept" in quality.__doc__ and "shapes" in quality.__doc__


@pytest.mark.slow
def test_quality_evaluate_reports_every_measured_column(case):
    scene, cameras, style = case
    recoloured = replace(scene, sh_dc=scene.sh_dc[::-1].copy())
    base = base_views(scene, cameras)
    result = evaluate_views(recoloured, base, style)  # what quality.run_case measures
    measured = result.mean
    assert len(result.renders_2x) == len(cameras)
    fit_keys = {"min_closed"}  # from the stylize log, not from the views
    for key, _, _ in quality.COLUMNS:
        if key not in fit_keys:
            assert key in measured and measured[key] is not None and math.isfinite(measured[key]), key
    assert -1.0 <= measured["texture_kept"] < 0.99 and 0.0 < measured["shapes"] < 1.0
    unstylized = evaluate_views(scene, base, style).mean
    assert unstylized["texture_kept"] == pytest.approx(1.0, abs=1e-5)
    assert unstylized["shapes"] == pytest.approx(1.0, abs=1e-5)
    table = "\n".join(quality.table([("unstylized", {**unstylized, "seconds": 0.0, "peak_rss": 1e9})]))
    assert all(label in table for label in NEW_COLUMNS.values())


def test_quality_verdicts_check_texture_kept_over_the_pairs_and_shapes_per_scene():
    def row(texture, shapes, sw=0.5):
        values = {key: sw for key, _, _ in quality.COLUMNS}
        return {**values, "texture_kept": texture, "shapes": shapes, "seconds": 1.0, "peak_rss": 1e9}

    results = {
        ("bonsai", "a"): {"colour-transfer": row(0.9, 0.9, 1.0), "preview": row(0.2, 0.7)},
        ("bonsai", "b"): {"colour-transfer": row(0.9, 0.9, 1.0), "preview": row(0.3, 0.6)},
        ("luigi", "a"): {"colour-transfer": row(0.9, 0.9, 1.0), "preview": row(0.5, 0.4)},
    }
    text = "\n".join(quality.verdicts(results, ["colour-transfer", "preview"], quick=True))
    assert "texture kept ↓" in text and "shapes ↑" in text
    line = next(line for line in text.splitlines() if "per scene" in line)
    assert "texture kept 0.333 over the pairs" in line and "per scene bonsai 0.250, luigi 0.500" in line
    assert "shapes bonsai 0.650, luigi 0.400" in line
    assert f"<= {quality.TARGET_TEXTURE_KEPT} over the pairs and on the bonsai: met" in line  # mean 0.333, bonsai 0.25
    assert f">= {quality.TARGET_SHAPES} on every scene: NOT met" in line
    results[("luigi", "b")] = {"colour-transfer": row(0.9, 0.9, 1.0), "preview": row(0.9, 0.9)}  # the mean over 0.35
    line = next(line for line in quality.verdicts(results, ["colour-transfer", "preview"], True) if "per scene" in line)
    assert "on the bonsai: NOT met" in line
    del results[("luigi", "b")]
    del results[("luigi", "a")]
    line = next(line for line in quality.verdicts(results, ["colour-transfer", "preview"], True) if "per scene" in line)
    assert line.count(": met") == 2


def test_the_fit_summary_takes_the_smallest_share_of_a_gap_closed():
    log = [
        {"stage": 1, "target_gap": 0.2, "gap_closed": 0.9, "fit_residual": 0.1},
        {"stage": 2, "target_gap": 0.1, "gap_closed": 0.8, "fit_residual": 0.1},
        {"stage": "post", "target_gap": 0.1, "gap_closed": 0.5, "fit_residual": 0.1},
    ]
    summary = quality.fit_summary(log)
    assert summary["min_closed"] == 0.5 and summary["closed_per_stage"] == [0.9, 0.8, 0.5]
    assert quality.fit_summary([])["min_closed"] is None


def test_rows_with_settings_split_on_semicolons_and_runs_merge_pair_by_pair(tmp_path, capsys):
    assert quality.split_rows("colour-transfer,standard") == ["colour-transfer", "standard"]
    assert quality.split_rows("standard@stroke_size=2,scene_light=0") == ["standard@stroke_size=2,scene_light=0"]
    assert quality.split_rows("unstylized,standard@seed=1,seed=2,preview") == [
        "unstylized",
        "standard@seed=1,seed=2",
        "preview",
    ]
    assert quality.split_rows("colour-transfer;standard@stroke_size=1.5,scene_light=0.5") == [
        "colour-transfer",
        "standard@stroke_size=1.5,scene_light=0.5",
    ]
    values = {key: 0.5 for key, _, _ in quality.COLUMNS}
    row = {**values, "texture_kept": 0.2, "shapes": 0.7, "seconds": 1.0, "peak_rss": 1e9}
    tuned = "standard@stroke_size=1.5,scene_light=0.5"
    first, second = tmp_path / "a.json", tmp_path / "b.json"
    quality.write_json(str(first), {("demo", "lines"): {"colour-transfer": {**row, "sw_patches": 0.9}}})
    quality.write_json(str(second), {("demo", "lines"): {tuned: {**row, "sw_patches": 0.0123}}})
    assert quality.main(["--from-json", str(first), str(second), "--rows", f"colour-transfer;{tuned}"]) == 0
    out = capsys.readouterr().out
    assert "### demo x lines" in out and "### Means over 1 scene x style pairs" in out
    assert f"| {tuned} | 0.0123" in out and "| colour-transfer | 0.9000" in out
