"""Scene file I/O: graphdeco PLY, antimatter15 ``.splat`` and PlayCanvas compressed PLY.

>>> scene = read_scene("point_cloud.ply")          # format from the content (and .splat extension)
>>> write_scene(scene, "point_cloud.splat")         # format from the extension, written atomically

Every problem with a file is a one-line :class:`~dresg_addon.util.errors.SceneFormatError` naming it.
Splats with non-finite values are an error unless ``drop_invalid=True``, which drops them and
reports how many (``read_scene_detailed(...).dropped``, or an :class:`InvalidSplatsWarning` from
:func:`read_scene`).
"""

from __future__ import annotations

import enum
import os
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ...util.errors import SceneFormatError, with_path
from ...util.fileutil import atomic_write_with, irregular_file_problem
from ..gaussians import GaussianScene
from .compressed_ply import encode_compressed, is_compressed, read_compressed
from .ply import encode_graphdeco, read_graphdeco
from .ply_container import is_ply, parse_header
from .splat import encode_splat, read_splat

__all__ = [
    "READABLE_EXTENSIONS",
    "WRITABLE_EXTENSIONS",
    "ClampedColoursWarning",
    "InvalidSplatsWarning",
    "SceneFormat",
    "SceneReadResult",
    "output_format",
    "read_scene",
    "read_scene_detailed",
    "write_scene",
]


# For file browsers: what read_scene opens (compressed PLY files end in .ply too).
READABLE_EXTENSIONS = (".ply", ".splat")
WRITABLE_EXTENSIONS = (".ply", ".compressed.ply", ".splat")


class SceneFormat(enum.Enum):
    GRAPHDECO_PLY = "graphdeco PLY"
    SPLAT = "antimatter15 .splat"
    COMPRESSED_PLY = "PlayCanvas compressed PLY"


class InvalidSplatsWarning(UserWarning):
    """Splats with non-finite values were dropped while reading (``drop_invalid=True``)."""


class ClampedColoursWarning(UserWarning):
    """Colour (SH) coefficients far outside any displayable range were clamped while reading."""


# |SH coefficient| beyond this is no colour (the DC term's colour would be 0.5 +- 2821; real ones stay
# within a few units): clamp on read, so a corrupt splat cannot overflow the float32 fit loss of a run.
SH_LIMIT = 1e4


@dataclass
class SceneReadResult:
    scene: GaussianScene
    format: SceneFormat
    dropped: int  # splats dropped for non-finite values (only with drop_invalid=True)
    file_size: int  # bytes
    clamped: int = 0  # splats whose SH coefficients were clamped to +-SH_LIMIT


def read_scene(path: str | os.PathLike, drop_invalid: bool = False) -> GaussianScene:
    """Read a scene file; see :func:`read_scene_detailed`. Dropping splats emits an InvalidSplatsWarning."""
    result = read_scene_detailed(path, drop_invalid=drop_invalid)
    if result.dropped:
        message = with_path(path, f"dropped {result.dropped} splats with non-finite values (NaN or Inf)")
        warnings.warn(message, InvalidSplatsWarning, stacklevel=2)
    if result.clamped:
        warnings.warn(with_path(path, clamped_note(result.clamped)), ClampedColoursWarning, stacklevel=2)
    return result.scene


def clamped_note(count: int) -> str:
    return f"clamped the colour coefficients of {count} splats to +-{SH_LIMIT:g} (far outside any colour)"


def read_scene_detailed(path: str | os.PathLike, drop_invalid: bool = False) -> SceneReadResult:
    """Read a scene file, detecting its format from the content (PLY) or the ``.splat`` extension.

    Raises SceneFormatError for a missing, empty, truncated or malformed file, for zero splats, and
    for non-finite values unless ``drop_invalid`` (then those splats are dropped and counted).
    """
    data = _read_bytes(path)
    if not data:
        raise SceneFormatError(with_path(path, "empty file"))
    with np.errstate(all="ignore"):  # a corrupt file's overflows become non-finite values, refused below
        fmt, scene = _decode(path, data)
    invalid = scene.invalid_mask()
    dropped = int(invalid.sum())
    if dropped:
        if not drop_invalid:
            raise SceneFormatError(
                with_path(
                    path,
                    f"{dropped} of {len(scene)} splats have non-finite values (NaN or Inf); "
                    "read with drop_invalid (--drop-invalid) to drop them",
                )
            )
        if dropped == len(scene):
            raise SceneFormatError(with_path(path, f"all {dropped} splats have non-finite values"))
        scene = scene.subset(~invalid)
    scene, clamped = _clamp_colours(scene)
    return SceneReadResult(scene, fmt, dropped, len(data), clamped)


def _clamp_colours(scene: GaussianScene) -> tuple[GaussianScene, int]:
    """The scene with SH coefficients clamped to +-SH_LIMIT, and how many splats had some beyond it."""
    extreme = (np.abs(scene.sh_dc) > SH_LIMIT).any(1)
    if scene.sh_rest is not None:
        extreme |= (np.abs(scene.sh_rest) > SH_LIMIT).any((1, 2))
    count = int(extreme.sum())
    if not count:
        return scene, 0
    rest = None if scene.sh_rest is None else np.clip(scene.sh_rest, -SH_LIMIT, SH_LIMIT)
    return replace(scene, sh_dc=np.clip(scene.sh_dc, -SH_LIMIT, SH_LIMIT), sh_rest=rest), count


def _decode(path, data: bytes) -> tuple[SceneFormat, GaussianScene]:
    """The format and the scene of a file's bytes (format from the content, or the .splat extension)."""
    if is_ply(data):
        header = parse_header(path, data)
        if is_compressed(header):
            return SceneFormat.COMPRESSED_PLY, read_compressed(path, data, header)
        return SceneFormat.GRAPHDECO_PLY, read_graphdeco(path, data, header)
    if Path(path).suffix.lower() == ".splat":
        return SceneFormat.SPLAT, read_splat(path, data)
    if data[:2] == b"\x1f\x8b":
        raise SceneFormatError(
            with_path(path, "gzip data (e.g. Niantic .spz) is not supported; convert it to .ply first")
        )
    raise SceneFormatError(
        with_path(path, "unknown scene format: not a PLY file, and only files named .splat are read as .splat")
    )


def _read_bytes(path) -> bytes:
    problem = irregular_file_problem(path)
    if problem:
        raise SceneFormatError(with_path(path, problem))
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise SceneFormatError(with_path(path, "file not found")) from None
    except IsADirectoryError:
        raise SceneFormatError(with_path(path, "is a directory, not a scene file")) from None
    except OSError as error:
        raise SceneFormatError(with_path(path, f"cannot read: {error.strerror or error}")) from None


def output_format(path: str | os.PathLike) -> SceneFormat:
    """The format ``write_scene`` uses for ``path``: .splat, .compressed.ply, else .ply (graphdeco)."""
    name = Path(path).name.lower()
    if name.endswith(".compressed.ply"):
        return SceneFormat.COMPRESSED_PLY
    if name.endswith(".ply"):
        return SceneFormat.GRAPHDECO_PLY
    if name.endswith(".splat"):
        return SceneFormat.SPLAT
    raise SceneFormatError(
        with_path(path, f"unknown output extension {Path(path).suffix!r} (use .ply, .compressed.ply or .splat)")
    )


def write_scene(scene: GaussianScene, path: str | os.PathLike) -> SceneFormat:
    """Write ``scene`` in the format given by the extension of ``path`` and return that format.

    The bytes are built in memory first and land atomically (temporary file, then rename), so a
    failed write leaves any previous file untouched. Scenes with non-finite values are refused.
    """
    fmt, parts = _encode(scene, path)
    atomic_write_with(path, lambda tmp: _write_parts(tmp, parts))  # WriteError with the system's reason
    return fmt


def encoded_size(scene: GaussianScene, path: str | os.PathLike) -> int:
    """The bytes :func:`write_scene` would write for ``scene`` at ``path`` (its format), without writing."""
    return sum(len(part) for part in _encode(scene, path)[1])


def _encode(scene: GaussianScene, path) -> tuple[SceneFormat, list[bytes | memoryview]]:
    fmt = output_format(path)
    invalid = int(scene.invalid_mask().sum())
    if invalid:
        raise SceneFormatError(with_path(path, f"refusing to write {invalid} splats with non-finite values"))
    if len(scene) == 0:
        raise SceneFormatError(with_path(path, "refusing to write a scene with no splats"))
    with np.errstate(all="ignore"):  # out-of-range values are clipped by each encoder
        if fmt is SceneFormat.GRAPHDECO_PLY:
            return fmt, encode_graphdeco(scene, path)
        if fmt is SceneFormat.SPLAT:
            return fmt, encode_splat(scene)
        return fmt, encode_compressed(scene)


def _write_parts(path: str, parts: list[bytes | memoryview]) -> None:
    with open(path, "wb") as stream:
        for part in parts:
            stream.write(part)
