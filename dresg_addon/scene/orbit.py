"""Orbit cameras for scenes that come without cameras: a ring around the scene's robust bounds."""

from __future__ import annotations

import math

import numpy as np

from ..util.errors import CameraError, ConfigError
from .camera import Camera, look_at
from .gaussians import GaussianScene


def robust_bounds(means, quantile: float = 0.02) -> tuple[np.ndarray, np.ndarray]:  # [3], [3]
    """Per-axis ``quantile`` and ``1 - quantile`` of the finite points: a box that floaters do not inflate."""
    points = np.asarray(means, dtype=np.float64)  # [N, 3]
    if points.ndim != 2 or points.shape[1] != 3:
        raise CameraError(f"scene points have shape {points.shape}, expected [N, 3]")
    if not 0.0 <= quantile < 0.5:
        raise ConfigError(f"bounds quantile {quantile} must be in [0, 0.5)")
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) == 0:
        raise CameraError("the scene has no finite points to place cameras around")
    return np.quantile(points, quantile, axis=0), np.quantile(points, 1.0 - quantile, axis=0)


def orbit_cameras(
    scene_or_means: GaussianScene | np.ndarray,
    n: int,
    *,
    width: int = 448,
    height: int = 320,
    fov_deg: float = 50.0,
    elevation_deg: float = 20.0,
    radius_scale: float = 1.0,
    up=(0.0, -1.0, 0.0),
    quantile: float = 0.02,
    azimuth_offset_deg: float = 0.0,
) -> list[Camera]:
    """``n`` cameras on a ring around the robust box of the scene, all looking at its centre.

        The box is :func:`robust_bounds`; its bounding sphere (radius ``r``) fits the view at distance
        ``radius_scale * r / sin(theta)``, with ``theta`` the smaller of the half fields of view. ``fov_deg``
        is horizontal; ``up`` is the world direction shown up (-y: COLMAP worlds are y-down);
        ``elevation_deg`` lifts the ring toward ``up``. The first camera looks along the world +z axis as
        seen from the ring (or +x when up is along z), turned by ``azimuth_offset_deg``; the next ones move to its
    right. Deterministic. An offset of half a step (180 / n degrees) gives the novel views between a ring's
    cameras.
    """
    means = scene_or_means.means if isinstance(scene_or_means, GaussianScene) else scene_or_means
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise CameraError(f"orbit needs at least one camera, got n={n!r}")
    if width < 1 or height < 1:
        raise ConfigError(f"orbit image size {width}x{height} must be at least 1x1")
    if not 0.0 < fov_deg < 180.0:
        raise ConfigError(f"orbit field of view {fov_deg} degrees must be in (0, 180)")
    if not -90.0 <= elevation_deg <= 90.0:
        raise ConfigError(f"orbit elevation {elevation_deg} degrees must be in [-90, 90]")
    if not math.isfinite(azimuth_offset_deg):
        raise ConfigError(f"orbit azimuth offset {azimuth_offset_deg} must be finite")
    if not (math.isfinite(radius_scale) and radius_scale > 0):
        raise ConfigError(f"orbit radius scale {radius_scale} must be positive")
    up_axis = np.asarray(up, dtype=np.float64)
    if up_axis.shape != (3,) or not np.isfinite(up_axis).all() or np.linalg.norm(up_axis) == 0:
        raise ConfigError(f"orbit up direction {up!r} must be a non-zero 3-vector")
    up_axis = up_axis / np.linalg.norm(up_axis)

    lo, hi = robust_bounds(means, quantile)
    centre = (lo + hi) / 2.0
    radius = float(np.linalg.norm(hi - lo)) / 2.0
    if radius <= 1e-9 * max(1.0, float(np.linalg.norm(centre))):
        radius = 1.0  # a single point has no size: any distance shows it

    fx = width / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
    tan_half = min(width, height) / (2.0 * fx)  # the image's inscribed cone
    distance = radius_scale * radius * math.sqrt(1.0 + tan_half**2) / tan_half  # r / sin(theta)

    # Horizontal frame of the ring: world +z (or +x) made perpendicular to up, and its right-hand side.
    for candidate in (np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])):
        front = candidate - (candidate @ up_axis) * up_axis
        if np.linalg.norm(front) > 1e-6:
            break
    front /= np.linalg.norm(front)
    side = np.cross(up_axis, front)

    elevation = math.radians(elevation_deg)
    cameras = []
    for index in range(n):
        azimuth = 2.0 * math.pi * index / n + math.radians(azimuth_offset_deg)
        horizontal = math.cos(azimuth) * front + math.sin(azimuth) * side
        view = math.cos(elevation) * horizontal - math.sin(elevation) * up_axis  # toward the centre
        eye = centre - distance * view
        w2c = look_at(eye, centre, up_axis)
        cameras.append(Camera(width, height, fx, fx, width / 2.0, height / 2.0, w2c, f"orbit_{index:03d}"))
    return cameras
