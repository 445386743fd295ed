"""PyTorch for the optimizer: used when importable, otherwise installed on request.

torch is far too large to ship inside the extension, so "Install Dependencies" runs pip in a
subprocess (``pip install --target``) into a folder of the add-on's user directory, which survives
extension upgrades, and puts that folder on ``sys.path``. Import, export and viewing never need torch.
"""

import contextlib
import importlib
import importlib.util
import os
import queue
import signal
import subprocess
import sys
import threading
from pathlib import Path

import bpy

from ..dresg_addon.util.errors import CancelledError, DresgError
from . import ADDON_PACKAGE
from .tasks import CancelJobOperator, Job, JobOperator, JobState

TORCH_REQUIREMENT = "torch==2.13.0"
TAIL_LINES = 12  # output lines kept for the panel and for error messages
STOP_GRACE = 5.0  # seconds pip gets to exit after SIGTERM before it is killed
CANCELLED_MESSAGE = "Installation cancelled: pip was stopped; Install Dependencies starts it again"


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


class Installer(Job):
    """Runs commands one after another as a :class:`~.tasks.Job`, keeping the last lines of output.

    The worker posts each output line; :meth:`~.tasks.Job.poll` (main thread) applies them to ``lines`` and
    ``text``, which the panels read. Cancelling stops the running command and what it started: the worker
    checks the request ten times a second, even while the command prints nothing.
    """

    kind = "install"

    def __init__(self, commands: list[list[str]]) -> None:
        super().__init__()
        self.commands = commands
        self.lines: list[str] = []

    def _update(self, events) -> None:
        for _, line in events:  # only output lines
            self.lines = [*self.lines[-(TAIL_LINES - 1) :], line]
        self.text = "Cancelling..." if self.cancel_requested else self.lines[-1]

    def _on_end(self) -> None:
        if self.state is JobState.CANCELLED:
            self.text = CANCELLED_MESSAGE

    def _work(self, post, cancel) -> None:  # worker thread: no bpy
        for command in self.commands:
            if cancel.is_set():
                raise CancelledError(CANCELLED_MESSAGE)
            _run_command(command, post, cancel)


def _run_command(command: list[str], post, cancel: threading.Event) -> None:
    """Run ``command``, posting its output lines; stop it (and its children) when ``cancel`` is set."""
    try:
        process = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONNOUSERSITE": "1"},
            start_new_session=True,  # its own process group, so a cancel reaches what pip starts (POSIX)
        )
    except OSError as error:
        raise DresgError(f"cannot run {command[0]}: {error}") from None
    output: queue.SimpleQueue = queue.SimpleQueue()
    # A reader thread, so the worker sees a cancel while the command is silent (a download).
    threading.Thread(
        target=_read_lines, args=(process.stdout, output), name="dresg-install-output", daemon=True
    ).start()
    tail: list[str] = []
    while True:
        if cancel.is_set():
            _stop(process)
            raise CancelledError(CANCELLED_MESSAGE)
        try:
            line = output.get(timeout=0.1)
        except queue.Empty:
            continue
        if line is None:  # the command closed its output
            break
        if line.strip():
            tail = [*tail[-2:], line.rstrip()]
            post("line", line.rstrip())
    if process.wait() != 0:
        text = " | ".join(tail) or "no output"
        raise DresgError(f"'{' '.join(command[1:4])}' failed (exit code {process.returncode}): {text}")


def _read_lines(stream, output: queue.SimpleQueue) -> None:
    try:
        for line in stream:
            output.put(line)
    finally:  # None ends the worker's loop even if reading failed
        output.put(None)


def _stop(process: subprocess.Popen) -> None:
    """SIGTERM to the command and what it started, SIGKILL to whatever is left after ``STOP_GRACE`` seconds."""
    _signal(process, signal.SIGTERM)
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(STOP_GRACE)
    _signal(process, getattr(signal, "SIGKILL", signal.SIGTERM))
    process.wait()


def _signal(process: subprocess.Popen, sig: int) -> None:
    if os.name != "posix":
        process.terminate()  # Windows: the command only
        return
    with contextlib.suppress(ProcessLookupError):  # the group is empty: nothing left to stop
        os.killpg(process.pid, sig)


class DRESG_OT_install_dependencies(JobOperator, bpy.types.Operator):
    """Install PyTorch into the add-on's user folder (a large download, several minutes); Esc cancels"""

    bl_idname = "dresg.install_dependencies"
    bl_label = "Install Dependencies"
    bl_options = {"REGISTER", "INTERNAL"}

    index_url: bpy.props.StringProperty(
        name="Index URL", description="Package index to install from (empty: pip's default, PyPI)"
    )

    _interval = 0.5
    _interrupted = "Installation cancelled: Blender ended it (was another file opened?); pip was stopped"

    @classmethod
    def poll(cls, context):
        if Installer.active() is not None:
            cls.poll_message_set("An installation is already running")
            return False
        return True

    def execute(self, context):
        installer = Installer(pip_commands(site_packages_dir(create=True), index_url=self.index_url))
        if bpy.app.background:
            return self.run_here(context, installer)
        return self.run_modal(context, installer)

    def _show_progress(self, context, job) -> None:
        context.workspace.status_text_set(None if job is None else f"Installing PyTorch: {job.text}")

    def _finish(self, context, installer: Installer):
        if installer.state is JobState.CANCELLED:
            self.report({"WARNING"}, installer.text)
            return {"CANCELLED"}
        if installer.state is JobState.ERROR:
            self.report({"ERROR"}, f"Installing PyTorch failed: {installer.error}")
            return {"CANCELLED"}
        add_site_packages()
        if not torch_available():
            self.report({"ERROR"}, f"pip finished but torch is still not importable from {site_packages_dir()}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"PyTorch installed in {site_packages_dir()}")
        return {"FINISHED"}


class DRESG_OT_cancel_install(CancelJobOperator, bpy.types.Operator):
    """Stop the PyTorch installation: pip and what it started are stopped"""

    bl_idname = "dresg.cancel_install"
    bl_label = "Cancel Installation"
    bl_options = {"INTERNAL"}
    _job_class = Installer


classes = (DRESG_OT_install_dependencies, DRESG_OT_cancel_install)
