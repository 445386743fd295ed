"""The ``render`` command: files, pixel values against ``render_scene``, orbit mode, and one-line errors."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dresg_addon.cli import main
from dresg_addon.commands._common import parse_background
from dresg_addon.commands.render import output_stems
from dresg_addon.raster import RasterSettings, render_scene
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.camera_io import load_cameras, write_cameras_json
from dresg_addon.scene.gaussians import GaussianScene
from dresg_addon.scene.io import read_scene, write_scene
from dresg_addon.scene.orbit import orbit_cameras
from dresg_addon.util.errors import ConfigError
from dresg_addon.util.imageio import read_image

REPO = Path(__file__).resolve().parents[1]


def small_scene(n=300, seed=0) -> GaussianScene:
    """A blob of splats around the origin with SH degree 1, so colours depend on the view."""
    rng = np.random.default_rng(seed)
    return GaussianScene(
        means=rng.normal(scale=0.5, size=(n, 3)).astype(np.float32),
        log_scales=rng.uniform(-3.0, -1.5, size=(n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacity_logits=rng.normal(1.0, 1.5, size=n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(scale=0.5, size=(n, 3, 3)).astype(np.float32),
    )


def camera(name, eye, target=(0.0, 0.0, 0.0), width=40, height=30) -> Camera:
    return Camera(width, height, 40.0, 40.0, width / 2, height / 2, look_at(eye, target), name)


@pytest.fixture
def inputs(tmp_path):
    """(scene.ply, cameras.json): one camera with a nested image name, one beside it, one looking away."""
    scene_path = tmp_path / "scene.ply"
    write_scene(small_scene(), scene_path)
    cameras_path = tmp_path / "cameras.json"
    write_cameras_json(
        cameras_path,
        [
            camera("views/front.JPG", (0.0, 0.0, -4.0)),
            camera("side", (4.0, -0.5, 0.0)),
            camera("away", (0.0, 0.0, -4.0), target=(0.0, 0.0, -8.0)),
        ],
    )
    return scene_path, cameras_path


def expected(scene_path, cam, **settings):
    out = render_scene(read_scene(scene_path), cam, RasterSettings(**settings))
    return out.rgb.numpy(), out.alpha.numpy(), out.depth.numpy()


def as_8bit(values):
    return np.round(np.clip(values, 0.0, 1.0) * 255.0)


def test_exr_and_png_hold_render_scene_values(inputs, tmp_path, capsys):
    scene_path, cameras_path = inputs
    exr_dir, png_dir = tmp_path / "exr", tmp_path / "png"
    base = ["render", str(scene_path), "--cameras", str(cameras_path), "--alpha", "--out"]
    assert main(base + [str(exr_dir), "--format", "exr", "--depth"]) == 0
    captured = capsys.readouterr()
    lines = captured.out.strip().splitlines()
    assert len(lines) == 4 and lines[0].startswith("views_front.exr: 40x30, ") and "pairs" in lines[0]
    assert lines[-1].startswith("rendered 3 views of 300 splats (SH degree 1)") and "1 saw nothing" in lines[-1]
    assert captured.err.strip().splitlines() == [
        "warning: away: the camera sees nothing of the scene (alpha is 0 everywhere)"
    ]
    assert main(base + [str(png_dir), "--format", "png"]) == 0
    assert sorted(p.name for p in png_dir.iterdir()) == sorted(
        f"{stem}{suffix}.png" for stem in ("views_front", "side", "away") for suffix in ("", "_alpha")
    )

    for cam in load_cameras(cameras_path):
        stem = output_stems([cam])[0]
        rgb, alpha, depth = expected(scene_path, cam)
        exr = read_image(exr_dir / f"{stem}.exr")
        np.testing.assert_array_equal(exr, rgb)
        np.testing.assert_array_equal(read_image(exr_dir / f"{stem}_alpha.exr")[..., 0], alpha)
        np.testing.assert_array_equal(read_image(exr_dir / f"{stem}_depth.exr")[..., 0], depth)
        png = read_image(png_dir / f"{stem}.png")
        assert png.shape == (30, 40, 3)
        np.testing.assert_array_equal(np.round(png * 255.0), as_8bit(exr))
        np.testing.assert_array_equal(
            np.round(read_image(png_dir / f"{stem}_alpha.png")[..., 0] * 255.0), as_8bit(alpha)
        )

    front = load_cameras(cameras_path)[0]
    _, front_alpha, front_depth = expected(scene_path, front)
    assert front_alpha.max() > 0.5 and front_depth[front_alpha > 0.5].min() > 2.0  # the blob is 4 units away
    # Colours are view-dependent: dropping the SH rest changes the image.
    dc_only = tmp_path / "dc.ply"
    write_scene(replace(read_scene(scene_path), sh_rest=None), dc_only)
    assert np.abs(expected(dc_only, front)[0] - read_image(exr_dir / "views_front.exr")).max() > 1e-3


def test_background_near_and_scale(inputs, tmp_path):
    scene_path, cameras_path = inputs
    out = tmp_path / "out"
    args = ["render", str(scene_path), "--cameras", str(cameras_path), "--out", str(out), "--format", "exr"]
    assert main(args + ["--background", "0.2,0.4,0.6", "--scale", "0.5", "--near", "3.5"]) == 0
    cams = load_cameras(cameras_path, factor=2.0)
    for cam, stem in zip(cams, output_stems(cams)):
        image = read_image(out / f"{stem}.exr")
        assert image.shape == (15, 20, 3)
        np.testing.assert_array_equal(image, expected(scene_path, cam, background=(0.2, 0.4, 0.6), near=3.5)[0])
    np.testing.assert_array_equal(
        read_image(out / "away.exr"), np.broadcast_to(np.float32([0.2, 0.4, 0.6]), (15, 20, 3))
    )
    # The near plane at 3.5 cuts the front half of the blob out of the front view.
    full = expected(scene_path, cams[0], background=(0.2, 0.4, 0.6))[0]
    assert np.abs(read_image(out / "views_front.exr") - full).max() > 1e-2


def test_orbit_mode(tmp_path, capsys):
    scene_path = tmp_path / "scene.ply"
    write_scene(small_scene(), scene_path)
    out = tmp_path / "orbit"
    args = ["render", str(scene_path), "--orbit", "3", "--width", "32", "--height", "24", "--format", "exr"]
    assert main(args + ["--out", str(out), "--up", "0,1,0"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["orbit_000.exr", "orbit_001.exr", "orbit_002.exr"]
    scene = read_scene(scene_path)
    for cam in orbit_cameras(scene, 3, width=32, height=24, up=(0.0, 1.0, 0.0)):
        image = read_image(out / f"{cam.name}.exr")
        np.testing.assert_array_equal(image, render_scene(scene, cam).rgb.numpy())
        assert image.max() > 0.1  # the orbit frames the scene
    assert len(capsys.readouterr().out.strip().splitlines()) == 4


def test_drop_invalid(tmp_path, capsys):
    scene_path = tmp_path / "bad.ply"
    write_scene(small_scene(50), scene_path)
    # The writer refuses NaN, so put one into splat 7's y by hand (binary float32 rows).
    data = bytearray(scene_path.read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    names = [line.split()[-1] for line in data[:body].decode().splitlines() if line.startswith("property")]
    offset = body + 4 * (7 * len(names) + names.index("y"))
    data[offset : offset + 4] = np.float32(np.nan).tobytes()
    scene_path.write_bytes(bytes(data))
    args = ["render", str(scene_path), "--orbit", "1", "--width", "16", "--out", str(tmp_path / "out")]
    assert main(args) == 2
    assert "1 of 50 splats have non-finite values" in capsys.readouterr().err
    assert main(args + ["--drop-invalid"]) == 0
    assert "dropped 1 splats" in capsys.readouterr().err
    assert read_image(tmp_path / "out" / "orbit_000.png").shape == (11, 16, 3)


def test_output_stems():
    cams = [camera(name, (0.0, 0.0, -4.0)) for name in ("a/b\\c.png", "c", "C.exr", "", "frame.0001", "..", "x:y?")]
    cams.append(camera("c", (0.0, 0.0, -4.0)))
    assert output_stems(cams) == ["a_b_c", "c", "C_2", "view_003", "frame.0001", "view_005", "x_y_", "c_3"]


def test_parse_background():
    assert parse_background("0.1, 0.2,0.3") == (0.1, 0.2, 0.3)
    assert parse_background("1") == (1.0, 1.0, 1.0)
    for bad in ("1,2", "a,b,c", "1,nan,1", "-1,0,0", ""):
        with pytest.raises(ConfigError, match="--background"):
            parse_background(bad)


BAD_OPTIONS = {
    "missing scene": (["MISSING", "--orbit", "2"], "file not found"),
    "missing cameras": (["SCENE", "--cameras", "nowhere.json"], "no such file"),
    "malformed cameras": (["SCENE", "--cameras", "BADJSON"], "malformed JSON"),
    "bad background": (["SCENE", "--orbit", "2", "--background", "red"], "--background 'red'"),
    "bad up": (["SCENE", "--orbit", "2", "--up", "0,0"], "--up '0,0'"),
    "scale and width": (["SCENE", "--orbit", "2", "--scale", "0.5", "--width", "10"], "--scale or --width"),
    "zero scale": (["SCENE", "--orbit", "2", "--scale", "0"], "--scale 0.0"),
    "no orbit cameras": (["SCENE", "--orbit", "0"], "--orbit 0"),
    "negative near": (["SCENE", "--orbit", "2", "--near", "-1"], "--near -1.0"),
    "out is a file": (["SCENE", "--orbit", "2", "--out", "SCENE"], "is not a folder"),
}


@pytest.mark.parametrize("case", sorted(BAD_OPTIONS))
def test_errors_are_one_line_with_exit_2(inputs, tmp_path, capsys, case):
    scene_path, _ = inputs
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("[{", encoding="utf-8")
    words, message = BAD_OPTIONS[case]
    paths = {"SCENE": str(scene_path), "MISSING": str(tmp_path / "missing.ply"), "BADJSON": str(bad_json)}
    argv = ["render"] + [paths.get(word, word) for word in words]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], captured.err
    assert captured.out == ""
    assert not (tmp_path / "out").exists()


def test_subprocess_error_and_help(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    command = [sys.executable, "-m", "dresg_addon", "render", str(tmp_path / "missing.ply"), "--orbit", "2"]
    done = subprocess.run(command + ["--out", str(tmp_path)], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [f"error: {tmp_path / 'missing.ply'}: file not found"]
    assert done.stdout == ""
    text = subprocess.run(
        [sys.executable, "-m", "dresg_addon", "render", "--help"], capture_output=True, text=True, env=env, check=True
    ).stdout
    options = ["--cameras", "--orbit", "--out", "--format", "--near", "--background", "--depth", "--alpha"]
    options += ["--width", "--height", "--scale", "--drop-invalid", "--up", "--device"]
    assert all(option in text for option in options)
