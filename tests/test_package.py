"""Package hygiene: the engine never imports bpy, and the CLI starts without heavy imports."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", f"import sys; {code}; print(' '.join(sorted(sys.modules)))"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    return set(out.stdout.split())


def test_engine_imports_no_bpy():
    modules = _modules_after(
        "import dresg_addon, dresg_addon.method.loop, dresg_addon.raster, dresg_addon.scene.io, dresg_addon.scene.camera_io, "
        "dresg_addon.evaluation.metrics, dresg_addon.method.proposal, dresg_addon.cli"
    )
    assert "bpy" not in modules
    assert "diffusers" not in modules  # only the sd15 backend imports it, lazily


def test_package_import_is_light():
    modules = _modules_after("import dresg_addon, dresg_addon.cli; dresg_addon.cli.build_parser()")
    assert "torch" not in modules and "bpy" not in modules


@pytest.mark.parametrize("command", ["info", "convert", "render", "select-views", "stylize", "evaluate", "demo"])
def test_every_command_has_help(command, capsys):
    from dresg_addon.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    assert command in capsys.readouterr().out


# Bottom to top; a module may import its own layer and those below it, never one above.
LAYERS = ("util", "scene", "blender", "raster", "method", "evaluation", "commands")
ENGINE = REPO / "dresg_addon"


def _layer(module: str) -> int:
    """The layer of a dotted module name under dresg_addon (the package root and the CLI sit at the ends)."""
    parts = module.split(".")[1:]
    if parts and parts[0] in ("cli", "__main__"):
        return len(LAYERS) - 1
    if not parts or parts[0] not in LAYERS:
        return 0  # the package root and its attributes (__version__): it imports nothing of the engine
    return LAYERS.index(parts[0])


def _engine_imports():
    """(importing module, imported module, line) for every import of the engine in the engine, nested ones included."""
    import ast

    for path in sorted(ENGINE.rglob("*.py")):
        parts = list(path.relative_to(REPO).with_suffix("").parts)
        package = parts[:-1]  # the package a relative import starts from, for modules and __init__ alike
        module = ".".join(parts if parts[-1] != "__init__" else package)
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package[: len(package) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != "dresg_addon":
                    continue
                names = [f"{target}.{a.name}" for a in node.names] if target == "dresg_addon" else [target]
                for name in names:
                    yield module, name, node.lineno
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] == "dresg_addon":
                        yield module, alias.name, node.lineno


def test_every_engine_module_belongs_to_a_layer():
    for path in ENGINE.rglob("*.py"):
        parts = path.relative_to(ENGINE).parts
        assert len(parts) == 1 and parts[0] in ("__init__.py", "__main__.py", "cli.py") or parts[0] in LAYERS, path


def test_imports_only_go_downward():
    """method -> raster -> scene -> util (evaluation and commands above the method): a layer never imports one above."""
    imports = list(_engine_imports())
    upward = [
        f"{module} (line {line}) imports {target}"
        for module, target, line in imports
        if _layer(target) > _layer(module)
    ]
    assert not upward, "\n".join(upward)
    assert len(imports) > 100  # the walk saw the engine's imports


def test_the_blender_math_is_for_the_add_on_only():
    """dresg_addon.blender (Blender's conventions as numpy math) serves the add-on: no other engine package imports it."""
    importers = {
        module
        for module, target, _ in _engine_imports()
        if target.startswith("dresg_addon.blender") and not module.startswith("dresg_addon.blender")
    }
    assert not importers


def test_the_settings_enter_the_method_at_the_loop_only():
    """One settings flow: StylizeConfig goes into loop.stylize (and views.select_active_views, an entry point
    too); the steps below get their own typed parts of it, so no other method module imports it."""
    importers = {
        module
        for module, target, _ in _engine_imports()
        if module.startswith("dresg_addon.method.") and target == "dresg_addon.method.config"
    }
    assert importers == {"dresg_addon.method.loop"}


def test_version_is_one_number_for_the_cli_and_the_extension(capsys):
    import tomllib

    from dresg_addon import __version__
    from dresg_addon.cli import main

    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    assert manifest["version"] == __version__
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0 and capsys.readouterr().out.strip() == f"python -m dresg_addon {__version__}"


UNIX_ONLY = ("resource", "fcntl", "termios", "pwd", "grp", "posix")  # modules Windows' Python does not have


def test_the_engine_and_the_add_on_import_no_unix_only_module_at_load():
    """Blender runs on Windows too: nothing the extension loads may import a Unix-only module at import time,
    and the manifest declares the platforms (Blender's names) it installs on."""
    import ast
    import tomllib

    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    assert set(manifest["platforms"]) == {"linux-x64", "windows-x64", "macos-arm64", "macos-x64"}

    for path in [*ENGINE.rglob("*.py"), *(REPO / "operators").rglob("*.py"), *(REPO / "ui").rglob("*.py")]:
        for node in ast.parse(path.read_text(encoding="utf-8")).body:  # module level only: guarded uses are inside
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            names += [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            assert not {n.split(".")[0] for n in names} & set(UNIX_ONLY), f"{path.relative_to(REPO)} imports {names}"


def test_without_unix_only_modules_the_engine_runs_and_measures_memory():
    """With the Unix-only modules missing (as on Windows), every engine module imports, a run's memory and
    process bookkeeping still work."""
    code = f"""
import sys
for name in {UNIX_ONLY[:-1]!r}:  # posix stays: the standard library itself runs on it here
    sys.modules[name] = None  # import fails, as where the module does not exist
import importlib, pkgutil, dresg_addon
for info in pkgutil.walk_packages(dresg_addon.__path__, "dresg_addon."):
    if not info.name.endswith("__main__"):
        importlib.import_module(info.name)
from dresg_addon.util.machine import peak_rss_mb, process_alive
import os
assert peak_rss_mb() > 0 and process_alive(os.getpid())
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_memory_freed_between_live_blocks_goes_back_to_the_system():
    """glibc keeps freed heap blocks that sit between live ones; a run hands them back between its steps."""
    code = """
import numpy as np
from dresg_addon.util.machine import release_free_memory
def rss():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS"))
big = np.ones(2**20)  # 8 MiB: freed, it raises glibc's threshold for mapping blocks of their own
del big
blocks = [np.ones(2**19) for _ in range(40)]  # 4 MiB each, now from the heap
del blocks[::2]  # freed between live blocks: the allocator keeps them
before = rss()
print(release_free_memory(), (before - rss()) / 2**20)
"""
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    released, mib = done.stdout.split()
    assert released == "True" and float(mib) > 60.0, done.stderr  # of the 80 MiB freed


def test_a_finished_process_is_not_alive():
    from dresg_addon.util.machine import process_alive

    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    assert not process_alive(int(child.stdout))
    import os

    assert process_alive(os.getpid())
