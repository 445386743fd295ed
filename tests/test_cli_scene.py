"""The ``info`` and ``convert`` commands, through ``dresg_addon.cli.main`` and once as a subprocess."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dresg_addon.cli import main
from dresg_addon.scene.gaussians import GaussianScene
from dresg_addon.scene.io import SceneFormat, read_scene, read_scene_detailed, write_scene

REPO = Path(__file__).resolve().parents[1]


def scene(n=500, degree=1, seed=0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    return GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=rng.uniform(-5, -2, size=(n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacity_logits=rng.normal(scale=2, size=n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(scale=0.2, size=(n, k, 3)).astype(np.float32) if k else None,
        normals=np.zeros((n, 3), np.float32),
    )


@pytest.fixture
def ply(tmp_path) -> Path:
    path = tmp_path / "scene.ply"
    write_scene(scene(), path)
    return path


def one_error_line(captured) -> str:
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert "Traceback" not in captured.err
    return lines[0]


def test_info_reports_the_statistics(ply, capsys):
    assert main(["info", str(ply)]) == 0
    out = capsys.readouterr().out
    s = read_scene(ply)
    assert "graphdeco PLY" in out
    assert "500" in out and "SH degree:       1" in out
    low, high = s.bounds()
    assert f"{low[0]:.4g}" in out and f"{high[2]:.4g}" in out
    robust_low, _ = s.bounds(0.01)
    assert f"{robust_low[1]:.4g}" in out
    scales = np.exp(s.log_scales.astype(np.float64))
    assert f"min {scales.min():.4g}" in out and f"max {scales.max():.4g}" in out


def test_info_json_matches_numpy(ply, capsys):
    assert main(["info", str(ply), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    s = read_scene(ply)
    assert summary["splats"] == 500 and summary["sh_degree"] == 1 and summary["format"] == "graphdeco PLY"
    assert summary["normals"] is True and summary["extras"] == []
    np.testing.assert_allclose(summary["bounds_min"], s.means.min(0))
    np.testing.assert_allclose(summary["robust_bounds_max"], np.quantile(s.means, 0.99, axis=0))
    scales = np.exp(s.log_scales.astype(np.float64))
    for p in (1, 50, 99):  # between the order statistics around the percentile
        low, high = (np.percentile(scales, p, method=m) for m in ("lower", "higher"))
        assert low * (1 - 1e-6) <= summary["scale_percentiles"][str(p)] <= high * (1 + 1e-6)
    assert summary["scale_percentiles"]["0"] == pytest.approx(scales.min(), rel=1e-6)
    np.testing.assert_allclose(summary["opacity_mean"], (1 / (1 + np.exp(-s.opacity_logits.astype(np.float64)))).mean())
    assert summary["file_bytes"] == ply.stat().st_size


def test_info_on_real_files(shared_data, capsys):
    assert main(["info", str(shared_data("scenes/bonsai-7k-mini.compressed.ply")), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["format"] == SceneFormat.COMPRESSED_PLY.value and summary["splats"] == 272956
    assert main(["info", str(shared_data("scenes/graphdeco_it7000_sh3.ply"))]) == 0
    assert "SH degree:       3" in capsys.readouterr().out


def test_info_non_finite_and_drop_invalid(tmp_path, capsys):
    path = tmp_path / "bad.ply"
    s = scene()
    write_scene(s, path)
    data = bytearray(path.read_bytes())
    # Splat 4's x (first float of its 26-float degree-1 record with normals) becomes NaN.
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    record = (3 + 3 + 3 + 9 + 1 + 3 + 4) * 4
    data[header_end + 4 * record : header_end + 4 * record + 4] = np.float32(np.nan).tobytes()
    path.write_bytes(bytes(data))
    assert main(["info", str(path)]) == 2
    line = one_error_line(capsys.readouterr())
    assert str(path) in line and "1 of 500 splats have non-finite values" in line
    assert main(["info", str(path), "--drop-invalid"]) == 0
    captured = capsys.readouterr()
    assert "dropped 1 splats" in captured.err and "499" in captured.out


def test_info_extreme_values_stay_finite(tmp_path, capsys):
    s = scene(n=50, degree=0)
    s.log_scales[0] = 100.0  # exp overflows float32
    s.opacity_logits[:2] = [-1000.0, 1000.0]
    write_scene(s, tmp_path / "x.ply")
    assert main(["info", str(tmp_path / "x.ply"), "--json"]) == 0

    def refuse(constant):
        raise AssertionError(f"non-finite number in the JSON: {constant}")

    summary = json.loads(capsys.readouterr().out, parse_constant=refuse)
    assert summary["scale_percentiles"]["100"] > 1e40 and summary["opacity_percentiles"]["0"] == 0.0
    assert main(["convert", str(tmp_path / "x.ply"), str(tmp_path / "x.splat")]) == 0
    back = read_scene(tmp_path / "x.splat")
    assert np.isfinite(back.log_scales).all() and back.opacities[0] < 1e-5 and back.opacities[1] > 1 - 1e-5


def test_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing.ply")]) == 2
    assert "file not found" in one_error_line(capsys.readouterr())
    (tmp_path / "empty.splat").write_bytes(b"")
    assert main(["info", str(tmp_path / "empty.splat")]) == 2
    assert "empty file" in one_error_line(capsys.readouterr())
    (tmp_path / "cut.splat").write_bytes(b"\0" * 40)
    assert main(["convert", str(tmp_path / "cut.splat"), str(tmp_path / "out.ply")]) == 2
    assert "truncated data" in one_error_line(capsys.readouterr())
    assert not (tmp_path / "out.ply").exists()


@pytest.mark.parametrize("suffix", [".splat", ".compressed.ply", ".ply"])
def test_convert_formats(ply, tmp_path, capsys, suffix):
    out = tmp_path / f"out{suffix}"
    assert main(["convert", str(ply), str(out)]) == 0
    captured = capsys.readouterr()
    assert f"wrote {out}" in captured.out and "500 splats" in captured.out
    result = read_scene_detailed(out)
    assert len(result.scene) == 500
    if suffix == ".splat":
        assert result.format is SceneFormat.SPLAT and result.scene.sh_degree == 0
        assert "SH degree 1 -> 0" in captured.err
    elif suffix == ".compressed.ply":
        assert result.format is SceneFormat.COMPRESSED_PLY and result.scene.sh_degree == 1
        assert "Morton order" in captured.err
    else:
        assert out.read_bytes() == ply.read_bytes() and captured.err == ""


def test_convert_back_and_forth_keeps_positions(ply, tmp_path):
    assert main(["convert", str(ply), str(tmp_path / "a.splat")]) == 0
    assert main(["convert", str(tmp_path / "a.splat"), str(tmp_path / "b.ply")]) == 0
    back = read_scene(tmp_path / "b.ply")
    np.testing.assert_array_equal(back.means, read_scene(ply).means)
    assert back.normals is None and back.sh_degree == 0


def test_convert_in_place_and_over_another_file(ply, tmp_path):
    other = tmp_path / "other.ply"
    write_scene(scene(n=3, degree=0, seed=5), other)
    before = ply.read_bytes()
    assert main(["convert", str(ply), str(other)]) == 0
    assert ply.read_bytes() == before and other.read_bytes() == before
    assert main(["convert", str(ply), str(ply)]) == 0
    assert ply.read_bytes() == before


def test_convert_bad_output_extension_fails_before_reading(tmp_path, capsys):
    assert main(["convert", str(tmp_path / "missing.ply"), str(tmp_path / "out.obj")]) == 2
    assert "unknown output extension '.obj'" in one_error_line(capsys.readouterr())


@pytest.mark.parametrize(
    ("command", "options"),
    [("info", ["--drop-invalid", "--json", "SCENE"]), ("convert", ["--drop-invalid", "IN", "OUT"])],
)
def test_help_explains_every_option(capsys, command, options):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for option in options:
        assert option in out
    assert "non-finite" in out


def python_m(args: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    command = [sys.executable, "-m", "dresg_addon", *args]
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)


def test_python_m_info_subprocess(ply):
    done = python_m(["info", str(ply)])
    assert done.returncode == 0, done.stderr
    assert "500" in done.stdout and "graphdeco PLY" in done.stdout
    done = python_m(["info", str(ply.with_name("nope.ply"))])
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "file not found" in done.stderr
