"""Which way is up, from the splats alone (the import's Automatic axes when no cameras lie beside the file).

Two pieces of evidence, each measured along the file's three axes:

* **a layer across the up axis**: floors, tables, a figure's base or outstretched arms put many splats at
  one height, so the opacity-weighted histogram of positions along the up axis has a much higher peak than
  along the other two. Flat splats lying in that layer (their shortest axis along it: floor normals) count up
  to three times, and where flat splats' normals gather within 30 degrees of an axis, the layer is also
  measured across their main direction (a floor tilted off the axis). ``plane_ratio`` = the highest peak /
  the next axis's peak.
* **wider below**: scenes stand on their wide end (a floor around the objects, a table under a pot, feet
  apart under a head), so along the up axis the splats at the bottom end spread wider across it than those
  at the top end. ``footprint_ratio`` = bottom spread / top spread (the mean log ratio over end slabs of
  5%, 10% and 20% of the height); which end is wider gives the sign.

Both must be clear for a confident answer; otherwise the caller keeps its default (OpenCV / COLMAP: -Y up).
Measured on the shared scenes and the demo in bench/README.md (`up_axis.py`).

The six up axes (``UP_AXES``, ``UP_AXIS_LABELS``) and the one nearest a direction (``up_axis_for``) live here
too: the camera files (``camera_io``) and the Blender splat object (``blender.splat_mesh``) share them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .gaussians import GaussianScene

MAX_SPLATS = 20_000  # a fixed random subset of larger scenes (the statistics are histograms): a few ms
MIN_SPLATS = 32
TRIM = 0.01  # splats outside the 1%-99% range on any axis (floaters, far background) are left out
BINS = 40  # histogram bins across each axis's trimmed extent
FLAT_BOOST = 2.0  # a flat splat lying in the layer counts 1 + FLAT_BOOST times
FLOOR_CONE = 30.0  # degrees: flat splats' normals this close to an axis may tilt its layer
END_SLABS = (0.05, 0.1, 0.2)  # end slabs, as fractions of the trimmed height
PLANE_SURE = 1.3  # plane_ratio from which the axis is trusted
FOOTPRINT_SURE = 1.25  # footprint_ratio from which the sign is trusted

# Which file axis points up in Blender: the splat object's Up Axis, and what the import's Axes choose.
UP_AXES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
UP_AXIS_LABELS = {
    "+X": "+X up",
    "-X": "-X up",
    "+Y": "+Y up (OpenGL, glTF)",
    "-Y": "-Y up (OpenCV / COLMAP)",
    "+Z": "+Z up (as Blender)",
    "-Z": "-Z up",
}


def up_axis_for(direction) -> str:
    """The one of :data:`UP_AXES` nearest a file-frame ``direction`` ([3], e.g. the cameras' mean up)."""
    direction = np.asarray(direction, dtype=np.float64)
    index = int(np.argmax(np.abs(direction)))
    return ("+" if direction[index] >= 0.0 else "-") + "XYZ"[index]


@dataclass(frozen=True)
class UpAxisGuess:
    axis: str  # one of UP_AXES: the file axis that points up
    plane_ratio: float  # >= 1: the densest layer across ``axis`` / the densest across the next axis
    footprint_ratio: float  # >= 1: how much wider the scene is at its bottom end than at its top end
    splats: int  # how many splats the statistics used

    @property
    def confidence(self) -> float:
        """>= 1 when both margins reach their thresholds (the smaller of the two, each on a log scale)."""
        return min(
            math.log(max(self.plane_ratio, 1.0)) / math.log(PLANE_SURE),
            math.log(max(self.footprint_ratio, 1.0)) / math.log(FOOTPRINT_SURE),
        )

    @property
    def sure(self) -> bool:
        return self.confidence >= 1.0

    def evidence(self) -> str:
        """The margins in words: "densest layer across Y, 2.8x the other axes'; 2.2x wider at +Y, the bottom"."""
        bottom = ("-" if self.axis[0] == "+" else "+") + self.axis[1]
        return (
            f"densest layer across {self.axis[1]}, {self.plane_ratio:.1f}x the other axes'; "
            f"{self.footprint_ratio:.1f}x wider at {bottom}" + (", the bottom" if self.sure else "")
        )


def _shortest_axes(quats: np.ndarray, log_scales: np.ndarray) -> np.ndarray:  # [N, 4], [N, 3] -> [N, 3]
    """Each splat's shortest axis (the normal of a flat splat) as a unit vector in the file frame."""
    norm = np.linalg.norm(quats, axis=1, keepdims=True)
    w, x, y, z = (quats / np.where(norm > 0.0, norm, 1.0)).T
    columns = (  # the columns of the rotation matrix of (w, x, y, z)
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], 1),
        np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], 1),
        np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], 1),
    )
    return np.choose(np.argmin(log_scales, axis=1)[:, None], columns)


def _spread(points: np.ndarray, weights: np.ndarray) -> float:
    """Weighted RMS distance of ``points`` ([N, 3]) from their weighted centre (0 when there are none)."""
    total = weights.sum()
    if len(points) < 2 or total <= 0.0:
        return 0.0
    centre = weights @ points / total
    return float(np.sqrt(weights @ ((points - centre) ** 2).sum(1) / total))


def _floor_normal(normals: np.ndarray, weights: np.ndarray, axis: int) -> np.ndarray:  # [3] unit
    """The main direction of the normals within FLOOR_CONE of a coordinate axis (the axis when there are none):
    the principal eigenvector of their weighted outer products, turned towards the axis."""
    near = np.abs(normals[:, axis]) >= math.cos(math.radians(FLOOR_CONE))
    if weights[near].sum() <= 0.0:
        return np.eye(3)[axis]
    _, vectors = np.linalg.eigh((normals[near] * weights[near, None]).T @ normals[near])
    main = vectors[:, -1]
    return main if main[axis] >= 0.0 else -main


def _layer(heights: np.ndarray, weights: np.ndarray) -> float:
    """The share of ``weights`` in the fullest of BINS equal slabs across ``heights``' range (1: one height)."""
    low, high = heights.min(), heights.max()
    if not high > low:
        return 1.0
    counts, _ = np.histogram(heights, bins=BINS, range=(low, high), weights=weights)
    return float(counts.max() / weights.sum())


def up_axis_from_splats(scene: GaussianScene) -> UpAxisGuess:
    """Which of the file's six signed axes points up, from the splats' positions, shapes and opacities.

    No bpy, no cameras: see the module's docstring for the evidence. The answer is snapped to an axis; its
    ``sure`` says whether both margins are clear (an isotropic cloud of splats gives ratios near 1).
    """
    index = np.arange(len(scene))
    if len(index) > MAX_SPLATS:
        index = np.sort(np.random.default_rng(0).choice(len(index), MAX_SPLATS, replace=False))
    means = np.asarray(scene.means[index], dtype=np.float64)
    log_scales = np.asarray(scene.log_scales[index], dtype=np.float64)
    quats = np.asarray(scene.quats[index], dtype=np.float64)
    logits = np.asarray(scene.opacity_logits[index], dtype=np.float64)
    valid = np.isfinite(means).all(1) & np.isfinite(log_scales).all(1) & np.isfinite(quats).all(1)
    index = np.flatnonzero(valid & np.isfinite(logits))
    unsure = UpAxisGuess("-Y", 1.0, 1.0, len(index))
    if len(index) < MIN_SPLATS:
        return unsure
    means, log_scales, quats = means[index], log_scales[index], quats[index]
    opacity = 1.0 / (1.0 + np.exp(-np.clip(logits[index], -60.0, 60.0)))  # no overflow warnings
    low, high = np.quantile(means, [TRIM, 1.0 - TRIM], axis=0)
    inside = ((means >= low) & (means <= high)).all(1)
    means, log_scales, quats, opacity = means[inside], log_scales[inside], quats[inside], opacity[inside]
    if len(means) < MIN_SPLATS or opacity.sum() <= 0.0 or not (high > low).any():
        return unsure

    # The axis: the densest layer of splats, flat ones lying in it counting more. A floor tilted off the axis
    # is measured across its own normal (the main direction of the flat splats' normals near the axis).
    ordered = np.sort(log_scales, axis=1)
    flatness = 1.0 - np.exp(ordered[:, 0] - ordered[:, 1])  # 0 for a round splat, -> 1 for a disk
    normals = _shortest_axes(quats, log_scales)
    peaks, directions = np.zeros(3), []
    for axis in range(3):
        best = (-1.0, np.eye(3)[axis])
        for direction in (np.eye(3)[axis], _floor_normal(normals, opacity * flatness**2, axis)):
            weights = opacity * (1.0 + FLAT_BOOST * flatness * (normals @ direction) ** 2)
            best = max(best, (_layer(means @ direction, weights), direction), key=lambda pair: pair[0])
        peaks[axis] = best[0]
        directions.append(best[1])
    order = np.argsort(-peaks, kind="stable")
    axis = int(order[0])
    plane_ratio = float(peaks[axis] / max(peaks[order[1]], 1e-12))

    # The sign: the end of that direction where the scene spreads wider is the bottom.
    direction = directions[axis]
    height = means @ direction
    across = means - height[:, None] * direction
    low, high = height.min(), height.max()
    logs = []
    for fraction in END_SLABS:
        cut = fraction * (high - low)
        spreads = [_spread(across[end], opacity[end]) for end in (height <= low + cut, height >= high - cut)]
        if min(spreads) > 0.0:
            logs.append(math.log(spreads[0] / spreads[1]))
    wider_low = float(np.mean(logs)) if logs else 0.0  # > 0: the low end is wider, so it is the bottom
    sign = "+" if wider_low >= 0.0 else "-"
    return UpAxisGuess(sign + "XYZ"[axis], plane_ratio, math.exp(abs(wider_low)), len(means))
