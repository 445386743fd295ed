"""Nothing lost or silently broken when the disk fills (issue 19).

Each command runs in a child process whose file size limit (RLIMIT_FSIZE) is set below what it writes,
with SIGXFSZ ignored, so every write past the limit fails with EFBIG as a full disk fails with ENOSPC, and
no root is needed. A failed write must be exit code 2 with one stderr line naming the path and the
system's reason; no file at a target may be left that was not there, or that differs from before; and a
stylization stopped by a failed checkpoint must resume from the last good one.
"""

from __future__ import annotations

import hashlib
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from messages import names

from dresg_addon import cli
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.camera_io import write_cameras_json
from dresg_addon.scene.gaussians import SH_C0, GaussianScene
from dresg_addon.scene.io import write_scene
from dresg_addon.util.errors import WriteError
from dresg_addon.util.fileutil import atomic_write_bytes, check_room
from dresg_addon.util.imageio import write_image

resource = pytest.importorskip("resource")  # Unix: the limit that stands in for a full disk
pytestmark = pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="no file size limit on this OS")

REPO = Path(__file__).resolve().parents[1]
TINY = ["--preset", "cpu", "--proposal-size", "32x24", "--quiet"]  # colours only, a post stage after the stages


def _limited(limit: int):
    def apply() -> None:
        import signal

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # ignored dispositions survive exec
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


def _cli(args: list[str], limit: int | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "dresg_addon", *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        preexec_fn=None if limit is None else _limited(limit),
    )


def _one_line_failure(done: subprocess.CompletedProcess, *needles: str) -> str:
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), done.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def _snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden temporaries included) and its digest."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()
    }


def _scene(n: int = 400) -> GaussianScene:
    rng = np.random.default_rng(0)
    means = rng.normal(size=(n, 3))
    quats = rng.normal(size=(n, 4))
    return GaussianScene(
        means=(0.5 * means / np.linalg.norm(means, axis=1, keepdims=True)).astype(np.float32),
        log_scales=np.full((n, 3), math.log(0.07), np.float32),
        quats=(quats / np.linalg.norm(quats, axis=1, keepdims=True)).astype(np.float32),
        opacity_logits=np.full(n, 2.0, np.float32),
        sh_dc=((rng.uniform(0.2, 0.8, (n, 3)) - 0.5) / SH_C0).astype(np.float32),
        sh_rest=(0.05 * rng.normal(size=(n, 15, 3))).astype(np.float32),
    )


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("inputs")
    write_scene(_scene(), folder / "scene.ply")
    ring = [
        Camera(64, 48, 50.0, 50.0, 32.0, 24.0, look_at([2 * math.sin(a), -0.5, -2 * math.cos(a)], [0, 0, 0]), f"c{k}")
        for k, a in enumerate((0.0, 2.1, 4.2))
    ]
    write_cameras_json(folder / "cameras.json", ring)
    style = np.random.default_rng(1).uniform(size=(24, 32, 3)).astype(np.float32)
    write_image(folder / "style.png", style)
    return {"scene": folder / "scene.ply", "cameras": folder / "cameras.json", "style": folder / "style.png"}


def test_convert_onto_a_full_disk_keeps_the_old_file(inputs, tmp_path):
    target = tmp_path / "out.ply"
    target.write_bytes(b"the old file")
    done = _cli(["convert", inputs["scene"], target], limit=4096)
    _one_line_failure(done, str(target), "cannot write", "File too large")
    assert target.read_bytes() == b"the old file" and _snapshot(tmp_path) == {"out.ply": _snapshot(tmp_path)["out.ply"]}


@pytest.mark.slow
def test_render_onto_a_full_disk_fails_instead_of_writing_empty_images(inputs, tmp_path):
    out = tmp_path / "renders"
    done = _cli(["render", inputs["scene"], "--cameras", inputs["cameras"], "--out", out], limit=256)
    _one_line_failure(done, "cannot write", "File too large")
    assert _snapshot(tmp_path) == {}  # no empty or half-written image, no temporary file

    exr = _cli(["render", inputs["scene"], "--orbit", "2", "--format", "exr", "--depth", "--out", out], limit=2048)
    _one_line_failure(exr, "cannot write")
    assert _snapshot(tmp_path) == {}


@pytest.mark.slow
def test_saved_views_onto_a_full_disk_stop_the_run_with_one_line(inputs, tmp_path):
    out = tmp_path / "run" / "stylized.ply"
    args = ["stylize", inputs["scene"], "--cameras", inputs["cameras"], "--style", inputs["style"], "--out", out]
    done = _cli([*args, *TINY, "--stages", "1", "--save-views", tmp_path / "views"], limit=3000)
    _one_line_failure(done, "cannot write", "File too large", "so the run stopped")
    assert not out.exists() and all(p.stat().st_size > 0 for p in tmp_path.rglob("*.png"))


@pytest.mark.slow
def test_a_failed_checkpoint_stops_the_run_and_the_last_good_one_resumes(inputs, tmp_path):
    args = ["stylize", inputs["scene"], "--cameras", inputs["cameras"], "--style", inputs["style"], *TINY]
    args += ["--sh-rest", "keep"]
    # The size of a first-stage checkpoint, from a one-stage run: the next stage's adds a log entry to it.
    probe = _cli([*args, "--stages", "1", "--out", tmp_path / "probe" / "s.ply"])
    assert probe.returncode == 0, probe.stderr
    first = (tmp_path / "probe" / "s.checkpoint" / "checkpoint.pt").stat().st_size

    out = tmp_path / "run" / "s.ply"
    checkpoint = out.with_suffix(".checkpoint") / "checkpoint.pt"
    stopped = _cli([*args, "--stages", "3", "--out", out], limit=first + 200)
    line = _one_line_failure(stopped, str(checkpoint), "cannot write", "File too large")
    assert line.endswith(f"{checkpoint} keeps the last good stage, 1")
    saved = torch.load(checkpoint, weights_only=True)
    assert saved["stage"] == 1 and not out.exists()
    assert not [p for p in checkpoint.parent.iterdir() if p.name != "checkpoint.pt"]  # no temporary left

    # The stages done, the scene write fails (the scene is larger than the limit): the checkpoint keeps them.
    size = (tmp_path / "probe" / "s.ply").stat().st_size
    assert size > first + 200  # the SH bands kept make the scene the largest file
    failed = _cli([*args, "--stages", "3", "--out", out], limit=size - 1)
    _one_line_failure(failed, str(out), "cannot write", "the same command resumes it")
    assert not out.exists() and torch.load(checkpoint, weights_only=True)["stage"] == 3
    resumed = _cli([*args, "--stages", "3", "--out", out])
    assert resumed.returncode == 0, resumed.stderr
    assert out.exists()
    log = [json.loads(line) for line in out.with_suffix(".log.jsonl").read_text().splitlines()]
    assert [e["stage"] for e in log] == [1, 2, 3, "post"]


def test_stylize_checks_its_folders_before_it_starts(inputs, tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_bytes(b"")
    args = ["stylize", str(inputs["scene"]), "--cameras", str(inputs["cameras"]), "--style", str(inputs["style"])]
    assert cli.main([*args, *TINY, "--out", str(blocker / "out.ply")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {blocker}: cannot write: ")

    import shutil

    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage._replace(free=1000))
    started = []
    monkeypatch.setattr("dresg_addon.method.loop.stylize", lambda *a, **k: started.append(1))
    assert cli.main([*args, *TINY, "--out", str(tmp_path / "out.ply")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not enough room" in err[0] and "0 MB free" in err[0] and not started


def test_room_is_counted_per_file_system_and_probed_for_writing(tmp_path, monkeypatch):
    import shutil

    check_room({tmp_path / "a": 10, tmp_path / "b" / "c": 10})  # created, written to, room enough
    assert (tmp_path / "b" / "c").is_dir() and not list((tmp_path / "b" / "c").iterdir())
    free = shutil.disk_usage(tmp_path).free
    monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(free, 0, 15))
    check_room({tmp_path / "a": 15})
    with pytest.raises(WriteError) as error:
        check_room({tmp_path / "a": 8, tmp_path / "b": 8})  # one file system: 16 bytes needed, 15 free
    names(error, str(tmp_path))  # where the run would write


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc to name a descriptor's file")
def test_writes_are_synced_before_the_rename(tmp_path, monkeypatch):
    """The temporary file reaches the disk before it replaces the target, and the folder after."""
    import os

    calls = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(
        os, "fsync", lambda fd: (calls.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))), real_fsync(fd))[1]
    )
    monkeypatch.setattr(os, "replace", lambda a, b: (calls.append(("replace", str(b))), real_replace(a, b))[1])
    target = tmp_path / "file.bin"
    atomic_write_bytes(target, b"data")
    kinds = [kind for kind, _ in calls]
    assert kinds == ["fsync", "replace", "fsync"]
    assert ".tmp" in calls[0][1] and calls[1][1] == str(target) and calls[2][1] == str(tmp_path)
