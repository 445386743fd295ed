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

One module per format (``cameras_json``, ``colmap``, ``llff``); ``common`` holds what they share (limits,
checks, resizing), ``load`` chooses the format from a path, ``capture`` finds the capture's cameras beside a
scene file and which file axis points up. Import from the package: the names below are its interface.
"""

from .cameras_json import read_cameras_json, write_cameras_json
from .capture import CAMERA_FILE_DEPTH, USUAL_UP_AXIS, detect_up_axis, find_capture_cameras, mean_camera_up
from .colmap import COLMAP_MODELS, find_colmap_model, quaternion_to_rotation, read_colmap
from .common import (
    IMAGE_SUFFIXES,
    MAX_IMAGE_SIDE,
    ROTATION_TOLERANCE,
    checked_rotation,
    resize_cameras,
    rigid_matrix,
)
from .llff import llff_to_opencv_c2w, read_llff
from .load import load_cameras

__all__ = [
    "CAMERA_FILE_DEPTH",
    "COLMAP_MODELS",
    "IMAGE_SUFFIXES",
    "MAX_IMAGE_SIDE",
    "ROTATION_TOLERANCE",
    "USUAL_UP_AXIS",
    "checked_rotation",
    "detect_up_axis",
    "find_capture_cameras",
    "find_colmap_model",
    "llff_to_opencv_c2w",
    "load_cameras",
    "mean_camera_up",
    "quaternion_to_rotation",
    "read_cameras_json",
    "read_colmap",
    "read_llff",
    "resize_cameras",
    "rigid_matrix",
    "write_cameras_json",
]
