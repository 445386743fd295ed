"""The ``stylize``, ``select-views`` and ``demo`` commands end to end on tiny scene files."""

from __future__ import annotations

import hashlib
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dresg_addon import cli
from dresg_addon.method.config import PLANS, PRESETS
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.camera_io import write_cameras_json
from dresg_addon.scene.gaussians import SH_C0, GaussianScene
from dresg_addon.scene.io import read_scene, write_scene
from dresg_addon.util.imageio import read_image, write_image

REPO = Path(__file__).resolve().parents[1]
# The paper's schedule with colours only, cut down to one stage (and its post stage) at 32x24; it renders the 64x48
# cameras at full size.
TINY_ARGS = ["--preset", "cpu", "--stages", "1", "--proposal-size", "32x24"]


def _scene(n: int = 300) -> GaussianScene:
    """Warm splats on a sphere at the origin, with degree-1 SH bands."""
    rng = np.random.default_rng(0)
    means = rng.normal(size=(n, 3))
    means = 0.5 * means / np.linalg.norm(means, axis=1, keepdims=True)
    quats = rng.normal(size=(n, 4))
    colors = rng.uniform([0.6, 0.25, 0.05], [0.95, 0.55, 0.3], (n, 3))
    return GaussianScene(
        means=means.astype(np.float32),
        log_scales=np.full((n, 3), math.log(0.07), np.float32),
        quats=(quats / np.linalg.norm(quats, axis=1, keepdims=True)).astype(np.float32),
        opacity_logits=np.full(n, 2.0, np.float32),
        sh_dc=((colors - 0.5) / SH_C0).astype(np.float32),
        sh_rest=(0.05 * rng.normal(size=(n, 3, 3))).astype(np.float32),
    )


def _camera(eye, name: str, target=(0.0, 0.0, 0.0)) -> Camera:
    return Camera(64, 48, 50.0, 50.0, 32.0, 24.0, look_at(eye, target), name)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """scene.ply, cameras.json (3 ring cameras and one looking away) and a 16-bit RGBA style PNG."""
    folder = tmp_path_factory.mktemp("cli")
    write_scene(_scene(), folder / "scene.ply")
    ring = [_camera([2 * math.sin(a), -0.5, -2 * math.cos(a)], f"ring_{k}") for k, a in enumerate((0.0, 2.1, 4.2))]
    write_cameras_json(folder / "cameras.json", ring)
    write_cameras_json(folder / "with_away.json", [*ring, _camera([0, 0, -2.0], "away", target=(0, 0, -5.0))])
    rng = np.random.default_rng(1)
    style = np.concatenate([rng.uniform(0, 1, (24, 32, 3)) * [0.3, 0.4, 1.0], np.full((24, 32, 1), 0.8)], 2)
    write_image(folder / "style.png", style.astype(np.float32), bits=16)
    return {
        "scene": folder / "scene.ply",
        "cameras": folder / "cameras.json",
        "with_away": folder / "with_away.json",
        "style": folder / "style.png",
    }


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _stylize_args(files, out: Path, *extra: str) -> list[str]:
    return [
        "stylize",
        str(files["scene"]),
        "--cameras",
        str(files["cameras"]),
        "--style",
        str(files["style"]),
        "--out",
        str(out),
        *TINY_ARGS,
        *extra,
    ]


def test_stylize_writes_the_scene_log_views_and_checkpoint_and_resumes(files, tmp_path, capsys):
    before = {name: _digest(path) for name, path in files.items()}
    out, views = tmp_path / "out.ply", tmp_path / "views"
    assert cli.main(_stylize_args(files, out, "--save-views", str(views))) == 0
    captured = capsys.readouterr()
    assert f"wrote {out}" in captured.out and "3 active views" in captured.out
    assert "Stage 1/1 | colour solve round" in captured.err and "Final colours | colour solve round" in captured.err
    assert "fit RMSE" in captured.err and "100% done in" in captured.err
    assert "colour fit: bounded least squares over the 3 active views" in captured.err

    scene, result = _scene(), read_scene(out)
    assert len(result) == len(scene)
    np.testing.assert_allclose(result.means, scene.means)
    assert not np.allclose(result.sh_dc, scene.sh_dc)
    assert result.sh_rest is not None and not result.sh_rest.any()  # the default: SH bands zeroed

    log = [json.loads(line) for line in (tmp_path / "out.log.jsonl").read_text().splitlines()]
    assert [e["stage"] for e in log] == [1, "post"]
    assert (tmp_path / "out.checkpoint" / "checkpoint.pt").is_file()
    images = sorted(p.name for p in (views / "stage01").iterdir())
    assert len(images) == 12 and "ring_0_residual.png" in images
    assert read_image(views / "stage01" / "ring_0_render.png").shape == (48, 64, 3)
    assert {name: _digest(path) for name, path in files.items()} == before  # inputs untouched

    # The same command again resumes from the default checkpoint and writes the same scene.
    first = out.read_bytes()
    assert cli.main(_stylize_args(files, out, "--save-views", str(views))) == 0
    assert "resuming after stage 1" in capsys.readouterr().err
    assert out.read_bytes() == first


def test_geometry_on_cpu_says_what_it_costs(files, tmp_path, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("the note is for CPU runs")
    assert cli.main(_stylize_args(files, tmp_path / "geo.ply", "--geometry")) == 0
    err = capsys.readouterr().err
    assert "note: geometry offsets are on: each of the 80 fit steps renders every active view" in err
    assert cli.main(_stylize_args(files, tmp_path / "colour.ply", "--no-geometry")) == 0
    assert "geometry offsets are on" not in capsys.readouterr().err


@pytest.mark.slow
def test_stylize_as_a_module_with_settings_and_quiet(files, tmp_path):
    out = tmp_path / "switches.ply"
    args = _stylize_args(files, out, "--views", "0,2", "--stages", "2", "--strength", "0")
    args += ["--sh-rest", "keep", "--log", str(tmp_path / "custom.jsonl"), "--quiet"]
    done = subprocess.run(
        [sys.executable, "-m", "dresg_addon", *args], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert "2 active views" in done.stdout
    assert "stage 1/1" not in done.stderr  # --quiet prints only the summary
    result = read_scene(out)
    np.testing.assert_array_equal(result.sh_rest, _scene().sh_rest)
    np.testing.assert_array_equal(result.sh_dc, _scene().sh_dc)  # --strength 0: the scene's own colours
    log = [json.loads(line) for line in (tmp_path / "custom.jsonl").read_text().splitlines()]
    assert log[0]["views"] == 2 and all("style_distance" in e for e in log if e["stage"] != "post")


def test_select_views_prints_a_table_and_json(files, capsys):
    assert cli.main(["select-views", str(files["scene"]), "--cameras", str(files["with_away"])]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["pick", "index", "camera", "own", "total"]
    picks = [line.split() for line in lines[1:] if " of 4 cameras" not in line and line.split()[0].isdigit()]
    assert [int(p[0]) for p in picks] == list(range(1, len(picks) + 1))
    assert {p[2] for p in picks} <= {"ring_0", "ring_1", "ring_2"}
    totals = [float(p[4]) for p in picks]
    assert totals == sorted(totals)
    assert any(line.startswith(f"{len(picks)} of 4 cameras; stopped:") for line in lines)
    assert lines[-1] == "cameras that see nothing: away"

    assert cli.main(["select-views", str(files["scene"]), "--cameras", str(files["with_away"]), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert [v["name"] for v in data["views"]] == [p[2] for p in picks]
    assert data["blind"] == ["away"] and data["stop_reason"]
    assert all(0 < v["own_coverage"] <= 1 and v["coverage_after"] <= 1 + 1e-9 for v in data["views"])

    assert cli.main(["select-views", str(files["scene"]), "--orbit", "4", "--max-views", "1", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert len(data["views"]) == 1 and data["stop_reason"] == "view limit reached"


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"--style": "missing.png"}, "missing.png"),
        ({"--views": "a,b"}, "--views must be comma-separated"),
        ({"--views": "0,9"}, "do not index the 3 cameras"),
        ({"--proposal-size": "big"}, "--proposal-size must look like"),
        ({"--proposal-size": "4x4"}, "at least 8x8"),
        ({"--proposal": "sd15"}, "needs a local model path"),
        ({"--proposal": "sd15", "--model": "x", "--proposal-size": "36x28"}, "multiple of 8"),
        ({"--background": "2,0,0"}, "--background"),
        ({"--strength": "2"}, "strength must be in [0, 1]"),
        ({"--stroke-size": "0.1"}, "stroke_size must be in [0.25, 8]"),
        ({"--paint-scene": "-0.5"}, "scene_weight must be in [0, 1]"),
    ],
)
def test_stylize_errors_are_one_line_with_exit_code_2(files, tmp_path, capsys, change, message):
    out = tmp_path / "never.ply"
    args = _stylize_args(files, out)
    for flag, value in change.items():
        value = str(tmp_path / value) if flag == "--style" else value
        if flag in args:
            args[args.index(flag) + 1] = value
        else:
            args += [flag, value]
    assert cli.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err
    assert not out.exists()


def test_select_views_with_cameras_that_see_nothing_exits_2(files, tmp_path, capsys):
    away = tmp_path / "away.json"
    write_cameras_json(away, [_camera([0, 0, -2.0], "away", target=(0, 0, -5.0))])
    assert cli.main(["select-views", str(files["scene"]), "--cameras", str(away)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none of the 1 cameras" in err[0]


def test_demo_command_writes_its_assets_and_before_after_images(tmp_path, monkeypatch, capsys):
    """The demo's own scene, cameras and style with a tiny schedule and small images (a full demo takes ~45 s)."""
    import dresg_addon.scene.demo as demo

    real_cameras = demo.demo_cameras
    monkeypatch.setattr(
        demo, "demo_cameras", lambda scene, n, **kw: real_cameras(scene, n=n, width=64, height=48, **kw)
    )
    monkeypatch.setitem(PRESETS, "preview", PRESETS["preview"].with_(stages=1, proposal_width=32, proposal_height=24))
    monkeypatch.setitem(PLANS, "preview", PLANS["preview"].with_(updates_per_stage=2))
    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out), "--views", "2"]) == 0
    assert "before_after.png" in capsys.readouterr().out
    for name in ("scene.ply", "cameras.json", "style.png", "stylized.ply", "stylize.log.jsonl"):
        assert (out / name).is_file(), name
    scene, stylized = read_scene(out / "scene.ply"), read_scene(out / "stylized.ply")
    assert len(scene) == len(stylized) and not np.array_equal(scene.sh_dc, stylized.sh_dc)
    before = read_image(out / "views" / "orbit_000_before.png")
    after = read_image(out / "views" / "orbit_000_after.png")
    assert before.shape == after.shape == (48, 64, 3) and np.abs(before - after).mean() > 0.01
    grid = read_image(out / "before_after.png")
    assert grid.shape == (2 * 48, 4 * 64, 3)  # two novel views: before | colour transfer | after | style
    assert np.abs(grid[:, :64] - grid[:, 64:128]).mean() > 0.01
    assert np.abs(grid[:, :64] - grid[:, 128:192]).mean() > 0.01


def test_stylize_a_selection_by_box_or_mask_file_keeps_every_other_splat(files, tmp_path, capsys):
    """Issue 18: --box and --mask stylize a selection; the other splats are written back bit-identical."""
    scene = read_scene(files["scene"])
    inside = scene.means[:, 0] > 0.0
    by_box = tmp_path / "box.ply"
    assert cli.main([*_stylize_args(files, by_box), "--box", "0,-1,-1,1,1,1", "--quiet"]) == 0
    boxed = read_scene(by_box)
    np.testing.assert_array_equal(boxed.sh_dc[~inside], scene.sh_dc[~inside])
    np.testing.assert_array_equal(boxed.sh_rest[~inside], scene.sh_rest[~inside])
    assert (np.abs(boxed.sh_dc[inside] - scene.sh_dc[inside]).max(1) > 1e-4).mean() > 0.5

    indices = tmp_path / "selection.txt"
    indices.write_text(" ".join(map(str, np.flatnonzero(inside))))
    masked = tmp_path / "mask.ply"
    assert cli.main([*_stylize_args(files, masked), "--mask", str(indices), "--quiet"]) == 0
    np.testing.assert_array_equal(read_scene(masked).sh_dc, boxed.sh_dc)
    np.save(tmp_path / "selection.npy", inside)
    assert cli.main([*_stylize_args(files, masked), "--mask", str(tmp_path / "selection.npy"), "--quiet"]) == 0
    np.testing.assert_array_equal(read_scene(masked).sh_dc, boxed.sh_dc)
    capsys.readouterr()

    for extra, message in (
        (["--box", "5,5,5,6,6,6"], "no splat centre lies inside it"),
        (["--box", "1,2,3"], "--box must be six numbers"),
        (["--mask", str(tmp_path / "missing.txt")], "missing.txt: cannot read a selection"),
        (["--mask", str(tmp_path / "selection.npy"), "--geometry"], "needs geometry frozen"),
    ):
        assert cli.main([*_stylize_args(files, tmp_path / "never.ply"), *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err


def test_the_cpu_note_of_a_gpu_backend_is_the_registrys_estimate(files, tmp_path, capsys):
    """Issue 29: the CLI prints the registry's slow_note (the operator reports the same function's line)."""
    from dresg_addon.commands.stylize import config_from_args
    from dresg_addon.method.backends import slow_note

    model = tmp_path / "not-a-model"
    model.mkdir()
    args = _stylize_args(files, tmp_path / "never.ply", "--proposal", "sd15", "--model", str(model), "--device", "cpu")
    assert cli.main(args) != 0  # the folder holds no model: the loader says so after the note
    note = slow_note(config_from_args(cli.build_parser().parse_args(args)), "cpu")
    assert note.startswith("sd15 on this CPU takes about ") and f"note: {note}\n" in capsys.readouterr().err


@pytest.mark.parametrize(
    "flag", ["--updates", "--fit-steps", "--post-steps", "--solve-anchor", "--guide-weight", "--early-stop"]
)
def test_the_method_s_internals_are_not_command_line_settings(flag, capsys):
    with pytest.raises(SystemExit):
        cli.main(["stylize", "scene.ply", "--style", "s.png", "--out", "o.ply", flag, "1"])
    assert f"unrecognized arguments: {flag}" in capsys.readouterr().err
