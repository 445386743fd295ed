"""Reprojection of an image between two cameras by rendered depth: what one view shows, seen from another.

Used by the method (a view's synthesis guides its neighbours', so that views agree) and by the metrics
(depth-warp consistency between stylized views).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .camera import Camera

DEPTH_TOLERANCE = 0.03  # relative: |z_src - depth_src| <= 3% of z counts as the same surface


def _bilinear(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Sample [H, W, C] at continuous pixel coordinates u, v [H', W'] (pixel i's centre at i + 0.5)."""
    h, w = image.shape[:2]
    grid = torch.stack([2.0 * u / w - 1.0, 2.0 * v / h - 1.0], -1)[None].to(image.dtype)
    out = F.grid_sample(image.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0)


def warp_to(
    src_rgb: torch.Tensor,  # [Hs, Ws, 3]
    src_depth: torch.Tensor,  # [Hs, Ws] camera-space z, 0 where nothing
    src_cam: Camera,
    dst_cam: Camera,
    dst_depth: torch.Tensor,  # [Hd, Wd] camera-space z, 0 where nothing
    src_alpha: torch.Tensor | None = None,  # [Hs, Ws]
    dst_alpha: torch.Tensor | None = None,  # [Hd, Wd]
    depth_tolerance: float = DEPTH_TOLERANCE,
    alpha_threshold: float = 0.5,
) -> tuple[torch.Tensor, torch.Tensor]:  # [Hd, Wd, 3], [Hd, Wd] bool
    """The source render seen from the destination camera, by exact reprojection, and its valid mask.

    For each destination pixel centre (u, v) with rendered depth z (the rasterizer's alpha-weighted
    camera-space z, not the ray length): X_dst = z ((u - cx) / fx, (v - cy) / fy, 1); X_src =
    W2C_src C2W_dst X_dst; (u', v') = (fx' x / z' + cx', fy' y / z' + cy'); the source image is
    sampled bilinearly at (u', v'). Valid where

    - (u', v') lies within the source's pixel centres [0.5, W - 0.5] x [0.5, H - 0.5];
    - z > 0, z' > 0 and the sampled source depth d' > 0;
    - |z' - d'| <= ``depth_tolerance`` z' (the point is the surface the source sees, not occluded;
      bilinear depth across a depth edge fails this test, which drops edge pixels conservatively);
    - both alphas (when given) exceed ``alpha_threshold``, the source one sampled at (u', v').

    Invalid pixels of ``warped`` hold 0.

    >>> import numpy as np
    >>> cam = Camera(8, 6, 10.0, 10.0, 4.0, 3.0, np.eye(4))
    >>> rgb, depth = torch.rand(6, 8, 3), torch.full((6, 8), 2.0)
    >>> warped, valid = warp_to(rgb, depth, cam, cam, depth)
    >>> bool(valid.all()), bool(torch.allclose(warped, rgb, atol=1e-6))
    (True, True)
    """
    hs, ws = src_cam.height, src_cam.width
    hd, wd = dst_cam.height, dst_cam.width
    for name, tensor, shape in (
        ("src_rgb", src_rgb, (hs, ws, 3)),
        ("src_depth", src_depth, (hs, ws)),
        ("dst_depth", dst_depth, (hd, wd)),
        ("src_alpha", src_alpha, (hs, ws)),
        ("dst_alpha", dst_alpha, (hd, wd)),
    ):
        if tensor is not None and tuple(tensor.shape) != shape:
            raise ValueError(f"warp_to: {name} has shape {tuple(tensor.shape)}, expected {shape} from the camera")
    if not depth_tolerance >= 0.0:
        raise ValueError(f"warp_to: depth_tolerance must be >= 0, got {depth_tolerance}")
    device = src_rgb.device
    f64 = torch.float64
    z = dst_depth.to(f64)
    v, u = torch.meshgrid(
        torch.arange(hd, dtype=f64, device=device) + 0.5,
        torch.arange(wd, dtype=f64, device=device) + 0.5,
        indexing="ij",
    )
    points = torch.stack([(u - dst_cam.cx) / dst_cam.fx * z, (v - dst_cam.cy) / dst_cam.fy * z, z], -1)
    transform = torch.as_tensor(src_cam.world_to_camera @ dst_cam.camera_to_world, dtype=f64, device=device)
    src_points = points @ transform[:3, :3].T + transform[:3, 3]
    zs = src_points[..., 2]
    z_safe = torch.where(zs > 0, zs, 1.0)
    us = src_cam.fx * src_points[..., 0] / z_safe + src_cam.cx
    vs = src_cam.fy * src_points[..., 1] / z_safe + src_cam.cy
    # Far off-screen points: keep the sampling grid finite (they are invalid anyway).
    us, vs = us.clamp(-1.0, ws + 1.0), vs.clamp(-1.0, hs + 1.0)
    valid = (z > 0) & (zs > 0) & (us >= 0.5) & (us <= ws - 0.5) & (vs >= 0.5) & (vs <= hs - 0.5)
    stack = [src_rgb.to(f64), src_depth.to(f64)[..., None]]
    if src_alpha is not None:
        stack.append(src_alpha.to(f64)[..., None])
    sampled = _bilinear(torch.cat(stack, -1), us, vs)
    sampled_depth = sampled[..., 3]
    valid &= (sampled_depth > 0) & ((zs - sampled_depth).abs() <= depth_tolerance * zs)
    if src_alpha is not None:
        valid &= sampled[..., 4] > alpha_threshold
    if dst_alpha is not None:
        valid &= dst_alpha > alpha_threshold
    warped = torch.where(valid[..., None], sampled[..., :3], 0.0).to(src_rgb.dtype)
    return warped, valid
