"""PyTorch for the optimizer: used when importable, otherwise installed on request.

torch is far too large to ship inside the extension, so "Install Dependencies" runs pip in a
subprocess (``pip install --target``) into a folder of the add-on's user directory, which survives
extension upgrades, and puts that folder on ``sys.path``. Import, export and viewing never need torch.
"""

import importlib
import importlib.util
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import bpy

from ..dresg_addon.util.errors import DresgError
from . import ADDON_PACKAGE
from .tasks import BackgroundTask, tag_redraw

TORCH_REQUIREMENT = "torch==2.13.0"
TAIL_LINES = 12  # output lines kept for the panel and for error messages


def site_packages_dir(create: bool = False) -> Path:
    """The add-on's private ``site-packages`` folder (per Blender version and user)."""
    try:
        return Path(bpy.utils.extension_path_user(ADDON_PACKAGE, path="site-packages", create=create))
    except ValueError:  # loaded as a plain add-on (development checkout, tests): no extension user folder
        folder = Path(bpy.utils.user_resource("CONFIG")) / ADDON_PACKAGE.rpartition(".")[2] / "site-packages"
        if create:
            folder.mkdir(parents=True, exist_ok=True)
        return folder


def add_site_packages() -> None:
    """Make packages installed by the add-on importable (called at registration and after an install)."""
    folder = str(site_packages_dir())
    if os.path.isdir(folder) and folder not in sys.path:
        sys.path.append(folder)
        importlib.invalidate_caches()


def torch_available() -> bool:
    """Whether ``import torch`` would work, without importing it (which takes seconds)."""
    return importlib.util.find_spec("torch") is not None


def pip_commands(target: Path, requirement: str = TORCH_REQUIREMENT, index_url: str = "") -> list[list[str]]:
    """The commands an install runs: pip bootstrapped when Blender's Python lacks it, then pip install."""
    commands = []
    if importlib.util.find_spec("pip") is None:
        commands.append([sys.executable, "-m", "ensurepip", "--upgrade"])
    install = [sys.executable, "-m", "pip", "install", "--disable-pip-version-check", "--no-input"]
    install += ["--target", str(target), "--upgrade", requirement]
    if index_url:
        install += ["--index-url", index_url]
    commands.append(install)
    return commands


@dataclass
class Installer:
    """Runs commands one after another as a :class:`~.tasks.BackgroundTask`, keeping the last lines of output.

    The worker posts each output line; :meth:`poll` (main thread) applies them to ``lines``, ``done`` and
    ``error``, which the panels read.
    """

    commands: list[list[str]]
    lines: list[str] = field(default_factory=list)
    done: bool = False
    error: str = ""
    _task: BackgroundTask | None = None

    def start(self) -> None:
        self._task = BackgroundTask("dresg-install", self._run)
        self._task.start()

    def wait(self, timeout: float | None = None) -> None:
        """Wait for the commands, then apply their output (main thread)."""
        if self._task is not None:
            self._task.join(timeout)
        self.poll()

    def poll(self) -> bool:
        """Apply what the worker posted (main thread); True once every command has run or one failed."""
        events = self._task.events() if self._task is not None else []
        for kind, payload in events:
            if kind == "line":
                self.lines = [*self.lines[-(TAIL_LINES - 1) :], payload]
            elif kind in ("done", "cancelled", "error"):
                self.done, self.error = True, payload if kind == "error" else ""
        if events:
            tag_redraw()
        return self.done

    @property
    def status(self) -> str:
        return self.lines[-1] if self.lines else "Starting..."

    def _run(self, post, cancel) -> None:  # worker thread: no bpy
        tail: list[str] = []
        for command in self.commands:
            try:
                process = subprocess.Popen(
                    command,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT,
                    text=True,
                    env={**os.environ, "PYTHONNOUSERSITE": "1"},
                )
            except OSError as error:
                raise DresgError(f"cannot run {command[0]}: {error}") from None
            for line in process.stdout:
                if line.strip():
                    tail = [*tail[-2:], line.rstrip()]
                    post("line", line.rstrip())
            if process.wait() != 0:
                output = " | ".join(tail) or "no output"
                raise DresgError(f"'{' '.join(command[1:4])}' failed (exit code {process.returncode}): {output}")


_installer: Installer | None = None


def current_installer() -> Installer | None:
    return _installer


class DRESG_OT_install_dependencies(bpy.types.Operator):
    """Install PyTorch into the add-on's user folder (a large download, several minutes)"""

    bl_idname = "dresg.install_dependencies"
    bl_label = "Install Dependencies"
    bl_options = {"REGISTER", "INTERNAL"}

    index_url: bpy.props.StringProperty(
        name="Index URL", description="Package index to install from (empty: pip's default, PyPI)"
    )

    _timer = None

    @classmethod
    def poll(cls, context):
        if _installer is not None and not _installer.done:
            cls.poll_message_set("An installation is already running")
            return False
        return True

    def execute(self, context):
        global _installer
        _installer = Installer(pip_commands(site_packages_dir(create=True), index_url=self.index_url))
        _installer.start()
        if bpy.app.background:
            _installer.wait()
            return self._finish(context)
        self._timer = context.window_manager.event_timer_add(0.5, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if not _installer.poll():
            context.workspace.status_text_set(f"Installing PyTorch: {_installer.status}")
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        context.workspace.status_text_set(None)
        return self._finish(context)

    def _finish(self, context):
        if _installer.error:
            self.report({"ERROR"}, f"Installing PyTorch failed: {_installer.error}")
            return {"CANCELLED"}
        add_site_packages()
        if not torch_available():
            self.report({"ERROR"}, f"pip finished but torch is still not importable from {site_packages_dir()}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"PyTorch installed in {site_packages_dir()}")
        return {"FINISHED"}


classes = (DRESG_OT_install_dependencies,)
