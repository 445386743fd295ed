"""``bench/quality.py``'s measurements and tables on a tiny scene (the benchmark itself is not run)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import quality  # bench/, on pytest's pythonpath

from dresg_addon.evaluation.stability import tiny_scene
from dresg_addon.evaluation.views import MARK_KEYS, base_views, evaluate_views
from dresg_addon.scene.orbit import orbit_cameras

NEW_COLUMNS = {
    "texture_kept": "texture kept ↓",
    "shapes": "shapes ↑",
    "forms": "forms ↑",
    "marks_fine": "marks fine",
    "marks_mid": "mid",
    "marks_coarse": "coarse",
}


@pytest.fixture(scope="module")
def case():
    scene = tiny_scene(120)
    cameras = orbit_cameras(scene, 4, width=48, height=32)
    style = np.random.default_rng(0).uniform(0, 1, (40, 56, 3)).astype(np.float32)
    return scene, cameras, style


def test_quality_columns_include_texture_kept_shapes_forms_and_marks():
    labels = {key: label for key, label, _ in quality.COLUMNS}
    for key, label in NEW_COLUMNS.items():
        assert labels[key] == label
    for text in ("texture kept", "shapes", "forms", "mark contrast"):
        assert text in quality.__doc__
    assert quality.MARK_KEYS == MARK_KEYS


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
    assert -1.0 <= measured["forms"] < 1.0 and all(measured[key] >= 0.0 for key in MARK_KEYS)
    unstylized = evaluate_views(scene, base, style).mean
    assert unstylized["texture_kept"] == pytest.approx(1.0, abs=1e-5)
    assert unstylized["shapes"] == pytest.approx(1.0, abs=1e-5) and unstylized["forms"] == pytest.approx(1.0)
    assert all(unstylized[key] == pytest.approx(0.0, abs=1e-6) for key in MARK_KEYS)  # the capture: no marks
    table = "\n".join(quality.table([("unstylized", {**unstylized, "seconds": 0.0, "peak_rss": 1e9})]))
    assert all(label in table for label in NEW_COLUMNS.values())


def test_quality_verdicts_check_texture_kept_forms_and_mark_contrast():
    def row(texture, forms, marks=(0.7, 1.0, 1.0), sw=0.5):
        values = {key: sw for key, _, _ in quality.COLUMNS}
        values.update(zip(quality.MARK_KEYS, marks))
        return {**values, "texture_kept": texture, "forms": forms, "seconds": 1.0, "peak_rss": 1e9}

    ct = row(0.9, 0.99, (0.1, 0.1, 0.1), sw=1.0)
    results = {
        ("bonsai", "a"): {"colour-transfer": ct, "preview": row(0.2, 0.9)},
        ("bonsai", "b"): {"colour-transfer": ct, "preview": row(0.3, 0.8, (0.5, 0.8, 0.8))},
        ("luigi", "a"): {"colour-transfer": ct, "preview": row(0.1, 0.7, (0.1, 0.1, 0.1))},
    }
    text = "\n".join(quality.verdicts(results, ["colour-transfer", "preview"], quick=True))
    for label in ("texture kept ↓", "shapes ↑", "forms ↑", "marks fine", "coarse"):
        assert label in text
    assert "by 50%, 50%, 50% at the fit size, half and a quarter (target >= 30%, 30%, 20%: met)" in text
    line = next(line for line in text.splitlines() if "per scene" in line)
    assert "texture kept 0.200 over the pairs" in line and "per scene bonsai 0.250, luigi 0.100" in line
    assert f"<= {quality.TARGET_TEXTURE_KEPT} over the pairs: met" in line
    assert "forms bonsai 0.850, luigi 0.700" in line and f">= {quality.TARGET_FORMS} on every scene: NOT met" in line
    marks = next(line for line in text.splitlines() if "mark contrast" in line)
    # Judged on the bonsai (means 0.60 / 0.90 / 0.90): met; the luigi is shown, not judged.
    assert "bonsai 0.60/0.90/0.90, luigi 0.10/0.10/0.10" in marks and marks.endswith(": met)")
    results[("bonsai", "c")] = {"colour-transfer": ct, "preview": row(0.9, 0.9, (0.7, 0.9, 2.5))}
    lines = quality.verdicts(results, ["colour-transfer", "preview"], True)
    assert next(line for line in lines if "per scene" in line).count("NOT met") == 2  # texture kept 0.375 now
    assert next(line for line in lines if "mark contrast" in line).endswith("NOT met)")  # coarse 1.43: above 1.3
    del results[("bonsai", "c")]
    del results[("luigi", "a")]
    lines = quality.verdicts(results, ["colour-transfer", "preview"], True)
    assert next(line for line in lines if "per scene" in line).count(": met") == 2
    del results[("bonsai", "a")], results[("bonsai", "b")]
    results[("luigi", "a")] = {"colour-transfer": ct, "preview": row(0.1, 0.9)}
    marks = next(
        line for line in quality.verdicts(results, ["colour-transfer", "preview"], True) if "mark contrast" in line
    )
    assert "none of bonsai and demo ran" in marks


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
