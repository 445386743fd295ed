"""``python -m dresg_addon evaluate`` end to end on a tiny synthetic scene, and its one-line errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dresg_addon import cli
from dresg_addon.evaluation import metrics
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.camera_io import write_cameras_json
from dresg_addon.scene.gaussians import SH_C0, GaussianScene
from dresg_addon.scene.io import write_scene
from dresg_addon.scene.orbit import orbit_cameras
from dresg_addon.util.imageio import write_image

REPO = Path(__file__).resolve().parents[1]


def textured_sphere(n=1500, seed=0) -> GaussianScene:
    """A sphere shell of small opaque splats with a stripe texture: visible, with depth, from every side."""
    rng = np.random.default_rng(seed)
    k = np.arange(n) + 0.5
    polar = np.arccos(1 - 2 * k / n)
    azimuth = math.pi * (1 + 5**0.5) * k
    points = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], 1)
    stripes = 0.5 + 0.4 * np.sin(3 * points[:, :1] + np.array([0.0, 2.0, 4.0]))  # [N, 3]
    return GaussianScene(
        means=points.astype(np.float32),
        log_scales=np.full((n, 3), math.log(0.06), np.float32),
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        opacity_logits=np.full(n, 4.0, np.float32),
        sh_dc=((stripes + rng.normal(0, 0.02, stripes.shape) - 0.5) / SH_C0).astype(np.float32),
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaluate")
    base = textured_sphere()
    stylized = base.copy()
    colours = np.clip(0.5 + SH_C0 * stylized.sh_dc, 0, 1)
    stylized.sh_dc = ((colours[:, [2, 0, 1]] ** 2 - 0.5) / SH_C0).astype(np.float32)  # recoloured
    write_scene(base, root / "base.ply")
    write_scene(stylized, root / "stylized.ply")
    yy, xx = np.mgrid[0:40, 0:56] / 8.0
    style = np.stack([0.5 + 0.5 * np.sin(xx), 0.5 + 0.5 * np.cos(yy), np.full_like(xx, 0.3)], -1)
    write_image(root / "style.png", style)
    log = [{"stage": "proposal", "seconds": 2.0, "peak_rss_mb": 700.0}, {"stage": 0, "seconds": 5.5}]
    (root / "log.jsonl").write_text("".join(json.dumps(line) + "\n" for line in log))
    return root


SIZE = ["--width", "40", "--height", "32"]


def evaluate(files, capsys, *extra, stylized="stylized.ply"):
    out = files / f"out_{len(list(files.glob('out_*')))}.json"
    args = ["evaluate", str(files / stylized), "--base", str(files / "base.ply"), "--style", str(files / "style.png")]
    code = cli.main([*args, *SIZE, "--json", str(out), *extra])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return json.loads(out.read_text()), captured.out


def assert_no_nan(value):
    json.dumps(value, allow_nan=False)


@pytest.mark.slow
def test_evaluate_end_to_end(files, capsys):
    report, table = evaluate(files, capsys, "--orbit", "6", "--log", str(files / "log.jsonl"), "--fps-repeats", "1")
    assert_no_nan(report)
    assert report["views"] == 6 and len(report["per_view"]) == 6
    assert [v["name"] for v in report["per_view"]] == [f"orbit_{i:03d}" for i in range(6)]
    for view in report["per_view"]:
        assert (view["width"], view["height"]) == (40, 32)
        assert view["sw_colors"] > 0 and view["sw_patches"] > 0
        # On the covered pixels only (as the quality bench): the recoloured sphere's SSIM may fall below 0.
        assert -1 <= view["ssim"] < 1 and 0 < view["structure"] < 1
        assert view["sw_patches_half"] > 0 and view["sw_patches_quarter"] > 0
        assert math.isfinite(view["texture_kept"]) and -1 <= view["texture_kept"] <= 1
        assert math.isfinite(view["shapes"]) and 0 < view["shapes"] <= 1
        assert -1 <= view["forms"] <= 1 and all(view[key] >= 0 for key in ("marks_fine", "marks_mid", "marks_coarse"))
        assert view["clip_s"] is None and view["dino_c"] is None
        assert view["alpha_coverage"] > 0.2
    mean = report["mean"]
    for key in ("ssim", "texture_kept", "shapes", "forms", "marks_mid"):
        assert mean[key] == pytest.approx(np.mean([v[key] for v in report["per_view"]]))
    assert mean["clip_s"] is None
    for label in ("stylized", "base"):
        short, long = report["consistency"][label]["short_term"], report["consistency"][label]["long_term"]
        assert short["gap"] == 1 and long["gap"] == 3
        assert len(short["pairs"]) == 5 and len(long["pairs"]) == 3
        assert short["rmse"] is not None and short["coverage"] > 0.1
        assert long["coverage"] < short["coverage"]  # opposite sides of a sphere share only the rim
    assert report["consistency"]["base"]["short_term"]["rmse"] < 0.1
    render = report["efficiency"]["render"]
    assert render["frames"] == 6 and render["fps"] > 0 and render["peak_rss_mb"] > 0
    log = report["efficiency"]["stylize_log"]
    assert log["optimisation_seconds"] == 5.5 and log["peak_rss_mb"] == 700.0 and log["records"] == 2
    assert report["efficiency"]["splats"] == 1500
    assert report["settings"]["depth_tolerance"] == metrics.DEPTH_TOLERANCE
    assert report["settings"]["style_size"] == [45, 32]  # 56x40 with its shorter side matched to 32
    assert report["settings"]["stroke_size"] == 1.5  # the standard preset's
    for label in ("texture kept", "shapes", "forms", "marks fine", "coarse"):
        assert label in table.splitlines()[0]
    assert "mean" in table and "short-term (gap 1)" in table and "FPS" in table and "stylize: 5.5 s" in table


@pytest.mark.slow
def test_evaluate_base_against_itself(files, capsys):
    report, _ = evaluate(files, capsys, "--orbit", "3", "--fps-repeats", "0", stylized="base.ply")
    assert report["efficiency"]["render"] is None and report["efficiency"]["stylize_log"] is None
    for view in report["per_view"]:
        assert view["ssim"] == pytest.approx(1.0, abs=1e-6)
        assert view["structure"] == pytest.approx(1.0, abs=1e-6)
        assert view["texture_kept"] == pytest.approx(1.0, abs=1e-5)
        assert view["shapes"] == pytest.approx(1.0, abs=1e-5) and view["forms"] == pytest.approx(1.0, abs=1e-5)
        assert [view[key] for key in ("marks_fine", "marks_mid", "marks_coarse")] == pytest.approx([0, 0, 0], abs=1e-6)
    assert report["consistency"]["stylized"] == report["consistency"]["base"]


@pytest.mark.slow
def test_evaluate_camera_file_order_and_empty_views(files, capsys, tmp_path):
    cameras = orbit_cameras(textured_sphere(), 3, width=40, height=32)
    # A camera looking away from the scene: an empty render that must give defined values.
    away = Camera(40, 32, 30.0, 30.0, 20.0, 16.0, look_at((0, 0, -5), (0, 0, -10)), "away.png")
    named = [Camera(40, 32, c.fx, c.fy, c.cx, c.cy, c.world_to_camera, f"img_{i}.png") for i, c in enumerate(cameras)]
    path = tmp_path / "cameras.json"
    write_cameras_json(path, [named[2], away, named[0]])
    report, table = evaluate(files, capsys, "--cameras", str(path), "--fps-repeats", "0")
    assert_no_nan(report)
    assert [v["name"] for v in report["per_view"]] == ["img_2.png", "away.png", "img_0.png"]
    empty = report["per_view"][1]
    assert empty["alpha_coverage"] == 0.0 and empty["ssim"] == pytest.approx(1.0)
    assert empty["texture_kept"] == 0.0 and empty["shapes"] == pytest.approx(1.0)  # both flat: nothing to keep
    assert empty["forms"] == pytest.approx(1.0) and empty["marks_fine"] == empty["marks_coarse"] == 0.0
    short = report["consistency"]["stylized"]["short_term"]
    assert [p["coverage"] for p in short["pairs"]] == [0.0, 0.0] and short["rmse"] is None
    assert "stylized -" in table


def test_evaluate_with_tiny_clip_and_dino(files, capsys, tmp_path):
    transformers = pytest.importorskip("transformers")
    small = {"hidden_size": 16, "intermediate_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2}
    clip = transformers.CLIPConfig(
        text_config={**small, "vocab_size": 64, "max_position_embeddings": 8, "bos_token_id": 0, "eos_token_id": 1},
        vision_config={**small, "image_size": 32, "patch_size": 8},
        projection_dim=8,
    )
    transformers.CLIPModel(clip).save_pretrained(tmp_path / "clip")
    transformers.ViTModel(
        transformers.ViTConfig(**small, image_size=32, patch_size=8), add_pooling_layer=False
    ).save_pretrained(tmp_path / "dino")
    report, table = evaluate(
        files,
        capsys,
        "--orbit",
        "2",
        "--fps-repeats",
        "0",
        "--clip",
        str(tmp_path / "clip"),
        "--dino",
        str(tmp_path / "dino"),
    )
    for view in report["per_view"]:
        assert -1 <= view["clip_s"] <= 1 and -1 <= view["dino_c"] <= 1
    assert report["mean"]["clip_s"] is not None and report["mean"]["dino_c"] is not None
    assert "CLIP-S" in table


def one_error_line(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--orbit", "0"], "--orbit 0"),
        (["--clip", "/nonexistent/clip"], "/nonexistent/clip: no such folder"),
        (["--log", "/nonexistent/log.jsonl"], "/nonexistent/log.jsonl: stylize log not found"),
        (["--depth-tolerance", "0"], "--depth-tolerance 0.0 must be a positive number"),
        (["--alpha-threshold", "1"], "--alpha-threshold 1.0 must be in [0, 1)"),
        (["--patch", "0"], "--patch 0 must be at least 1"),
        (["--color-samples", "0"], "--color-samples 0 must be at least 1"),
        (["--width", "5", "--height", "5", "--orbit", "2"], "smaller than a patch"),
        (["--cameras", "/nonexistent/cameras.json"], "no such file"),
    ],
)
def test_evaluate_errors(files, capsys, tmp_path, extra, message):
    args = [
        "evaluate",
        str(files / "stylized.ply"),
        "--base",
        str(files / "base.ply"),
        "--style",
        str(files / "style.png"),
    ]
    assert cli.main([*args, *extra, "--json", str(tmp_path / "out.json")]) == 2
    assert message in one_error_line(capsys)
    assert not (tmp_path / "out.json").exists()


def test_evaluate_missing_inputs(files, capsys, tmp_path):
    base = ["--base", str(files / "base.ply"), "--orbit", "2"]
    assert cli.main(["evaluate", str(files / "stylized.ply"), *base, "--style", str(tmp_path / "none.png")]) == 2
    assert "none.png" in one_error_line(capsys)
    assert cli.main(["evaluate", str(tmp_path / "none.ply"), *base, "--style", str(files / "style.png")]) == 2
    assert "none.ply" in one_error_line(capsys)
    out_dir = tmp_path / "folder"
    out_dir.mkdir()
    style = ["--style", str(files / "style.png")]
    assert cli.main(["evaluate", str(files / "stylized.ply"), *base, *style, "--json", str(out_dir)]) == 2
    assert "is a folder" in one_error_line(capsys)


def test_help_mentions_metric_defaults_and_cli_stays_light():
    help_text = cli.build_parser()._subparsers._group_actions[0].choices["evaluate"].format_help()
    assert f"default {metrics.DEPTH_TOLERANCE:g}" in help_text
    assert f"default {metrics.ALPHA_THRESHOLD:g}" in help_text
    # Building the parser (every command) must not import torch: `info` and `--help` stay instant.
    code = "import sys; from dresg_addon import cli; cli.build_parser(); print('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"
