"""Read cameras from a path, choosing the format from what it is."""

from __future__ import annotations

import os
from pathlib import Path

from ...util.errors import CameraError, with_path
from ..camera import Camera
from .cameras_json import read_cameras_json
from .colmap import find_colmap_model, read_colmap
from .common import _check_resize, resize_cameras
from .llff import read_llff


def load_cameras(
    path: str | os.PathLike,
    *,
    factor: float | None = None,
    width: int | None = None,
    height: int | None = None,
) -> list[Camera]:
    """Read cameras from ``path``, choosing the format from what it is.

    ``.json``: graphdeco ``cameras.json``; ``.npy``: LLFF ``poses_bounds.npy``; ``.bin`` / ``.txt`` or a
    folder: COLMAP (the folder itself, ``sparse/0`` or ``sparse`` below it). A folder without a COLMAP
    model is searched for ``cameras.json``, then ``poses_bounds.npy``.

    ``factor`` divides every image size (``factor=8`` for ``images_8``); ``width`` / ``height`` set the
    image size directly (one of them keeps the aspect ratio). Intrinsics are scaled to match.
    """
    _check_resize(factor, width, height)
    path = Path(path)
    if not path.exists():
        raise CameraError(with_path(path, "no such file or folder"))
    if path.is_dir():
        if find_colmap_model(path, required=False) is not None:
            return resize_cameras(read_colmap(path), factor=factor, width=width, height=height)
        if (path / "cameras.json").is_file():
            return resize_cameras(read_cameras_json(path / "cameras.json"), factor=factor, width=width, height=height)
        if (path / "poses_bounds.npy").is_file():
            return read_llff(path / "poses_bounds.npy", factor=factor, width=width, height=height)
        raise CameraError(
            with_path(path, "no cameras found (looked for a COLMAP model, cameras.json and poses_bounds.npy)")
        )
    suffix = path.suffix.lower()
    if suffix == ".json":
        cameras = read_cameras_json(path)
    elif suffix == ".npy":
        return read_llff(path, factor=factor, width=width, height=height)
    elif suffix in (".bin", ".txt"):
        cameras = read_colmap(path)
    else:
        raise CameraError(with_path(path, "unknown camera file type (expected .json, .npy, .bin, .txt or a folder)"))
    return resize_cameras(cameras, factor=factor, width=width, height=height)
