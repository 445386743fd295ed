"""The one camera type: an OpenCV pinhole.

Conventions (written down once):

===========  ===========================  ==========================================
frame        axes                         used by
===========  ===========================  ==========================================
OpenCV       x right, y down, z forward   this engine, graphdeco PLY, COLMAP
Blender cam  x right, y up, looks down -z camera objects; ``matrix_world @ diag(1,-1,-1,1)`` = OpenCV c2w
Blender      z up world                   scene objects
===========  ===========================  ==========================================

Pixel (i, j) covers [i, i+1) x [j, j+1) and is sampled at its centre (i + 0.5, j + 0.5), as in
COLMAP: a point at camera coordinates (x, y, z) projects to u = fx x / z + cx, v = fy y / z + cy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: np.ndarray = field(default_factory=lambda: np.eye(4))  # [4, 4] float64
    name: str = ""

    def __post_init__(self) -> None:
        w2c = np.asarray(self.world_to_camera, dtype=np.float64)
        if w2c.shape != (4, 4):
            raise ValueError(f"Camera.world_to_camera has shape {w2c.shape}, expected (4, 4)")
        object.__setattr__(self, "world_to_camera", w2c)
        if self.width < 1 or self.height < 1:
            raise ValueError(f"Camera size {self.width}x{self.height} must be at least 1x1")
        if not (np.isfinite([self.fx, self.fy, self.cx, self.cy]).all() and self.fx > 0 and self.fy > 0):
            raise ValueError(f"Camera intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy} are invalid")

    @property
    def camera_to_world(self) -> np.ndarray:  # [4, 4]
        return np.linalg.inv(self.world_to_camera)

    @property
    def center(self) -> np.ndarray:  # [3] camera centre in world coordinates
        r = self.world_to_camera[:3, :3]
        return -r.T @ self.world_to_camera[:3, 3]

    @property
    def tan_half_fov(self) -> tuple[float, float]:
        """(tan(fov_x / 2), tan(fov_y / 2)), as graphdeco computes them (W / (2 fx))."""
        return self.width / (2.0 * self.fx), self.height / (2.0 * self.fy)

    def resized(self, width: int, height: int) -> Camera:
        """The same camera with the image resampled to ``width`` x ``height`` (intrinsics scaled)."""
        sx, sy = width / self.width, height / self.height
        return Camera(
            width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.world_to_camera, self.name
        )


def view_name(camera: Camera, index: int) -> str:
    """The name a view goes by in logs, reports and saved images: the camera's own, else ``view_NNN`` from its
    index among the cameras given."""
    return camera.name or f"view_{index:03d}"


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """[4, 4] OpenCV world-to-camera matrix of a camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear up in the image (default -y: COLMAP worlds are
    y-down).
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-12:  # up parallel to the view direction: pick any perpendicular
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]) if abs(forward[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    r = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = r
    w2c[:3, 3] = -r @ eye
    return w2c
