"""graphdeco ``cameras.json``: read and write."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ...util.errors import CameraError, with_path
from ...util.fileutil import atomic_write_bytes
from ..camera import Camera
from .common import _camera, _check_regular, _finite, _no_cameras, checked_rotation, rigid_matrix

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
        _finite(position, f"{where}: position")
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
