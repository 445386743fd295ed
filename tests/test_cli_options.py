"""Issue 20: an option several commands share is spelled, parsed and refused the same way by each of them
(one definition and one parser per option, in ``dresg_addon/commands/_common.py``), and no command borrows
another command's private helpers.

Every command checks its options before it reads any file, so a run on a missing scene tells whether the
command's own checks accepted an option (the error is then about the scene) or refused it (the error names
the option). Nothing is rendered.
"""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from messages import names

from dresg_addon import cli
from dresg_addon.commands import _common
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.camera_io import MAX_IMAGE_SIDE, write_cameras_json
from dresg_addon.scene.gaussians import GaussianScene
from dresg_addon.scene.io import write_scene
from dresg_addon.util.imageio import write_image

COMMANDS_DIR = Path(_common.__file__).parent
SHARED = ("--background", "--width", "--height", "--device", "--up")
# The commands that must take each shared option (more may).
EXPECTED = {
    "--background": {"render", "evaluate", "stylize"},
    "--width": {"render", "evaluate", "stylize", "select-views"},
    "--device": {"render", "evaluate", "stylize", "select-views", "demo"},
    "--up": {"render", "evaluate", "stylize", "select-views"},
}


def _command_parsers() -> dict:
    """Each command's sub-parser, as ``dresg_addon.cli`` builds it."""
    return dict(cli.build_parser()._subparsers._group_actions[0].choices)


def _takes() -> dict[str, set[str]]:
    """Shared option -> the commands whose parser has it."""
    parsers = _command_parsers()
    return {option: {name for name, p in parsers.items() if option in p._option_string_actions} for option in SHARED}


@pytest.fixture(scope="module")
def paths(tmp_path_factory) -> dict[str, str]:
    """A style image that reads, a scene file that does not exist, and an output path."""
    folder = tmp_path_factory.mktemp("options")
    write_image(folder / "style.png", np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32))
    return {"STYLE": str(folder / "style.png"), "MISSING": str(folder / "missing.ply"), "OUT": str(folder / "out")}


# Per command: the smallest command line that passes its option checks and then fails on the missing scene,
# except for the commands that make their own inputs: their runs are only ever refused here.
RUNS = {
    "render": ["render", "MISSING", "--orbit", "2", "--out", "OUT"],
    "evaluate": ["evaluate", "MISSING", "--base", "MISSING", "--style", "STYLE", "--orbit", "2"],
    "stylize": ["stylize", "MISSING", "--style", "STYLE", "--out", "OUT", "--orbit", "2"],
    "select-views": ["select-views", "MISSING", "--orbit", "2"],
    "demo": ["demo", "--out", "OUT"],
    "report": ["report", "--out", "OUT"],
}
NO_SCENE = {"demo", "report"}


def _argv(command: str, paths: dict[str, str], extra: list[str]) -> list[str]:
    return [paths.get(word, word) for word in RUNS[command]] + extra


def _error_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    return lines[0]


def test_every_command_that_should_takes_the_shared_options():
    takes = _takes()
    for option, commands in EXPECTED.items():
        assert commands <= takes[option], f"{option} is missing from {sorted(commands - takes[option])}"
    assert takes["--width"] == takes["--height"]
    assert set(RUNS) >= set().union(*takes.values()), "add a run for the new command to RUNS"


GOOD = {
    "--background": [(["--background", "1"], (1.0, 1.0, 1.0)), (["--background", "0.2,0.3,0.4"], (0.2, 0.3, 0.4))],
    "--width": [(["--width", "64", "--height", "48"], (64, 48)), (["--width", "64"], (64, 46))],
    "--up": [(["--up", "0,0,1"], (0.0, 0.0, 1.0))],
    "--device": [(["--device", "cpu"], torch.device("cpu"))],
}


def _value(option: str, args):
    """The shared parser's reading of ``option`` (for the size options: the orbit cameras' size)."""
    return {
        "--background": lambda: _common.parse_background(args.background),
        "--width": lambda: _common.orbit_size(args),
        "--up": lambda: _common.parse_up(args.up),
        "--device": lambda: _common.parse_device(args.device),
    }[option]()


@pytest.mark.parametrize("option", sorted(GOOD))
def test_the_same_spelling_gives_the_same_value_everywhere(option, paths, capsys):
    parser = cli.build_parser()
    for command in sorted(_takes()[option]):
        for extra, expected in GOOD[option]:
            args = parser.parse_args(_argv(command, paths, extra))
            assert _value(option, args) == expected, (command, extra)
            if command in NO_SCENE:
                continue
            # The command's own checks accept it: the run goes on to the scene, which is missing.
            assert cli.main(_argv(command, paths, extra)) == 2
            assert _error_line(capsys) == f"error: {paths['MISSING']}: file not found", (command, extra)


BAD = {
    "--background 2": (["--background", "2"], "error: --background '2': values must be in [0, 1]"),
    "--background a,b": (["--background", "a,b"], "error: --background 'a,b': expected comma-separated numbers"),
    "--background 1,1": (["--background", "1,1"], "error: --background '1,1': expected 1 or 3 numbers, got 2"),
    "--device tpu": (["--device", "tpu"], "error: --device 'tpu': expected cpu, cuda or cuda:N"),
    "--device cpu:1": (["--device", "cpu:1"], "error: --device 'cpu:1': expected cpu, cuda or cuda:N"),
    "--device cuda:99": (["--device", "cuda:99"], "error: --device 'cuda:99': this torch build sees "),
    "--width 0": (["--width", "0"], f"error: --width 0 must be between 1 and {MAX_IMAGE_SIDE} pixels"),
    "--height 99999": (["--height", "99999"], f"error: --height 99999 must be between 1 and {MAX_IMAGE_SIDE} pixels"),
    "--up 0,0,0": (["--up", "0,0,0"], "error: --up '0,0,0': the direction must not be zero"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_the_same_bad_spelling_gives_the_same_one_line_error_everywhere(case, paths, capsys):
    extra, start = BAD[case]
    commands = _takes()[extra[0]]
    errors = {}
    for command in sorted(commands):
        assert cli.main(_argv(command, paths, extra)) == 2, command
        errors[command] = _error_line(capsys)
    assert len(set(errors.values())) == 1, errors
    assert next(iter(errors.values())).startswith(start), errors
    assert not Path(paths["OUT"]).exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="the message is for machines without a CUDA GPU")
def test_cuda_without_a_gpu_is_one_line(paths, capsys):
    assert cli.main(_argv("stylize", paths, ["--device", "cuda"])) == 2
    names(_error_line(capsys), "--device", "cuda", "--device cpu")  # the option, its value and what to use


def test_width_or_height_alone_keeps_the_aspect_ratio_of_file_and_orbit_cameras(tmp_path):
    """stylize and select-views once needed --width and --height together; one alone now works as in render."""
    rng = np.random.default_rng(0)
    n = 50
    scene = GaussianScene(
        means=rng.normal(scale=0.3, size=(n, 3)).astype(np.float32),
        log_scales=np.full((n, 3), math.log(0.05), np.float32),
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        opacity_logits=np.ones(n, np.float32),
        sh_dc=np.zeros((n, 3), np.float32),
    )
    write_scene(scene, tmp_path / "scene.ply")
    camera = Camera(64, 48, 50.0, 50.0, 32.0, 24.0, look_at([0.0, 0.0, -2.0], [0.0, 0.0, 0.0]), "front")
    write_cameras_json(tmp_path / "cameras.json", [camera])
    parser = cli.build_parser()
    for command in ("stylize", "select-views"):
        extra = ["--style", "s.png", "--out", "o.ply"] if command == "stylize" else []
        for cameras, size, expected in (
            (["--cameras", str(tmp_path / "cameras.json")], ["--width", "32"], (32, 24)),
            (["--cameras", str(tmp_path / "cameras.json")], ["--height", "24"], (32, 24)),
            (["--orbit", "2"], ["--width", "64"], (64, 46)),
            (["--orbit", "2"], ["--height", "64"], (90, 64)),
        ):
            args = parser.parse_args([command, str(tmp_path / "scene.ply"), *cameras, *size, *extra])
            _, loaded = _common.load_scene_and_cameras(args)
            assert {(c.width, c.height) for c in loaded} == {expected}, (command, cameras, size)


def _command_imports(tree: ast.Module, package: str = "dresg_addon.commands") -> list[tuple[str, list[str]]]:
    """(module of dresg_addon/commands, the names imported from it) for every import of one in ``tree``."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name.removeprefix(f"{package}."), []) for a in node.names if a.name.startswith(f"{package}.")]
        elif isinstance(node, ast.ImportFrom):
            names = [alias.name for alias in node.names]
            if (node.level, node.module) in ((1, None), (0, package)):  # from . import render: modules
                found += [(name, []) for name in names]
            elif node.level == 1:
                found.append((node.module, names))
            elif node.level == 0 and node.module.startswith(f"{package}."):
                found.append((node.module.removeprefix(f"{package}."), names))
    return found


def test_no_command_imports_another_commands_private_names():
    for path in sorted(COMMANDS_DIR.glob("*.py")):
        for module, imported in _command_imports(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            private = [name for name in imported if name.startswith("_")]
            assert not private, f"{path.name} imports private {private} from {module}"
            # Shared helpers live in _common; a command never depends on another command.
            assert module == "_common", f"{path.name} imports from the {module} command"
