"""LLFF ``poses_bounds.npy``: read."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...util.errors import CameraError, with_path
from ..camera import Camera
from .common import (
    IMAGE_SUFFIXES,
    _camera,
    _check_regular,
    _check_resize,
    _finite,
    _no_cameras,
    checked_rotation,
    resize_cameras,
    rigid_matrix,
)


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
