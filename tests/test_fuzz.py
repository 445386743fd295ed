"""A seeded, bounded mutation fuzzer over every reader and the CLI's error path (issue 11).

Each case mutates a small valid file (byte flips, truncation, inserted bytes, and for text formats numbers
swapped for extreme ones) and reads it. A reader must either return finite data or raise one of the
project's own errors; the file is never modified; no numpy warning escapes; through the CLI a failure is
exit code 2 with one stderr line. Deterministic: the same seed gives the same cases.
"""

from __future__ import annotations

import hashlib
import re
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from test_cameras import colmap_images, write_colmap_text

from dresg_addon import cli
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.camera_io import load_cameras, write_cameras_json
from dresg_addon.scene.gaussians import SH_C0, GaussianScene
from dresg_addon.scene.io import ClampedColoursWarning, InvalidSplatsWarning, read_scene_detailed, write_scene
from dresg_addon.util.errors import DresgError
from dresg_addon.util.imageio import read_rgb, write_image

SEED = 20261124
CASES_PER_FILE = 40
EXTREME_NUMBERS = ("1e309", "-1e309", "nan", "-0", "0", "-1", "1e-320", "9" * 400, "4294967296", "18446744073709551615")


def _scene(n: int = 24) -> GaussianScene:
    rng = np.random.default_rng(0)
    quats = rng.normal(size=(n, 4))
    return GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=rng.uniform(-4, -1, (n, 3)).astype(np.float32),
        quats=(quats / np.linalg.norm(quats, axis=1, keepdims=True)).astype(np.float32),
        opacity_logits=rng.normal(size=n).astype(np.float32),
        sh_dc=((rng.uniform(0, 1, (n, 3)) - 0.5) / SH_C0).astype(np.float32),
        sh_rest=(0.1 * rng.normal(size=(n, 3, 3))).astype(np.float32),
        normals=rng.normal(size=(n, 3)).astype(np.float32),
    )


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    """One small valid file of every kind the readers take."""
    folder = tmp_path_factory.mktemp("seeds")
    scene = _scene()
    for name in ("scene.ply", "scene.splat", "scene.compressed.ply"):
        write_scene(scene, folder / name)
    cameras = [Camera(64, 48, 50.0, 50.0, 32.0, 24.0, look_at([0, 0, -3.0 - k], [0, 0, 0]), f"c{k}") for k in range(2)]
    write_cameras_json(folder / "cameras.json", cameras)
    write_colmap_text(folder / "colmap", colmap_images(np.random.default_rng(1), count=2))
    rgb = np.random.default_rng(2).uniform(0, 1, (24, 32, 3)).astype(np.float32)
    write_image(folder / "style.png", rgb)
    write_image(folder / "style.jpg", rgb)
    return {
        "ply": folder / "scene.ply",
        "splat": folder / "scene.splat",
        "compressed": folder / "scene.compressed.ply",
        "json": folder / "cameras.json",
        "colmap": folder / "colmap" / "cameras.txt",
        "png": folder / "style.png",
        "jpg": folder / "style.jpg",
    }


def _mutate(data: bytes, rng: np.random.Generator, text: bool) -> bytes:
    """One random mutation: flip bytes, truncate, insert bytes, or (text) replace a number by an extreme one."""
    kind = rng.integers(5 if text else 4)
    if kind == 0:  # flip a few bytes
        out = bytearray(data)
        for position in rng.integers(0, len(out), rng.integers(1, 9)):
            out[position] ^= int(rng.integers(1, 256))
        return bytes(out)
    if kind == 1:  # truncate
        return data[: int(rng.integers(0, len(data)))]
    if kind == 2:  # insert random bytes
        position = int(rng.integers(0, len(data) + 1))
        return (
            data[:position] + rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes() + data[position:]
        )
    if kind == 3:  # mutate the header area of binary formats too: digits there are counts and sizes
        head = data[:400]
        numbers = [m.span() for m in re.finditer(rb"\d+", head)]
        if not numbers:
            return data[::-1]
        start, end = numbers[int(rng.integers(len(numbers)))]
        return data[:start] + EXTREME_NUMBERS[int(rng.integers(len(EXTREME_NUMBERS)))].encode() + data[end:]
    numbers = [m.span() for m in re.finditer(rb"-?\d+(\.\d+)?(e-?\d+)?", data)]
    start, end = numbers[int(rng.integers(len(numbers)))]
    return data[:start] + EXTREME_NUMBERS[int(rng.integers(len(EXTREME_NUMBERS)))].encode() + data[end:]


def _check_finite_scene(scene: GaussianScene) -> None:
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest", "normals"):
        value = getattr(scene, name)
        assert value is None or np.isfinite(value).all(), name
    for name, value in scene.extras.items():
        assert not np.issubdtype(value.dtype, np.floating) or np.isfinite(value).all(), name


def _read(kind: str, path: Path) -> None:
    if kind in ("ply", "splat", "compressed"):
        _check_finite_scene(read_scene_detailed(path, drop_invalid=True).scene)
    elif kind in ("json", "colmap"):
        for camera in load_cameras(path if kind == "json" else path.parent):
            assert np.isfinite(camera.world_to_camera).all() and camera.width >= 1 and camera.height >= 1
    else:
        assert np.isfinite(read_rgb(path)).all()


@pytest.mark.parametrize("kind", ["ply", "splat", "compressed", "json", "colmap", "png", "jpg"])
def test_mutated_files_read_cleanly_or_fail_with_the_projects_own_error(seeds, kind, tmp_path):
    rng = np.random.default_rng([SEED, ["ply", "splat", "compressed", "json", "colmap", "png", "jpg"].index(kind)])
    original = seeds[kind].read_bytes()
    text = kind in ("json", "colmap")
    outcomes = {"read": 0, "refused": 0}
    for case in range(CASES_PER_FILE):
        folder = tmp_path / f"case{case:03d}"
        folder.mkdir()
        if kind == "colmap":  # the model's other file comes along unchanged
            (folder / "images.txt").write_bytes((seeds[kind].parent / "images.txt").read_bytes())
        path = folder / seeds[kind].name
        path.write_bytes(_mutate(original, rng, text))
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            warnings.simplefilter("ignore", InvalidSplatsWarning)
            warnings.simplefilter("ignore", ClampedColoursWarning)
            warnings.simplefilter("ignore", UserWarning)  # e.g. COLMAP distortion notes
            warnings.simplefilter("error", RuntimeWarning)
            try:
                _read(kind, path)
                outcomes["read"] += 1
            except DresgError as error:
                assert "\n" not in str(error), (case, str(error))
                outcomes["refused"] += 1
        assert hashlib.sha256(path.read_bytes()).hexdigest() == digest, f"case {case} modified its input"
    assert outcomes["refused"] > 0  # the mutations do break files


@pytest.mark.parametrize("kind", ["ply", "splat", "compressed"])
def test_the_cli_says_one_line_and_exits_2_on_mutated_scenes(seeds, kind, tmp_path, capsys):
    rng = np.random.default_rng([SEED, 99, ["ply", "splat", "compressed"].index(kind)])
    original = seeds[kind].read_bytes()
    for case in range(12):
        path = tmp_path / f"case{case:02d}{seeds[kind].name[5:]}"
        path.write_bytes(_mutate(original, rng, text=False))
        code = cli.main(["info", str(path)])
        out, err = capsys.readouterr()
        assert code in (0, 2), (case, code)
        lines = err.strip().splitlines()
        if code == 2:
            assert len(lines) == 1 and lines[0].startswith("error: "), (case, lines)
        else:
            assert all(line.startswith("note: ") for line in lines), (case, lines)


FULL_DISK_CASES = """
import hashlib, json, os, resource, signal, sys
import numpy as np
from pathlib import Path
from dresg_addon.scene.io import read_scene, write_scene
from dresg_addon.util.errors import WriteError
from dresg_addon.util.imageio import write_image
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
seeds, out = Path(sys.argv[1]), Path(sys.argv[2])
scene = read_scene(seeds / "scene.ply")
image = np.random.default_rng(3).uniform(size=(48, 64, 3)).astype(np.float32)
rng = np.random.default_rng(int(sys.argv[3]))
hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1]
outcomes = []
for case in range(48):
    name = ["a.ply", "a.splat", "a.compressed.ply", "a.png", "a.exr", "a.tif", "a.jpg"][case % 7]
    target = out / name
    target.write_bytes(b"old " + bytes([case]))
    limit = int(rng.integers(0, 200000))
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        if name[-3:] in ("png", "exr", "tif", "jpg"):
            write_image(target, image)
        else:
            write_scene(scene, target)
        outcome = "written"
    except WriteError as error:
        outcome = "refused: " + str(error)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
    left = sorted(p.name for p in out.iterdir())
    outcomes.append({"case": case, "limit": limit, "name": name, "outcome": outcome, "left": left,
                     "old": target.read_bytes() == b"old " + bytes([case]), "size": target.stat().st_size})
    target.unlink()
print(json.dumps(outcomes))
"""


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_FSIZE stands in for a full disk on Unix")
def test_writes_at_random_size_limits_complete_or_fail_cleanly(seeds, tmp_path):
    """Issue 19: every scene and image format, written under random file size limits (a disk that fills at a
    random point): either the whole file lands, or one WriteError names the path and the reason, the old
    file stays as it was and no temporary file is left."""
    import json
    import subprocess

    done = subprocess.run(
        [sys.executable, "-c", FULL_DISK_CASES, str(seeds["ply"].parent), str(tmp_path), str(SEED)],
        cwd=Path(__file__).resolve().parents[1],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    outcomes = json.loads(done.stdout)
    for case in outcomes:
        assert case["left"] == [case["name"]], case  # no temporary file beside it
        if case["outcome"] == "written":
            assert not case["old"] and case["size"] <= case["limit"], case
        else:
            assert case["old"], case
            assert case["outcome"].startswith(f"refused: {tmp_path / case['name']}: cannot write: "), case
            assert "\n" not in case["outcome"]
    kinds = {c["outcome"] == "written" for c in outcomes}
    assert kinds == {True, False}  # the limits cover both
