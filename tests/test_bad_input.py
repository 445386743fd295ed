"""Named regressions from the bad-input fuzzer (issue 11): each case once crashed with a traceback, blocked
forever or read gigabytes; now it is a one-line error of the project's own type, through the CLI too."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from messages import names
from test_cameras import colmap_images, write_colmap_binary
from test_io import graphdeco_columns, random_scene, write_test_ply

from dresg_addon import cli
from dresg_addon.scene.camera_io import MAX_IMAGE_SIDE, load_cameras, read_cameras_json
from dresg_addon.scene.io import read_scene
from dresg_addon.util.errors import CameraError, ImageError, SceneFormatError
from dresg_addon.util.imageio import read_rgb


def _one_line_error(capsys, args) -> str:
    assert cli.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


# --- numbers Python cannot hold -----------------------------------------------------------------------


def test_a_ply_element_count_of_thousands_of_digits_is_a_clean_error(tmp_path, capsys):
    good = write_test_ply(tmp_path / "good.ply", graphdeco_columns(random_scene(n=4, degree=0)))
    data = good.read_bytes().replace(b"element vertex 4", b"element vertex " + b"9" * 5000, 1)
    (tmp_path / "huge.ply").write_bytes(data)
    with pytest.raises(SceneFormatError) as error:
        read_scene(tmp_path / "huge.ply")
    names(error, "huge.ply", "5000")  # the count's length
    assert len(str(error.value)) < 300  # the line is quoted shortened, not 5000 digits long
    assert "huge.ply" in _one_line_error(capsys, ["info", str(tmp_path / "huge.ply")])


def _camera_entry(**changes) -> dict:
    entry = {
        "id": 0,
        "img_name": "a",
        "width": 64,
        "height": 48,
        "position": [0.0, 0.0, -2.0],
        "rotation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "fx": 50.0,
        "fy": 50.0,
    }
    return {**entry, **changes}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[{"width": ' + "9" * 4301 + "}]", "malformed JSON"),  # Python's int conversion limit
        ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ],
)
def test_json_python_cannot_parse_is_a_clean_error(tmp_path, text, message):
    path = tmp_path / "cameras.json"
    path.write_text(text)
    with pytest.raises(CameraError, match=message):
        read_cameras_json(path)


@pytest.mark.parametrize("key", ["width", "height", "cx", "cy", "fx", "fy", "position", "rotation"])
def test_a_400_digit_integer_in_a_camera_is_a_clean_error(tmp_path, key):
    huge = 10**400
    value = [huge, 0, 0] if key == "position" else [[huge, 0, 0], [0, 1, 0], [0, 0, 1]] if key == "rotation" else huge
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([_camera_entry(**{key: value})]))
    with pytest.raises(CameraError, match="camera 0"):
        read_cameras_json(path)


# --- a PLY with two vertex elements -------------------------------------------------------------------


def test_duplicate_vertex_elements_are_refused(tmp_path):
    good = write_test_ply(tmp_path / "good.ply", graphdeco_columns(random_scene(n=4, degree=0)))
    header, body = good.read_bytes().split(b"end_header\n", 1)
    lines = header.split(b"\n")
    vertex = [i for i, line in enumerate(lines) if line.startswith(b"element vertex")][0]
    block = lines[vertex : len(lines) - 1]  # the vertex element and its properties
    doubled = b"\n".join(lines[:-1] + [b"element vertex 2", *block[1:], b"end_header"]) + b"\n"
    (tmp_path / "twice.ply").write_bytes(doubled + body + body[: len(body) // 2])
    with pytest.raises(SceneFormatError, match="duplicate element 'vertex'"):
        read_scene(tmp_path / "twice.ply")


# --- absurd camera sizes --------------------------------------------------------------------------------


@pytest.mark.parametrize("width", [1e300, 10**12, MAX_IMAGE_SIDE + 1, 20000])
def test_absurd_camera_sizes_are_refused_on_read(tmp_path, width):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([_camera_entry(width=width)]))
    with pytest.raises(CameraError) as error:
        read_cameras_json(path)
    names(error, "cameras.json", MAX_IMAGE_SIDE)


def test_a_colmap_binary_width_of_2_64_minus_1_is_a_clean_error(tmp_path, capsys):
    cameras = [(1, "PINHOLE", 2**64 - 1, 48, (50.0, 50.0, 32.0, 24.0))]
    images = [image[:3] + (1,) + image[4:] for image in colmap_images(np.random.default_rng(0), count=2)]
    write_colmap_binary(tmp_path / "model", images, cameras)
    with pytest.raises(CameraError) as error:
        load_cameras(tmp_path / "model")
    names(error, "model", MAX_IMAGE_SIDE)


# --- paths that are not regular files -------------------------------------------------------------------


@pytest.fixture
def fifo(tmp_path):
    def make(name: str) -> Path:
        path = tmp_path / name
        os.mkfifo(path)
        return path

    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this platform")
    return make


def test_a_fifo_is_refused_instead_of_blocking(fifo, capsys):
    for read, name, kind in (
        (read_scene, "scene.ply", SceneFormatError),
        (read_cameras_json, "cameras.json", CameraError),
        (read_rgb, "style.png", ImageError),
    ):
        with pytest.raises(kind) as error:
            read(fifo(name))
        names(error, name, "FIFO")
    names(_one_line_error(capsys, ["info", str(fifo("other.ply"))]), "other.ply", "FIFO")


def test_a_link_to_a_device_is_refused_instead_of_read_forever(tmp_path):
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero")
    link = tmp_path / "endless.splat"
    link.symlink_to("/dev/zero")
    with pytest.raises(SceneFormatError) as error:
        read_scene(link)
    names(error, "endless.splat", "device")
    (tmp_path / "poses_bounds.npy").symlink_to("/dev/zero")
    with pytest.raises(CameraError) as error:
        load_cameras(tmp_path / "poses_bounds.npy")
    names(error, "poses_bounds.npy", "device")


# --- non-finite values in any property, and colours beyond any colour -----------------------------------


def test_a_nan_normal_or_extra_property_is_caught_on_read(tmp_path, capsys):
    from dresg_addon.scene.io import read_scene_detailed

    scene = random_scene(n=6, degree=0, normals=True, extras={"confidence": np.ones(6, np.float32)})
    columns = graphdeco_columns(scene)
    columns["nx"][2] = np.nan
    write_test_ply(tmp_path / "nan_normal.ply", columns)
    with pytest.raises(SceneFormatError) as error:
        read_scene(tmp_path / "nan_normal.ply")
    names(error, "nan_normal.ply", "non-finite", "1 of 6")
    assert read_scene_detailed(tmp_path / "nan_normal.ply", drop_invalid=True).dropped == 1
    columns = graphdeco_columns(scene)
    columns["confidence"][4] = np.inf
    write_test_ply(tmp_path / "inf_extra.ply", columns)
    with pytest.raises(SceneFormatError, match="non-finite"):
        read_scene(tmp_path / "inf_extra.ply")
    before = (tmp_path / "nan_normal.ply").read_bytes()
    assert "non-finite" in _one_line_error(
        capsys, ["convert", str(tmp_path / "nan_normal.ply"), str(tmp_path / "o.ply")]
    )
    assert not (tmp_path / "o.ply").exists() and (tmp_path / "nan_normal.ply").read_bytes() == before


def test_colours_far_outside_any_colour_are_clamped_on_read_with_a_note(tmp_path, capsys):
    from dresg_addon.scene.io import SH_LIMIT, ClampedColoursWarning, read_scene_detailed

    columns = graphdeco_columns(random_scene(n=6, degree=1))
    columns["f_dc_0"][1] = 1e30
    columns["f_rest_2"][3] = -1e30
    path = write_test_ply(tmp_path / "bright.ply", columns)
    result = read_scene_detailed(path)
    assert result.clamped == 2
    assert np.abs(result.scene.sh_dc).max() <= SH_LIMIT and np.abs(result.scene.sh_rest).max() <= SH_LIMIT
    with pytest.warns(ClampedColoursWarning) as warned:
        read_scene(path)
    names(warned[0].message, "bright.ply", "2 splats")
    assert cli.main(["info", str(path)]) == 0
    assert capsys.readouterr().err.count("\n") <= 1


# --- nothing but the one line on stderr -------------------------------------------------------------------


def test_a_corrupt_png_is_one_line_with_libpngs_own_words_kept_off_stderr(tmp_path, capfd):
    from dresg_addon.util.imageio import write_image

    write_image(tmp_path / "good.png", np.random.default_rng(0).uniform(0, 1, (64, 64, 3)).astype(np.float32))
    data = (tmp_path / "good.png").read_bytes()
    broken = tmp_path / "broken.png"
    broken.write_bytes(data[:60] + bytes(200) + data[260:])  # a damaged first chunk
    capfd.readouterr()
    with pytest.raises(ImageError) as error:
        read_rgb(broken)
    out, err = capfd.readouterr()
    assert err == "" and "\n" not in str(error.value) and "broken.png" in str(error.value)


def test_reading_and_writing_corrupt_scenes_raises_no_numpy_warnings(tmp_path):
    import warnings

    from dresg_addon.scene.io import write_scene

    columns = graphdeco_columns(random_scene(n=8, degree=0))
    columns["x"] = columns["x"].astype(np.float64)
    columns["x"][3] = 1e300  # overflows float32 on read
    path = write_test_ply(tmp_path / "overflow.ply", columns, types={"x": "double"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SceneFormatError, match="non-finite"):
            read_scene(path)
        scene = random_scene(n=4, degree=0)
        scene.log_scales[1] = 500.0  # exp overflows in the .splat encoder, which clamps it
        write_scene(scene, tmp_path / "big.splat")


# --- renders larger than the memory there is --------------------------------------------------------------


@pytest.mark.slow
def test_a_render_that_cannot_fit_in_memory_is_refused_before_allocating(monkeypatch):
    import torch

    import dresg_addon.util.machine as machine
    from dresg_addon.raster import render
    from dresg_addon.scene.camera import Camera, look_at

    n = 50
    g = torch.Generator().manual_seed(0)
    args = (
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.full((n, 3), -2.0),
        torch.full((n,), 2.0),
    )
    colors = torch.rand(n, 3, generator=g)
    big = Camera(2048, 2048, 1800.0, 1800.0, 1024.0, 1024.0, look_at([0, 0, -3.0], [0, 0, 0]), "big")
    monkeypatch.setattr(machine, "available_memory_bytes", lambda: 10**8)  # 0.1 GB left
    with pytest.raises(CameraError) as error:
        render(*args, colors, big)
    names(error, "2048x2048", "big", "0.1 GB")  # the view, its size and the memory there is
    monkeypatch.setattr(machine, "available_memory_bytes", lambda: None)  # unknown: no check
    plain = render(*args, colors, big)
    with torch.enable_grad():
        kept = render(*args, colors.clone().requires_grad_(True), big)  # samples kept for a backward
    assert torch.equal(plain.rgb, kept.rgb.detach()) and plain.n_pairs == kept.n_pairs > 0


# --- each kind of bad input: one line naming the file and the problem, whatever the wording ---------------


def _bad_input(tmp_path: Path, family: str) -> tuple[list[str], tuple]:
    """CLI arguments with one bad input of ``family``, and what its error line must name."""
    from dresg_addon.scene.io import write_scene
    from dresg_addon.util.imageio import write_image

    scene = random_scene(n=50, degree=0)
    write_scene(scene, tmp_path / "scene.ply")
    write_image(tmp_path / "style.png", np.random.default_rng(0).uniform(0, 1, (32, 32, 3)).astype(np.float32))
    run = ["stylize", str(tmp_path / "scene.ply"), "--style", str(tmp_path / "style.png")]
    run += ["--out", str(tmp_path / "out.ply"), "--width", "32", "--height", "24", "--stages", "1", "--quiet"]
    if family == "ply":
        columns = graphdeco_columns(scene)
        del columns["opacity"]
        write_test_ply(tmp_path / "holey.ply", columns)
        return ["info", str(tmp_path / "holey.ply")], ("holey.ply", "opacity")
    if family == "cameras":
        (tmp_path / "cams.json").write_text(json.dumps([_camera_entry(fx=float("nan"))]))  # NaN, as JSON allows
        return [*run, "--cameras", str(tmp_path / "cams.json")], ("cams.json", "camera 0")
    if family == "image":
        data = (tmp_path / "style.png").read_bytes()
        (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
        return [*run[:3], str(tmp_path / "cut.png"), *run[4:], "--orbit", "3"], ("cut.png",)
    if family == "config":
        return [*run, "--orbit", "3", "--stroke-size", "100"], ("stroke_size", "100")
    assert family == "mask"
    np.save(tmp_path / "short.npy", np.ones(7, bool))
    return [*run, "--orbit", "3", "--mask", str(tmp_path / "short.npy")], ("short.npy", "7", "50")


@pytest.mark.parametrize("family", ["ply", "cameras", "image", "config", "mask"])
def test_each_kind_of_bad_input_is_one_line_naming_the_file_and_the_problem(tmp_path, capsys, family):
    args, named = _bad_input(tmp_path, family)
    names(_one_line_error(capsys, args), *named)
    assert not (tmp_path / "out.ply").exists()
