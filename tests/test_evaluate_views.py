"""One novel-view evaluator: ``dresg evaluate``, the report and the quality bench give the same numbers."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import quality  # bench/, on pytest's pythonpath
import torch
import torch.nn.functional as F

from dresg_addon import cli
from dresg_addon.evaluation import report_measure
from dresg_addon.evaluation.stability import tiny_cameras, tiny_scene
from dresg_addon.evaluation.views import KEYS, MARK_KEYS, _mark_contrast, base_views, evaluate_views, painting_for_marks
from dresg_addon.scene.camera_io import write_cameras_json
from dresg_addon.scene.io import write_scene
from dresg_addon.util.errors import ConfigError
from dresg_addon.util.imageio import write_image

CASE = {"scene": "demo", "style": "demo", "row": "colour-transfer", "views": 4, "width": 56, "height": 40}


def test_evaluate_the_report_and_the_quality_bench_give_identical_numbers(tmp_path, monkeypatch, capsys):
    scene, train, novel, style = quality.load_case(CASE)
    stylized = quality.colour_transfer_scene(scene, train, style)
    bench = quality.run_case(CASE)  # the bench's own path: its cameras, painting and colour transfer

    # The report, its stylization replaced by the colour transfer (the evaluation is what is compared).
    def stylize_with_log(*_):
        return SimpleNamespace(scene=stylized, seconds=1.0, selection=SimpleNamespace(indices=[0])), [], []

    monkeypatch.setattr(report_measure, "stylize_with_log", stylize_with_log)
    inputs = report_measure.ReportInputs(scene, "demo", train, novel, None, [("demo", style)])
    options = report_measure.ReportOptions(quick=True, presets=("preview",), stage_counts=()).resolved()
    records, _ = report_measure.run_stylizations(inputs, options, tmp_path, say=lambda _: None)

    write_scene(scene, tmp_path / "base.ply")
    write_scene(stylized, tmp_path / "stylized.ply")
    write_image(tmp_path / "style.exr", style)  # float: the painting read back bit for bit
    write_cameras_json(tmp_path / "cameras.json", novel)
    args = ["evaluate", str(tmp_path / "stylized.ply"), "--base", str(tmp_path / "base.ply")]
    args += ["--style", str(tmp_path / "style.exr"), "--cameras", str(tmp_path / "cameras.json")]
    assert cli.main([*args, "--fps-repeats", "0", "--json", str(tmp_path / "out.json")]) == 0
    capsys.readouterr()
    command = json.loads((tmp_path / "out.json").read_text())["mean"]

    assert [records[0].metrics[key] for key in KEYS] == [bench[key] for key in KEYS]
    # The command reads the cameras back from cameras.json (camera-to-world, inverted again): a few ulps of float64
    # that reach the float32 renders on some CPUs and not others (a splat order can flip: pixels up to 1e-3 apart,
    # which the band-passes of mark contrast see most).
    loose = {key: 2e-4 for key in (*MARK_KEYS, "mark_elongation")}
    for key in KEYS:
        assert command[key] == pytest.approx(bench[key], rel=loose.get(key, 1e-5), abs=1e-7), key
    assert 0.0 < bench["ssim"] < 1.0 and bench["sw_patches_quarter"] > 0.0


def test_unstylized_scene_measures_as_its_own_base():
    base = tiny_scene(40)
    cameras = [c.resized(48, 32) for c in tiny_cameras()]
    style = np.random.default_rng(0).uniform(0, 1, (16, 16, 3)).astype(np.float32)
    views = base_views(base, cameras)
    unstylized = evaluate_views(base, views, style).mean
    assert list(unstylized) == list(KEYS)
    assert unstylized["ssim"] == pytest.approx(1.0) and unstylized["structure"] == pytest.approx(1.0)
    assert unstylized["texture_kept"] == pytest.approx(1.0, abs=1e-5) and unstylized["shapes"] == pytest.approx(1.0)
    assert unstylized["texture_kept_2x"] == pytest.approx(1.0, abs=1e-5)  # the 2x renders against themselves
    assert unstylized["forms"] == pytest.approx(1.0)
    assert [unstylized[key] for key in MARK_KEYS] == pytest.approx([0.0] * 3, abs=1e-6)  # no marks but the capture's
    assert 0.0 <= unstylized["short_rmse"] < 0.1  # the exact warp's resampling floor
    recoloured = replace(base, sh_dc=base.sh_dc[::-1].copy())
    m = evaluate_views(recoloured, views, style)
    assert m.mean["ssim"] < 1.0 and all(v is None or np.isfinite(v) for v in m.mean.values())
    assert -1.0 <= m.mean["texture_kept"] < 1.0 and 0.0 < m.mean["shapes"] < 1.0
    assert -1.0 <= m.mean["texture_kept_2x"] < 1.0 and -1.0 <= m.mean["forms"] < 1.0
    assert all(m.mean[key] > 0.0 for key in MARK_KEYS)
    assert [tuple(image.shape) for image in m.renders_2x] == [(3, 64, 96)] * 2
    assert m.style_size == (32, 32)  # the square painting's side to the cameras' shorter side
    with pytest.raises(ConfigError, match="smaller than a patch"):
        evaluate_views(base, views, style, patch=9)  # 32 px / 4 = 8 px at the coarsest scale
    for bad in (0.0, -1.0, float("nan"), float("inf"), True):
        with pytest.raises(ConfigError, match="stroke size"):
            evaluate_views(base, views, style, stroke_size=bad)


def test_mark_contrast_compares_with_the_painting_at_the_run_s_stroke_size():
    """The painting itself, painted onto a flat scene at Stroke Size 1: its own marks, 1 in every band."""
    painting = torch.rand(3, 40, 56, generator=torch.Generator().manual_seed(1))
    assert painting_for_marks(painting, 56, 40, 1.0) is painting
    assert tuple(painting_for_marks(painting, 56, 40, 1.5).shape) == (3, 60, 84)  # each side x 1.5, stretched
    grey = torch.full_like(painting, 0.5)
    covered = torch.ones(40, 56)
    base_2x = [F.interpolate(grey[None], scale_factor=2.0)[0]]
    painted = [painting]
    ones = _mark_contrast(painting, painted, [covered], base_2x, 1.0)
    assert ones.shape == (1, 3) and ones[0].tolist() == pytest.approx([1.0, 1.0, 1.0], abs=1e-5)
    # The same marks against the painting at Stroke Size 2, whose marks are twice as large: finer than its own.
    fine, _, coarse = _mark_contrast(painting, painted, [covered], base_2x, 2.0)[0].tolist()
    assert fine > 1.2 and coarse < 0.8
