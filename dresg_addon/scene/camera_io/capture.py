"""The capture beside a scene file: its camera file or folder, the cameras' up, and which file axis points up."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...util.errors import CameraError, DresgError
from ..camera import Camera
from ..gaussians import GaussianScene
from ..up_axis import UP_AXIS_LABELS, up_axis_for, up_axis_from_splats
from .colmap import find_colmap_model
from .load import load_cameras

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
    """Which file axis points up (one of ``scene.up_axis.UP_AXES``) and why, in words: the import's Automatic axes.

    From the capture's cameras near the file (:func:`find_capture_cameras`) when there are any: their average
    up, snapped to an axis. Otherwise from the splats of ``scene`` (:func:`~dresg_addon.scene.up_axis.up_axis_from_splats`) when
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
