"""Per-Gaussian stages of the rasterizer: rotation, 3D covariance, camera transform, EWA projection.

All functions are batched over leading dimensions and differentiable. The rasterizer runs them in
float64: they are O(N) and float64 keeps scales from 1e-7 to 1e4 and anisotropy 1e6 finite and exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

LOW_PASS = 0.3  # added to the 2D covariance diagonal (graphdeco's anti-aliasing floor)
FRUSTUM_GUARD = 1.3  # Jacobian x/z, y/z clamped to 1.3 tan(fov/2)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z), any norm -> [..., 3, 3] rotation. A zero quaternion gives the identity."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


@dataclass
class Projected:
    """Projected Gaussians (only those that survived culling), in float64."""

    index: torch.Tensor  # [M] indices into the input Gaussians
    means2d: torch.Tensor  # [M, 2] pixel coordinates (COLMAP: pixel centres at i + 0.5)
    cov2d: torch.Tensor  # [M, 3] (xx, xy, yy) including the low-pass
    conic: torch.Tensor  # [M, 3] inverse covariance (a, b, c): power = a dx^2 + 2 b dx dy + c dy^2
    depth: torch.Tensor  # [M] camera-space z


def project_gaussians(
    means: torch.Tensor,  # [N, 3] world
    quats: torch.Tensor,  # [N, 4]
    log_scales: torch.Tensor,  # [N, 3]
    world_to_camera: torch.Tensor,  # [4, 4]
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    near: float,
    valid: torch.Tensor | None = None,  # [N] bool, extra Gaussians to skip (e.g. non-finite opacity)
) -> Projected:
    """EWA splatting of 3D Gaussians (Zwicker et al.; graphdeco's computeCov2D).

    Culls non-finite Gaussians and those with z <= near *before* any arithmetic on them, so that their
    gradients are exactly zero rather than NaN.
    """
    f64 = torch.float64
    w2c = world_to_camera.to(means.device, f64)
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    with torch.no_grad():
        finite = torch.isfinite(means).all(-1) & torch.isfinite(quats).all(-1) & torch.isfinite(log_scales).all(-1)
        if valid is not None:
            finite &= valid
        z_all = torch.where(finite, means.detach().to(f64) @ rot[2] + trans[2], torch.zeros((), dtype=f64))
        index = torch.nonzero(finite & (z_all > near)).squeeze(-1)
    p_cam = means[index].to(f64) @ rot.T + trans  # [M, 3]
    x, y, z = p_cam.unbind(-1)
    lim_x = FRUSTUM_GUARD * width / (2.0 * fx)
    lim_y = FRUSTUM_GUARD * height / (2.0 * fy)
    tx = torch.clamp(x / z, -lim_x, lim_x) * z
    ty = torch.clamp(y / z, -lim_y, lim_y) * z
    zero = torch.zeros_like(z)
    jac = torch.stack([fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], dim=-1).reshape(
        -1, 2, 3
    )  # [M, 2, 3]
    # Sigma_2D = J W Sigma W^T J^T = M M^T with M = J W R S  [M, 2, 3]
    rs = quat_to_rotmat(quats[index].to(f64)) * torch.exp(log_scales[index].to(f64))[:, None, :]
    m = jac @ rot @ rs
    cxx0 = (m[:, 0] * m[:, 0]).sum(-1)
    cxy = (m[:, 0] * m[:, 1]).sum(-1)
    cyy0 = (m[:, 1] * m[:, 1]).sum(-1)
    # det(M M^T) as the sum of squared 2x2 minors (Cauchy-Binet): no cancellation at anisotropy 1e6.
    minors = torch.linalg.cross(m[:, 0], m[:, 1], dim=-1)
    det = (minors * minors).sum(-1) + LOW_PASS * (cxx0 + cyy0) + LOW_PASS * LOW_PASS
    cxx, cyy = cxx0 + LOW_PASS, cyy0 + LOW_PASS
    with torch.no_grad():
        keep = torch.nonzero(torch.isfinite(det) & (det > 0)).squeeze(-1)
    cxx, cxy, cyy, det = cxx[keep], cxy[keep], cyy[keep], det[keep]
    conic = torch.stack([cyy / det, -cxy / det, cxx / det], dim=-1)
    means2d = torch.stack([fx * x[keep] / z[keep] + cx, fy * y[keep] / z[keep] + cy], dim=-1)
    return Projected(index[keep], means2d, torch.stack([cxx, cxy, cyy], -1), conic, z[keep])
