"""Atomic, durable writes: build the bytes first, touch the disk last (temporary file in the same folder, flushed
to the disk, then renamed over the target, then the folder flushed).

Every step is checked, the writer's own close included: a full disk, a file-size limit or a missing
permission raises :class:`WriteError` ("PATH: cannot write: No space left on device"), the temporary file
is removed, and the file that was at the target stays as it was. The fsync of the temporary file before
the rename, and of the folder after it, is what keeps a power cut from leaving an empty file where a good
one was (ext4 and XFS may otherwise commit the rename before the data).

The temporary file is ``.NAME.PID.RANDOM.tmpSUFFIX`` beside the target. It is created with mode 0666
less the umask (as ``open`` would create the target), or with the target's own mode when it is being
replaced, so a written file has the permissions users expect rather than ``mkstemp``'s 0600. A process
killed mid-write leaves its temporary file behind; the next write to the same target removes those
whose process is gone.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import stat
from collections.abc import Callable
from pathlib import Path

from .errors import WriteError, with_path
from .machine import process_alive

TEMP_MARK = ".tmp"


def irregular_file_problem(path: str | os.PathLike) -> str | None:
    """What is wrong with reading ``path`` as a file when it is not a regular one (after symlinks), or None.

    A FIFO blocks forever and a device (``/dev/zero``) never ends, so readers refuse both up front;
    a missing path is left to the caller's own message.
    """
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    kind = "a FIFO" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a socket"
    return f"is {kind}, not a regular file"


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see either the old file or the whole new one."""
    atomic_write_with(path, lambda tmp: Path(tmp).write_bytes(data))


def check_room(needs: dict[Path, int]) -> None:
    """Before a long run: each folder of ``needs`` (folder -> bytes the run will write there) can be created
    and written to, and its file system has room for what every folder on it needs; else WriteError."""
    devices: dict[int, tuple[Path, int]] = {}
    for folder, size in needs.items():
        try:
            folder.mkdir(parents=True, exist_ok=True)
            probe = folder / f".write-probe.{os.getpid()}.{secrets.token_hex(4)}{TEMP_MARK}"
            os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
            probe.unlink()
            device = os.stat(folder).st_dev
        except OSError as error:
            raise write_problem(folder, error) from None
        first, total = devices.get(device, (folder, 0))
        devices[device] = (first, total + size)
    for folder, total in devices.values():
        free = shutil.disk_usage(folder).free
        if free < total:
            raise WriteError(
                with_path(
                    folder,
                    f"not enough room: this run writes up to {total / 1e6:.0f} MB here, {free / 1e6:.0f} MB free",
                )
            )


def write_problem(path: str | os.PathLike, error: OSError) -> WriteError:
    """The one-line error for a failed write to ``path``: the path and the system's reason."""
    return WriteError(with_path(path, f"cannot write: {error.strerror or error}"))


def append_text(path: str | os.PathLike, text: str) -> None:
    """Append ``text`` to ``path`` (a log), flushed and synced; a failed write raises :class:`WriteError`."""
    try:
        with open(path, "a", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
    except OSError as error:
        raise write_problem(path, error) from None


def _fsync_path(path: Path, directory: bool = False) -> None:
    """Flush ``path`` to the disk; a folder only where the OS can open one (not Windows)."""
    if directory and os.name == "nt":
        return
    fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files of earlier atomic writes to ``path`` whose writing process is gone."""
    path = Path(path)
    removed = []
    for candidate in path.parent.glob(f".{path.name}.*{TEMP_MARK}*"):
        parts = candidate.name[len(path.name) + 2 :].split(".")
        if len(parts) < 3 or not parts[0].isdigit() or int(parts[0]) == os.getpid():
            continue  # not ours, or this process's own write in progress
        if not process_alive(int(parts[0])):
            try:
                candidate.unlink()
                removed.append(candidate)
            except OSError:
                pass  # gone already, or not ours to remove: leave it
    return removed


def atomic_write_with(path: str | os.PathLike, writer: Callable[[str], None], suffix: str | None = None) -> None:
    """Call ``writer(tmp_path)`` on a temporary file beside ``path``, then rename it over ``path``.

    ``suffix`` defaults to the target's suffix, so writers that pick a format by extension (OpenImageIO)
    still see the right one.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise write_problem(path, error) from None
    remove_stale_temporaries(path)
    suffix = path.suffix if suffix is None else suffix
    tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{TEMP_MARK}{suffix}"
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        mode = None
    try:
        fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)  # the kernel applies the umask
        os.close(fd)
    except OSError as error:
        raise write_problem(path, error) from None
    try:
        if mode is not None:
            os.chmod(tmp, mode)
        writer(str(tmp))
        _fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException as error:
        with contextlib.suppress(OSError):  # never created, or already gone
            tmp.unlink()
        if isinstance(error, OSError):
            raise write_problem(path, error) from None
        raise
    with contextlib.suppress(OSError):  # the file is complete and in place; only the rename's durability is left
        _fsync_path(path.parent, directory=True)
