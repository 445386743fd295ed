"""What every camera reader shares: limits, checks that raise ``CameraError`` naming the file, and resizing."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ...util.errors import CameraError, ConfigError, with_path
from ...util.fileutil import irregular_file_problem
from ..camera import Camera

MAX_IMAGE_SIDE = 16384  # pixels; a camera wider or taller than this is refused on read (a 16k render is ~3 GB)
ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| accepted from files (rounded decimals), then projected
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp")


def checked_rotation(matrix, where: str) -> np.ndarray:  # [3, 3]
    """The nearest proper rotation to ``matrix``; ``CameraError`` if it is singular, mirrored or skewed.

    ``where`` names the source in the message (``'cameras.json: camera 3'``).
    """
    r = np.asarray(matrix, dtype=np.float64)
    if r.shape != (3, 3):
        raise CameraError(f"{where}: rotation has shape {r.shape}, expected (3, 3)")
    if not np.isfinite(r).all():
        raise CameraError(f"{where}: rotation has non-finite values")
    det = float(np.linalg.det(r))
    if abs(det) < 1e-6:
        raise CameraError(f"{where}: rotation is singular (determinant {det:.3g})")
    if det < 0:
        raise CameraError(f"{where}: rotation is a reflection (determinant {det:.3g})")
    error = float(np.abs(r.T @ r - np.eye(3)).max())
    if error > ROTATION_TOLERANCE:
        raise CameraError(f"{where}: rotation is not orthonormal (|R^T R - I| = {error:.3g})")
    u, _, vt = np.linalg.svd(r)
    return u @ vt


def rigid_matrix(rotation, translation) -> np.ndarray:  # [4, 4]
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def _finite(values, where: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    if not np.isfinite(array).all():
        raise CameraError(f"{where}: non-finite values")
    return array


def _image_size(width, height, where: str) -> tuple[int, int]:
    size = []
    for label, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise CameraError(f"{where}: {label} {value!r} is not a number")
        if isinstance(value, float) and not math.isfinite(value):
            raise CameraError(f"{where}: {label} {value!r} is not a number")
        if value < 1 or value != int(value):
            raise CameraError(f"{where}: {label} {_short(value)} must be a positive whole number")
        if value > MAX_IMAGE_SIDE:
            raise CameraError(f"{where}: {label} {_short(value)} is larger than the {MAX_IMAGE_SIDE} pixels supported")
        size.append(int(value))
    return size[0], size[1]


def _short(value) -> str:
    """A number for a message: huge integers as their digit count (their repr can be thousands of characters)."""
    text = repr(value)
    return text if len(text) <= 24 else f"of {len(text)} digits"


def _camera(where: str, width, height, fx, fy, cx, cy, w2c, name: str) -> Camera:
    width, height = _image_size(width, height, where)
    for label, value in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        _finite(value, f"{where}: {label}")
    intrinsics = np.asarray([fx, fy, cx, cy], dtype=np.float64)
    if intrinsics[0] <= 0 or intrinsics[1] <= 0:
        raise CameraError(f"{where}: focal lengths fx={intrinsics[0]:g}, fy={intrinsics[1]:g} must be positive")
    return Camera(width, height, *map(float, intrinsics), world_to_camera=w2c, name=name)


def _no_cameras(path) -> CameraError:
    return CameraError(with_path(path, "contains no cameras"))


def resize_cameras(
    cameras: list[Camera], *, factor: float | None = None, width: int | None = None, height: int | None = None
) -> list[Camera]:
    """Cameras for resampled images: sizes divided by ``factor``, or set to ``width`` and/or ``height``."""
    _check_resize(factor, width, height)
    if factor is None and width is None and height is None:
        return list(cameras)
    resized = []
    for camera in cameras:
        if factor is not None:
            w, h = round(camera.width / factor), round(camera.height / factor)
        elif width is not None and height is not None:
            w, h = width, height
        elif width is not None:
            w, h = width, round(camera.height * width / camera.width)
        else:
            w, h = round(camera.width * height / camera.height), height
        if w < 1 or h < 1:
            raise ConfigError(f"camera {camera.name!r}: {camera.width}x{camera.height} resized to {w}x{h} is empty")
        resized.append(camera.resized(w, h))
    return resized


def _check_resize(factor, width, height) -> None:
    if factor is not None and (width is not None or height is not None):
        raise ConfigError("give either a downscale factor or a target width/height, not both")
    if factor is not None and not (math.isfinite(factor) and factor > 0):
        raise ConfigError(f"downscale factor {factor} must be a positive number")
    for label, value in (("width", width), ("height", height)):
        if value is not None and value < 1:
            raise ConfigError(f"target {label} {value} must be at least 1")


def _check_regular(path: Path) -> None:
    problem = irregular_file_problem(path)
    if problem:
        raise CameraError(with_path(path, problem))


def _read_text(path: Path) -> str:
    _check_regular(path)
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise CameraError(with_path(path, f"cannot read: {error}")) from None
