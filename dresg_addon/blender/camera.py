"""Blender camera <-> :class:`~dresg_addon.scene.camera.Camera`, as pure math (no bpy).

The operator copies a camera's settings into :class:`BlenderCameraParams` (floats and a 4x4 matrix)
and calls :func:`blender_to_camera`; :func:`camera_to_blender` gives the settings to write back.

Blender's perspective view plane (``BKE_camera_params_compute_viewplane``), for a render of
``W x H`` pixels with pixel aspect ``ax : ay`` (``ycor = ay / ax``):

- the sensor size is ``sensor_height`` for fit VERTICAL, ``sensor_width`` otherwise (AUTO included);
- the fit is resolved: AUTO becomes HORIZONTAL when ``ax W >= ay H``, else VERTICAL;
- ``viewfac = W`` (HORIZONTAL) or ``ycor H`` (VERTICAL): the sensor spans ``viewfac`` and a shift of 1
  moves the view window by ``viewfac`` pixels (right for ``shift_x``, up for ``shift_y``).

In OpenCV pixels (y down, pixel centres at i + 0.5) that is

    fx = lens viewfac / sensor,   fy = fx / ycor,
    cx = W / 2 - shift_x viewfac, cy = H / 2 + shift_y viewfac / ycor.

Cameras are expressed in the splat object's LOCAL frame, where its Gaussians live. A uniform object
scale ``s`` is divided out of the camera-space coordinates, which leaves every projection unchanged
and keeps ``world_to_camera`` rigid (depths are then in local units). Non-uniform or mirroring object
scales cannot be expressed by a rigid camera and raise :class:`~dresg_addon.util.errors.CameraError`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..scene.camera import Camera
from ..util.errors import CameraError

SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")
BLENDER_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # Blender camera axes (y up, looks down -z) -> OpenCV
MATRIX_TOLERANCE = 1e-4  # float32 world matrices: relative error accepted before calling a matrix skewed
MIN_LENS_MM = 1.0  # Blender's lower limit on Camera.lens and sensor sizes
MAX_SHIFT = 10.0  # Blender's limit on Camera.shift_x / shift_y


@dataclass(frozen=True)
class BlenderCameraParams:
    """The settings of a Blender perspective camera and its render output; Blender's defaults."""

    lens: float = 50.0  # mm
    sensor_width: float = 36.0  # mm
    sensor_height: float = 24.0  # mm
    sensor_fit: str = "AUTO"  # AUTO, HORIZONTAL or VERTICAL
    shift_x: float = 0.0  # fraction of the fitted image dimension
    shift_y: float = 0.0
    resolution_x: int = 1920
    resolution_y: int = 1080
    resolution_percentage: int = 100
    pixel_aspect_x: float = 1.0
    pixel_aspect_y: float = 1.0
    matrix_world: np.ndarray = field(default_factory=lambda: np.eye(4))  # [4, 4] camera object, may hold scale
    camera_type: str = "PERSP"  # Camera.type; only PERSP is a pinhole


def render_size(params: BlenderCameraParams) -> tuple[int, int]:
    """Rendered image size in pixels, as Blender rounds it: ``resolution * percentage // 100``."""
    width = int(params.resolution_x) * int(params.resolution_percentage) // 100
    height = int(params.resolution_y) * int(params.resolution_percentage) // 100
    if width < 1 or height < 1:
        raise CameraError(
            f"Blender camera: render size {params.resolution_x}x{params.resolution_y} at "
            f"{params.resolution_percentage}% is empty"
        )
    return width, height


def _resolved_fit(sensor_fit: str, width: float, height: float, aspect_x: float, aspect_y: float) -> str:
    if sensor_fit not in SENSOR_FITS:
        raise CameraError(f"Blender camera: sensor fit {sensor_fit!r} is not one of {', '.join(SENSOR_FITS)}")
    if sensor_fit == "AUTO":
        return "HORIZONTAL" if aspect_x * width >= aspect_y * height else "VERTICAL"
    return sensor_fit


def _view_factor(fit: str, width: float, height: float, ycor: float) -> float:
    """Pixels spanned by the sensor (and by a shift of 1) for a resolved fit."""
    return width if fit == "HORIZONTAL" else ycor * height


def blender_intrinsics(params: BlenderCameraParams) -> tuple[int, int, float, float, float, float]:
    """(width, height, fx, fy, cx, cy) of a Blender perspective camera in OpenCV pixels."""
    if params.camera_type != "PERSP":
        raise CameraError(f"Blender camera: type {params.camera_type} is not supported (use a perspective camera)")
    values = [params.lens, params.sensor_width, params.sensor_height, params.pixel_aspect_x, params.pixel_aspect_y]
    values += [params.shift_x, params.shift_y]
    if not np.isfinite(values).all():
        raise CameraError("Blender camera: lens, sensor, pixel aspect or shift is not finite")
    if min(values[:5]) <= 0:
        raise CameraError("Blender camera: lens, sensor size and pixel aspect must be positive")
    width, height = render_size(params)
    ycor = params.pixel_aspect_y / params.pixel_aspect_x
    fit = _resolved_fit(params.sensor_fit, width, height, params.pixel_aspect_x, params.pixel_aspect_y)
    sensor = params.sensor_height if params.sensor_fit == "VERTICAL" else params.sensor_width
    viewfac = _view_factor(fit, width, height, ycor)
    fx = params.lens * viewfac / sensor
    fy = fx / ycor
    cx = width / 2.0 - params.shift_x * viewfac
    cy = height / 2.0 + params.shift_y * viewfac / ycor
    return width, height, float(fx), float(fy), float(cx), float(cy)


def _checked_matrix(matrix, what: str) -> np.ndarray:  # [4, 4]
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise CameraError(f"{what}: world matrix has shape {m.shape}, expected (4, 4)")
    if not np.isfinite(m).all():
        raise CameraError(f"{what}: world matrix has non-finite values")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > MATRIX_TOLERANCE:
        raise CameraError(f"{what}: world matrix is projective (last row {m[3].tolist()})")
    return m


def _nearest_rotation(matrix) -> np.ndarray:  # [3, 3]
    u, _, vt = np.linalg.svd(matrix)
    return u @ vt


def camera_object_to_opencv_c2w(matrix_world) -> np.ndarray:  # [4, 4]
    """OpenCV camera-to-world matrix of a Blender camera object, its scale removed as Blender does."""
    m = _checked_matrix(matrix_world, "camera object")
    lengths = np.linalg.norm(m[:3, :3], axis=0)
    if lengths.min() <= 1e-12 * max(1.0, lengths.max()):
        raise CameraError("camera object: world matrix has a zero scale")
    rotation = m[:3, :3] / lengths
    if np.linalg.det(rotation) < 0:
        raise CameraError("camera object: world matrix is mirrored (negative scale)")
    skew = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if skew > MATRIX_TOLERANCE:
        raise CameraError(f"camera object: world matrix is sheared (axes off by {skew:.3g}); apply the scale")
    c2w = np.eye(4)
    c2w[:3, :3] = _nearest_rotation(rotation)
    c2w[:3, 3] = m[:3, 3]
    return c2w @ BLENDER_TO_OPENCV


def object_uniform_scale(matrix_world) -> float:
    """The uniform scale ``s`` of a splat object's world matrix; ``CameraError`` when it is not uniform."""
    m = _checked_matrix(matrix_world, "splat object")
    singular = np.linalg.svd(m[:3, :3], compute_uv=False)
    if singular[-1] <= 1e-12 * max(1.0, singular[0]):
        raise CameraError("splat object: world matrix has a zero scale")
    if np.linalg.det(m[:3, :3]) < 0:
        raise CameraError("splat object: world matrix is mirrored (negative scale); apply the scale")
    if singular[0] / singular[-1] - 1.0 > MATRIX_TOLERANCE:
        raise CameraError(
            f"splat object: scale is not uniform (axis scales {', '.join(f'{s:.4g}' for s in singular)}); "
            "cameras cannot be expressed in its local frame"
        )
    return float(singular.mean())


def blender_to_camera(params: BlenderCameraParams, object_matrix_world=None, name: str = "") -> Camera:
    """The Camera seeing what the Blender camera renders, in the splat object's local frame.

    ``world_to_camera = (inv(C) @ M) / s`` on the first three rows, with ``C`` the camera's OpenCV
    camera-to-world matrix (scale removed), ``M`` the splat object's world matrix (identity when None)
    and ``s`` its uniform scale.
    """
    width, height, fx, fy, cx, cy = blender_intrinsics(params)
    c2w = camera_object_to_opencv_c2w(params.matrix_world)
    m = np.eye(4) if object_matrix_world is None else _checked_matrix(object_matrix_world, "splat object")
    scale = object_uniform_scale(m)
    a = np.linalg.inv(c2w) @ m
    w2c = np.eye(4)
    w2c[:3, :3] = _nearest_rotation(a[:3, :3] / scale)
    w2c[:3, 3] = a[:3, 3] / scale
    return Camera(width, height, fx, fy, cx, cy, w2c, name)


def camera_to_blender(
    camera: Camera,
    object_matrix_world=None,
    *,
    sensor_fit: str = "AUTO",
    sensor_width: float = 36.0,
    sensor_height: float = 24.0,
) -> BlenderCameraParams:
    """Blender settings reproducing ``camera`` (given in the splat object's local frame).

    The sensor sizes and fit are chosen by the caller; the lens, shifts, resolution (at 100%), pixel
    aspect (for fx != fy) and the camera object's world matrix (without scale) follow from them.
    """
    if not (sensor_width > 0 and sensor_height > 0):
        raise CameraError(f"Blender camera: sensor {sensor_width}x{sensor_height} mm must be positive")
    width, height = camera.width, camera.height
    ycor = camera.fx / camera.fy
    aspect_x, aspect_y = (1.0, ycor) if ycor >= 1.0 else (1.0 / ycor, 1.0)
    fit = _resolved_fit(sensor_fit, width, height, aspect_x, aspect_y)
    sensor = sensor_height if sensor_fit == "VERTICAL" else sensor_width
    viewfac = _view_factor(fit, width, height, ycor)
    lens = camera.fx * sensor / viewfac
    if lens < MIN_LENS_MM:
        raise CameraError(
            f"camera {camera.name!r}: a {lens:.3g} mm lens is needed, below Blender's {MIN_LENS_MM:g} mm "
            "(field of view too wide)"
        )
    shift_x = (width / 2.0 - camera.cx) / viewfac
    shift_y = (camera.cy - height / 2.0) * ycor / viewfac
    if max(abs(shift_x), abs(shift_y)) > MAX_SHIFT:
        raise CameraError(
            f"camera {camera.name!r}: principal point ({camera.cx:g}, {camera.cy:g}) needs a lens shift beyond "
            f"Blender's +-{MAX_SHIFT:g}"
        )
    m = np.eye(4) if object_matrix_world is None else _checked_matrix(object_matrix_world, "splat object")
    scale = object_uniform_scale(m)
    # Inverse of blender_to_camera: C = M @ inv(w2c) @ diag(1/s, 1/s, 1/s, 1).
    c2w = m @ camera.camera_to_world @ np.diag([1.0 / scale, 1.0 / scale, 1.0 / scale, 1.0])
    c2w[:3, :3] = _nearest_rotation(c2w[:3, :3])
    return BlenderCameraParams(
        lens=float(lens),
        sensor_width=float(sensor_width),
        sensor_height=float(sensor_height),
        sensor_fit=sensor_fit,
        shift_x=float(shift_x),
        shift_y=float(shift_y),
        resolution_x=width,
        resolution_y=height,
        resolution_percentage=100,
        pixel_aspect_x=float(aspect_x),
        pixel_aspect_y=float(aspect_y),
        matrix_world=c2w @ BLENDER_TO_OPENCV,
    )


CLIP_MARGIN = 1.5  # clip_end beyond the farthest corner of the splats' box
CLIP_RATIO = 1e4  # clip_end / clip_start: keeps Blender's depth buffer precise


def clip_distances(camera: Camera, bounds_min, bounds_max, object_matrix_world=None) -> tuple[float, float]:
    """``clip_start`` and ``clip_end`` (world units) that keep a box of splats inside a camera's range.

    ``camera`` and the box are in the splat object's local frame; local depths are multiplied by the
    object's uniform scale. clip_end is 1.5x the depth of the box's farthest corner, clip_start
    clip_end / 1e4 (so a camera inside the box still sees what is in front of it).
    """
    lo, hi = np.asarray(bounds_min, dtype=np.float64), np.asarray(bounds_max, dtype=np.float64)
    corners = np.array([[(lo, hi)[(k >> axis) & 1][axis] for axis in range(3)] for k in range(8)])
    depths = corners @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
    scale = 1.0 if object_matrix_world is None else object_uniform_scale(object_matrix_world)
    far = CLIP_MARGIN * scale * float(np.max(np.linalg.norm(depths, axis=1)))
    if not np.isfinite(far) or far <= 0.0:
        raise CameraError(f"camera {camera.name!r}: the splats' bounds give no clip range")
    return far / CLIP_RATIO, far


def size_within(width: int, height: int, max_width: int, max_height: int) -> tuple[int, int]:
    """The largest size of the aspect ``width : height`` inside ``max_width x max_height`` (never larger)."""
    factor = min(1.0, max_width / width, max_height / height)
    return max(1, round(width * factor)), max(1, round(height * factor))
