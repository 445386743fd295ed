"""Atomic writes: build the bytes first, touch the disk last (temporary file in the same folder, then rename).

The temporary file is ``.NAME.PID.RANDOM.tmpSUFFIX`` beside the target. It is created with mode 0666
less the umask (as ``open`` would create the target), or with the target's own mode when it is being
replaced, so a written file has the permissions users expect rather than ``mkstemp``'s 0600. A process
killed mid-write leaves its temporary file behind; the next write to the same target removes those
whose process is gone.
"""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Callable
from pathlib import Path

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


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files of earlier atomic writes to ``path`` whose writing process is gone."""
    path = Path(path)
    removed = []
    for candidate in path.parent.glob(f".{path.name}.*{TEMP_MARK}*"):
        parts = candidate.name[len(path.name) + 2 :].split(".")
        if len(parts) < 3 or not parts[0].isdigit() or int(parts[0]) == os.getpid():
            continue  # not ours, or this process's own write in progress
        if not _process_alive(int(parts[0])):
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
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    suffix = path.suffix if suffix is None else suffix
    tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{TEMP_MARK}{suffix}"
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        mode = None
    fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)  # the kernel applies the umask
    os.close(fd)
    try:
        if mode is not None:
            os.chmod(tmp, mode)
        writer(str(tmp))
        os.replace(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise
