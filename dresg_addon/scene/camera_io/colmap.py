"""COLMAP sparse models (``cameras`` + ``images``, text or binary): read."""

from __future__ import annotations

import os
import struct
import warnings
from pathlib import Path

import numpy as np

from ...util.errors import CameraError, with_path
from ..camera import Camera
from .common import _camera, _check_regular, _finite, _no_cameras, _read_text, rigid_matrix

# model id -> (name, parameter count); the first five are perspective, read as pinhole
COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_MODEL_IDS = {name: model_id for model_id, (name, _) in COLMAP_MODELS.items()}
_SINGLE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")  # f, cx, cy, ...
_TWO_FOCALS = ("PINHOLE", "OPENCV", "FULL_OPENCV")  # fx, fy, cx, cy, ...


def find_colmap_model(path: str | os.PathLike, required: bool = True) -> tuple[Path, str] | None:
    """(folder, ``'.bin'`` or ``'.txt'``) of the COLMAP model at ``path``.

    ``path`` may be the folder holding ``cameras`` + ``images``, a dataset folder with ``sparse/0`` or
    ``sparse``, or one of the model files (its format is preferred). Binary wins over text otherwise.
    """
    path = Path(path)
    suffixes = (".bin", ".txt")
    if path.is_file():
        folder = path.parent
        candidates = [folder]
        if path.suffix.lower() == ".txt":
            suffixes = (".txt", ".bin")
    else:
        folder = path
        candidates = [path, path / "sparse" / "0", path / "sparse"]
    for candidate in candidates:
        for suffix in suffixes:
            if (candidate / f"cameras{suffix}").is_file() and (candidate / f"images{suffix}").is_file():
                return candidate, suffix
    if not required:
        return None
    raise CameraError(
        with_path(folder, "no COLMAP model (cameras + images, .bin or .txt) here or in sparse/0 or sparse")
    )


def read_colmap(path: str | os.PathLike) -> list[Camera]:
    """Read a COLMAP sparse model (text or binary); cameras are sorted by image name.

    Perspective models with distortion (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV) are read as pinhole
    and a warning says so when their distortion is not zero; fisheye models raise ``CameraError``.
    """
    folder, suffix = find_colmap_model(path)
    if suffix == ".bin":
        intrinsics = _read_colmap_cameras_bin(folder / "cameras.bin")
        images = _read_colmap_images_bin(folder / "images.bin")
    else:
        intrinsics = _read_colmap_cameras_txt(folder / "cameras.txt")
        images = _read_colmap_images_txt(folder / "images.txt")
    images_path = folder / f"images{suffix}"
    if not images:
        raise _no_cameras(images_path)
    cameras = []
    for image_id, quat, translation, camera_id, name in sorted(images, key=lambda image: image[4]):
        where = with_path(images_path, f"image {image_id} ({name})")
        if camera_id not in intrinsics:
            raise CameraError(f"{where}: refers to camera {camera_id}, which cameras{suffix} does not define")
        rotation = quaternion_to_rotation(quat, where)
        w2c = rigid_matrix(rotation, _finite(translation, where))
        width, height, fx, fy, cx, cy = intrinsics[camera_id]
        cameras.append(_camera(where, width, height, fx, fy, cx, cy, w2c, name))
    return cameras


def quaternion_to_rotation(quat, where: str = "quaternion") -> np.ndarray:  # [3, 3]
    """Rotation matrix of a (w, x, y, z) quaternion, normalised first; ``CameraError`` if it is zero."""
    q = _finite(quat, where)
    norm = float(np.linalg.norm(q))
    if norm < 1e-12:
        raise CameraError(f"{where}: quaternion is zero")
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _colmap_intrinsics(model: str, width, height, params, where: str) -> tuple:
    """(width, height, fx, fy, cx, cy) of a COLMAP camera read as a pinhole."""
    if model in _SINGLE_FOCAL:
        f, cx, cy, *distortion = params
        fx = fy = f
    elif model in _TWO_FOCALS:
        fx, fy, cx, cy, *distortion = params
    else:
        raise CameraError(f"{where}: camera model {model} is not supported (use a perspective model, e.g. PINHOLE)")
    if any(value != 0 for value in distortion):
        warnings.warn(f"{where}: {model} distortion is ignored (read as a pinhole camera)", stacklevel=4)
    return width, height, fx, fy, cx, cy


def _read_colmap_cameras_txt(path: Path) -> dict[int, tuple]:
    intrinsics = {}
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = with_path(path, f"line {number}")
        fields = line.split()
        if len(fields) < 4:
            raise CameraError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")
        model = fields[1]
        if model not in _MODEL_IDS:
            raise CameraError(f"{where}: unknown camera model {model}")
        expected = COLMAP_MODELS[_MODEL_IDS[model]][1]
        if len(fields) != 4 + expected:
            raise CameraError(f"{where}: {model} needs {expected} parameters, found {len(fields) - 4}")
        try:
            camera_id, width, height = int(fields[0]), int(fields[2]), int(fields[3])
            params = [float(value) for value in fields[4:]]
        except ValueError as error:
            raise CameraError(f"{where}: malformed number ({error})") from None
        intrinsics[camera_id] = _colmap_intrinsics(model, width, height, params, where)
    return intrinsics


def _read_colmap_images_txt(path: Path) -> list[tuple]:
    images = []
    lines = _read_text(path).splitlines()
    number = 0
    while number < len(lines):
        line = lines[number].strip()
        number += 1
        if not line or line.startswith("#"):
            continue
        where = with_path(path, f"line {number}")
        fields = line.split(maxsplit=9)  # the name may contain spaces
        if len(fields) != 10:
            raise CameraError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        try:
            image_id, camera_id = int(fields[0]), int(fields[8])
            values = [float(value) for value in fields[1:8]]
        except ValueError as error:
            raise CameraError(f"{where}: malformed number ({error})") from None
        images.append((image_id, values[:4], values[4:], camera_id, fields[9]))
        number += 1  # the next line lists the image's 2D points (possibly empty)
    return images


class _Reader:
    """Bounds-checked little-endian reads from a bytes buffer."""

    def __init__(self, path: Path):
        self.path = path
        _check_regular(path)
        try:
            self.data = path.read_bytes()
        except OSError as error:
            raise CameraError(with_path(path, f"cannot read: {error}")) from None
        self.offset = 0

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        self.skip(size)
        return struct.unpack_from("<" + fmt, self.data, self.offset - size)

    def skip(self, size: int) -> None:
        if self.offset + size > len(self.data):
            raise CameraError(with_path(self.path, f"truncated data at byte {self.offset}"))
        self.offset += size

    def read_name(self) -> str:
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise CameraError(with_path(self.path, f"truncated data at byte {self.offset} (unterminated name)"))
        name = self.data[self.offset : end].decode("utf-8", errors="replace")
        self.offset = end + 1
        return name


def _read_colmap_cameras_bin(path: Path) -> dict[int, tuple]:
    reader = _Reader(path)
    (count,) = reader.read("Q")
    intrinsics = {}
    for _ in range(count):
        camera_id, model_id, width, height = reader.read("iiQQ")
        where = with_path(path, f"camera {camera_id}")
        if model_id not in COLMAP_MODELS:
            raise CameraError(f"{where}: unknown camera model id {model_id}")
        model, param_count = COLMAP_MODELS[model_id]
        params = reader.read(f"{param_count}d")
        intrinsics[camera_id] = _colmap_intrinsics(model, width, height, params, where)
    return intrinsics


def _read_colmap_images_bin(path: Path) -> list[tuple]:
    reader = _Reader(path)
    (count,) = reader.read("Q")
    images = []
    for _ in range(count):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.read("i7di")
        name = reader.read_name()
        (point_count,) = reader.read("Q")
        reader.skip(24 * point_count)  # (x, y, point3D_id) per 2D point
        images.append((image_id, [qw, qx, qy, qz], [tx, ty, tz], camera_id, name))
    return images
