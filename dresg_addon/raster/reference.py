"""The slow, obviously correct float64 reference renderer: the oracle the fast rasterizer is tested against.

Written independently of the fast path (numpy, no shared code): per Gaussian the textbook EWA formulas,
per pixel a sequential front-to-back loop with graphdeco's rules (alpha = min(0.99, o G) >= 1/255, a
sample with T (1 - alpha) < 1e-4 ends the pixel and is not added). Only small images or pixel windows.
"""

from __future__ import annotations

import numpy as np

from ..scene.camera import Camera


def _rotation(q):
    norm = np.linalg.norm(q)
    if norm == 0.0:
        return np.eye(3)
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def reference_project(means, quats, log_scales, camera: Camera, near=0.01):
    """Per Gaussian: (ok, mean2d [2], conic [3], depth) in float64, one at a time."""
    w2c = camera.world_to_camera
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    lim_x = 1.3 * camera.width / (2 * camera.fx)
    lim_y = 1.3 * camera.height / (2 * camera.fy)
    out = []
    for m, q, s in zip(means.astype(np.float64), quats.astype(np.float64), log_scales.astype(np.float64)):
        if not (np.isfinite(m).all() and np.isfinite(q).all() and np.isfinite(s).all()):
            out.append((False, None, None, None))
            continue
        x, y, z = rot @ m + trans
        if not z > near:
            out.append((False, None, None, None))
            continue
        tx = min(max(x / z, -lim_x), lim_x) * z
        ty = min(max(y / z, -lim_y), lim_y) * z
        jac = np.array([[camera.fx / z, 0, -camera.fx * tx / z**2], [0, camera.fy / z, -camera.fy * ty / z**2]])
        r = _rotation(q)
        sigma = r @ np.diag(np.exp(2 * s)) @ r.T
        cov = jac @ rot @ sigma @ rot.T @ jac.T + 0.3 * np.eye(2)
        det = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
        if not det > 0:
            out.append((False, None, None, None))
            continue
        conic = np.array([cov[1, 1] / det, -cov[0, 1] / det, cov[0, 0] / det])
        mean2d = np.array([camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy])
        out.append((True, mean2d, conic, z))
    return out


def reference_render(
    means,  # [N, 3]
    quats,  # [N, 4]
    log_scales,  # [N, 3]
    opacity_logits,  # [N]
    colors,  # [N, 3]
    camera: Camera,
    near: float = 0.01,
    background=(0.0, 0.0, 0.0),
    window: tuple[int, int, int, int] | None = None,  # (x0, y0, width, height) of pixels to render
):
    """Returns dict rgb [h, w, 3], alpha [h, w], depth [h, w], visibility [N] (sum of T alpha over the window)."""
    means, quats, log_scales = (np.asarray(a, dtype=np.float64) for a in (means, quats, log_scales))
    logits = np.asarray(opacity_logits, dtype=np.float64)
    colors = np.asarray(colors, dtype=np.float64)
    x0, y0, w, h = window if window is not None else (0, 0, camera.width, camera.height)
    px, py = np.meshgrid(np.arange(x0, x0 + w) + 0.5, np.arange(y0, y0 + h) + 0.5)
    px, py = px.ravel(), py.ravel()
    projected = reference_project(means, quats, log_scales, camera, near)
    candidates = []  # (depth, index, alpha over the window)
    for i, (ok, mean2d, conic, z) in enumerate(projected):
        if not ok or not (np.isfinite(logits[i]) and np.isfinite(colors[i]).all()):
            continue
        o = 1.0 / (1.0 + np.exp(-logits[i]))
        dx, dy = px - mean2d[0], py - mean2d[1]
        power = conic[0] * dx * dx + 2 * conic[1] * dx * dy + conic[2] * dy * dy
        alpha = np.minimum(0.99, o * np.exp(-0.5 * power))
        alpha = np.where(alpha >= 1.0 / 255.0, alpha, 0.0)
        if alpha.any():
            candidates.append((z, i, alpha))
    candidates.sort(key=lambda item: (item[0], item[1]))
    t = np.ones(px.size)
    done = np.zeros(px.size, dtype=bool)
    rgb = np.zeros((px.size, 3))
    depth_sum = np.zeros(px.size)
    visibility = np.zeros(len(means))
    for z, i, alpha in candidates:
        active = (alpha > 0) & ~done
        test_t = t * (1.0 - alpha)
        stop = active & (test_t < 1e-4)
        done |= stop
        add = active & ~stop
        weight = np.where(add, t * alpha, 0.0)
        rgb += weight[:, None] * colors[i]
        depth_sum += weight * z
        visibility[i] = weight.sum()
        t = np.where(add, test_t, t)
    rgb += t[:, None] * np.asarray(background, dtype=np.float64)
    wsum = 1.0 - t
    depth = np.where(depth_sum > 0, depth_sum / np.where(wsum > 0, wsum, 1.0), 0.0)
    return {
        "rgb": rgb.reshape(h, w, 3),
        "alpha": wsum.reshape(h, w),
        "depth": depth.reshape(h, w),
        "visibility": visibility,
    }
