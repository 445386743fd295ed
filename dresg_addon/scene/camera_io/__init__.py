"""Camera files: graphdeco ``cameras.json``, COLMAP sparse models and LLFF ``poses_bounds.npy``.

Every reader returns :class:`~dresg_addon.scene.camera.Camera` objects in the file's world frame (OpenCV /
COLMAP axes: x right, y down, z forward), float64, and raises :class:`~dresg_addon.util.errors.CameraError`
naming the file and the problem on bad input.

==================  ===============================================================================
format              what it stores
==================  ===============================================================================
``cameras.json``    graphdeco list of {id, img_name, width, height, position (centre), rotation
                    (camera-to-world 3x3, rows), fx, fy}; no principal point (image centre)
COLMAP              ``cameras`` (intrinsics) + ``images`` (qw qx qy qz tx ty tz world-to-camera), text or
                    binary, in ``sparse/0`` or any folder holding the files
LLFF                ``[N, 17]``: 3x5 = camera-to-world 3x4 with columns (down, right, backwards, centre)
                    and a column (H, W, focal), then near and far bounds
==================  ===============================================================================
"""

from __future__ import annotations

import json
import math
import os
import struct
import warnings
from pathlib import Path

import numpy as np

from ...util.errors import CameraError, ConfigError, DresgError, with_path
from ...util.fileutil import atomic_write_bytes, irregular_file_problem
from ..camera import Camera
from ..gaussians import GaussianScene
from ..splat_mesh import UP_AXIS_LABELS, up_axis_for
from ..up_axis import up_axis_from_splats

MAX_IMAGE_SIDE = 16384  # pixels; a camera wider or taller than this is refused on read (a 16k render is ~3 GB)
ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| accepted from files (rounded decimals), then projected
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp")


# ----------------------------------------------------------------------------------------------------
# Shared checks


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
    intrinsics = _finite([fx, fy, cx, cy], where)
    if intrinsics[0] <= 0 or intrinsics[1] <= 0:
        raise CameraError(f"{where}: focal lengths fx={intrinsics[0]:g}, fy={intrinsics[1]:g} must be positive")
    return Camera(width, height, *map(float, intrinsics), world_to_camera=w2c, name=name)


def _no_cameras(path) -> CameraError:
    return CameraError(with_path(path, "contains no cameras"))


# ----------------------------------------------------------------------------------------------------
# Dispatcher and resizing


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


# ----------------------------------------------------------------------------------------------------
# graphdeco cameras.json

_JSON_KEYS = ("width", "height", "position", "rotation", "fx", "fy")


def read_cameras_json(path: str | os.PathLike) -> list[Camera]:
    """Read a graphdeco ``cameras.json``; the principal point is the image centre unless ``cx``/``cy`` are present."""
    path = Path(path)
    _check_regular(path)
    try:
        entries = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CameraError(with_path(path, "no such file")) from None
    except (OSError, UnicodeDecodeError) as error:
        raise CameraError(with_path(path, f"cannot read: {error}")) from None
    except json.JSONDecodeError as error:
        raise CameraError(with_path(path, f"malformed JSON: {error}")) from None
    except ValueError as error:  # an integer of thousands of digits: Python's int conversion limit
        raise CameraError(with_path(path, f"malformed JSON: {str(error).splitlines()[0]}")) from None
    except RecursionError:
        raise CameraError(with_path(path, "malformed JSON: arrays or objects nested too deeply")) from None
    if not isinstance(entries, list):
        raise CameraError(with_path(path, f"expected a list of cameras, found {type(entries).__name__}"))
    if not entries:
        raise _no_cameras(path)
    cameras = []
    for index, entry in enumerate(entries):
        where = with_path(path, f"camera {index}")
        if not isinstance(entry, dict):
            raise CameraError(f"{where}: expected an object, found {type(entry).__name__}")
        missing = [key for key in _JSON_KEYS if key not in entry]
        if missing:
            raise CameraError(f"{where}: missing key{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
        try:
            position = np.asarray(entry["position"], dtype=np.float64)
            rotation = np.asarray(entry["rotation"], dtype=np.float64)
            fx, fy = float(entry["fx"]), float(entry["fy"])
            cx = float(entry.get("cx", entry["width"] / 2.0))
            cy = float(entry.get("cy", entry["height"] / 2.0))
        except (TypeError, ValueError, OverflowError) as error:
            raise CameraError(f"{where}: malformed values ({error})") from None
        if position.shape != (3,):
            raise CameraError(f"{where}: position has shape {position.shape}, expected (3,)")
        _finite(position, where)
        c2w = checked_rotation(rotation, where)
        w2c = rigid_matrix(c2w.T, -c2w.T @ position)
        name = str(entry.get("img_name", entry.get("id", index)))
        cameras.append(_camera(where, entry["width"], entry["height"], fx, fy, cx, cy, w2c, name))
    return cameras


def _cameras_json_text(cameras: list[Camera]) -> str:
    """graphdeco ``cameras.json`` text; ``cx``/``cy`` are added only where they are off the image centre."""
    entries = []
    for index, camera in enumerate(cameras):
        c2w = camera.camera_to_world
        entry = {
            "id": index,
            "img_name": camera.name,
            "width": camera.width,
            "height": camera.height,
            "position": [float(v) for v in c2w[:3, 3]],
            "rotation": [[float(v) for v in row] for row in c2w[:3, :3]],
            "fy": float(camera.fy),
            "fx": float(camera.fx),
        }
        if camera.cx != camera.width / 2.0 or camera.cy != camera.height / 2.0:
            entry["cx"], entry["cy"] = float(camera.cx), float(camera.cy)
        entries.append(entry)
    return json.dumps(entries, allow_nan=False)


def write_cameras_json(path: str | os.PathLike, cameras: list[Camera]) -> None:
    """Write graphdeco ``cameras.json`` atomically."""
    if not cameras:
        raise CameraError(with_path(path, "no cameras to write"))
    try:
        text = _cameras_json_text(cameras)
    except ValueError:
        raise CameraError(with_path(path, "cameras have non-finite values")) from None
    atomic_write_bytes(path, text.encode("utf-8"))


# ----------------------------------------------------------------------------------------------------
# COLMAP

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


# ----------------------------------------------------------------------------------------------------
# LLFF


def llff_to_opencv_c2w(pose) -> np.ndarray:  # [3, 5] -> [4, 4]
    """OpenCV camera-to-world matrix of one LLFF 3x5 pose.

    LLFF's columns are the camera's (down, right, backwards) axes and its centre in world coordinates,
    so OpenCV x (right) = column 1, y (down) = column 0, z (forward) = -column 2.
    """
    pose = np.asarray(pose, dtype=np.float64)
    rotation = np.stack([pose[:, 1], pose[:, 0], -pose[:, 2]], axis=1)
    return rigid_matrix(rotation, pose[:, 3])


def read_llff(
    path: str | os.PathLike,
    *,
    factor: float | None = None,
    width: int | None = None,
    height: int | None = None,
) -> list[Camera]:
    """Read LLFF ``poses_bounds.npy`` (full-resolution H, W, focal), resized like :func:`resize_cameras`.

    Names are the sorted image file names of the matching image folder beside the file
    (``images_<factor>`` for an integer factor, else ``images``, else the first ``images_*`` with one
    image per pose); ``'000'``, ``'001'``... when there is none.
    """
    _check_resize(factor, width, height)
    path = Path(path)
    _check_regular(path)
    try:
        array = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise CameraError(with_path(path, "no such file")) from None
    except (OSError, ValueError) as error:
        raise CameraError(with_path(path, f"not a numpy array file ({error})")) from None
    if array.ndim != 2 or array.shape[1] != 17:
        raise CameraError(with_path(path, f"poses_bounds has shape {array.shape}, expected [N, 17]"))
    if array.shape[0] == 0:
        raise _no_cameras(path)
    if not np.issubdtype(array.dtype, np.number):
        raise CameraError(with_path(path, f"poses_bounds has dtype {array.dtype}, expected numbers"))
    poses = array[:, :15].astype(np.float64).reshape(-1, 3, 5)
    names = _llff_image_names(path.parent, len(poses), factor)
    cameras = []
    for index, pose in enumerate(poses):
        where = with_path(path, f"pose {index}")
        _finite(pose, where)
        h, w, focal = pose[:, 4]
        c2w = llff_to_opencv_c2w(pose)
        rotation = checked_rotation(c2w[:3, :3], where)
        w2c = rigid_matrix(rotation.T, -rotation.T @ c2w[:3, 3])
        cameras.append(_camera(where, float(w), float(h), focal, focal, w / 2.0, h / 2.0, w2c, names[index]))
    return resize_cameras(cameras, factor=factor, width=width, height=height)


def _llff_image_names(root: Path, count: int, factor: float | None) -> list[str]:
    folders = []
    if factor is not None and float(factor).is_integer():
        folders.append(root / f"images_{int(factor)}")
    folders.append(root / "images")
    folders.extend(sorted(root.glob("images_*"), key=lambda p: (len(p.name), p.name)))
    for folder in folders:
        if folder.is_dir():
            names = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if len(names) == count:
                return names
    return [f"{index:03d}" for index in range(count)]


CAMERA_FILE_DEPTH = 2  # graphdeco output: MODEL/cameras.json beside MODEL/point_cloud/iteration_N/point_cloud.ply


def find_capture_cameras(scene_path: str | os.PathLike) -> Path | None:
    """The capture's camera file or folder near a scene file, or None.

    Looks in the scene's folder and up to two folders above it (where 3DGS training writes
    ``cameras.json``) for ``cameras.json``, a COLMAP model (``sparse/0``, ``sparse``) or
    ``poses_bounds.npy``; the nearest folder wins.
    """
    folder = Path(scene_path).resolve().parent
    for _ in range(CAMERA_FILE_DEPTH + 1):
        for candidate in (folder / "cameras.json", folder / "poses_bounds.npy"):
            if candidate.is_file():
                return candidate
        if find_colmap_model(folder, required=False) is not None:
            return folder
        if folder.parent == folder:
            break
        folder = folder.parent
    return None


def mean_camera_up(cameras: list[Camera]) -> np.ndarray:  # [3] unit vector, world frame
    """The cameras' average up direction in the world (OpenCV cameras look along +z with y down)."""
    if not cameras:
        raise CameraError("no cameras to take an up direction from")
    up = np.sum([-np.linalg.inv(camera.world_to_camera)[:3, 1] for camera in cameras], axis=0)
    norm = np.linalg.norm(up)
    if not np.isfinite(norm) or norm < 1e-9 * len(cameras):
        raise CameraError("the cameras' up directions cancel out (no common up)")
    return up / norm


USUAL_UP_AXIS = "-Y"  # OpenCV / COLMAP: what 3DGS training from COLMAP produces


def detect_up_axis(scene_path: str | os.PathLike, scene: GaussianScene | None = None) -> tuple[str, str]:
    """Which file axis points up (one of ``splat_mesh.UP_AXES``) and why, in words: the import's Automatic axes.

    From the capture's cameras near the file (:func:`find_capture_cameras`) when there are any: their average
    up, snapped to an axis. Otherwise from the splats of ``scene`` (:func:`.up_axis.up_axis_from_splats`) when
    they are sure; otherwise -Y (OpenCV / COLMAP), the usual for 3DGS captures, saying so.
    """
    found = find_capture_cameras(scene_path)
    note = ""
    if found is not None:
        try:
            up = up_axis_for(mean_camera_up(load_cameras(found)))
            return up, f"{UP_AXIS_LABELS[up]}, from the cameras in {found.name}"
        except DresgError as error:
            note = f"cameras unreadable: {error}"
    usual = f"{UP_AXIS_LABELS[USUAL_UP_AXIS]}, the usual for 3DGS captures"
    if scene is None:
        return USUAL_UP_AXIS, f"{usual} ({note or 'no cameras found beside the file'})"
    guess = up_axis_from_splats(scene)
    note = f"{note}; " if note else ""
    if guess.sure:
        return guess.axis, f"{UP_AXIS_LABELS[guess.axis]} from the splats ({note}{guess.evidence()}; confident)"
    return (
        USUAL_UP_AXIS,
        f"{usual}: not sure from the splats ({note}{guess.evidence()}); check the Up Axis in the object panel",
    )
