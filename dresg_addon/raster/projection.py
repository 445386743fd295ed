"""Per-Gaussian stage of the rasterizer: camera transform, rotation, 3D covariance, EWA projection.

It runs in float64: it is O(N), and float64 keeps scales from 1e-7 to 1e4 and anisotropy 1e6 finite
and exact. The backward is written by hand (see :class:`_EWA`) and checked by gradcheck.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

LOW_PASS = 0.3  # added to the 2D covariance diagonal (graphdeco's anti-aliasing floor)
FRUSTUM_GUARD = 1.3  # Jacobian x/z, y/z clamped to 1.3 tan(fov/2)
_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))  # the entries of a symmetric 3 x 3 matrix kept


@dataclass
class Projected:
    """Projected Gaussians (only those that survived culling), float64 [M] columns."""

    index: torch.Tensor  # indices into the input Gaussians
    mx: torch.Tensor  # pixel coordinates of the centre (COLMAP: pixel centres at i + 0.5)
    my: torch.Tensor
    conic_a: torch.Tensor  # inverse covariance (a, b, c): power = a dx^2 + 2 b dx dy + c dy^2
    conic_b: torch.Tensor
    conic_c: torch.Tensor
    cxx: torch.Tensor  # 2D covariance including the low-pass; no gradient
    cxy: torch.Tensor
    cyy: torch.Tensor
    depth: torch.Tensor  # camera-space z; no gradient


def _rotation_columns(q):
    """The 9 entries (row-major) of the rotation of unit quaternions q = (w, x, y, z), each [K]."""
    w, x, y, z = q
    return (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip


def _rotation_vjp(q, g):
    """Gradient of sum(g * R(q)) with respect to the unit quaternion q; g holds the 9 entries' gradients."""
    w, x, y, z = q
    g00, g01, g02, g10, g11, g12, g20, g21, g22 = g
    return (
        2 * (z * (g10 - g01) + y * (g02 - g20) + x * (g21 - g12)),
        2 * (y * (g01 + g10) + z * (g02 + g20) + w * (g21 - g12) - 2 * x * (g11 + g22)),
        2 * (x * (g01 + g10) + w * (g02 - g20) + z * (g12 + g21) - 2 * y * (g00 + g22)),
        2 * (w * (g10 - g01) + x * (g02 + g20) + y * (g12 + g21) - 2 * z * (g00 + g11)),
    )


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


CHUNK = 65536  # Gaussians per piece of the projection: its ~100 temporaries stay in cache


def _ewa_forward(means, quats, log_scales, camera):
    """EWA projection of K Gaussians as [K] float64 columns; returns (outputs, what the backward needs)."""
    rot, trans, fx, fy, cx, cy, lim_x, lim_y = camera
    px, py, pz = means.unbind(-1)
    x, y, z = (rot[i][0] * px + rot[i][1] * py + rot[i][2] * pz + trans[i] for i in range(3))
    inv_z = 1.0 / z
    u_raw, v_raw = x * inv_z, y * inv_z
    u, v = u_raw.clamp(-lim_x, lim_x), v_raw.clamp(-lim_y, lim_y)
    # J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]]; W = J R (world to image plane, 2 x 3)
    j00, j02, j11, j12 = fx * inv_z, -fx * u * inv_z, fy * inv_z, -fy * v * inv_z
    w0 = [j00 * rot[0][c] + j02 * rot[2][c] for c in range(3)]
    w1 = [j11 * rot[1][c] + j12 * rot[2][c] for c in range(3)]
    norm = quats.norm(dim=-1).clamp_min(1e-300)
    q = (quats / norm[:, None]).unbind(-1)
    r = _rotation_columns(q)
    s = torch.exp(log_scales).unbind(-1)
    # M = W Rq S: rows m0, m1 (each 3 columns)
    m0 = [(w0[0] * r[c] + w0[1] * r[3 + c] + w0[2] * r[6 + c]) * s[c] for c in range(3)]
    m1 = [(w1[0] * r[c] + w1[1] * r[3 + c] + w1[2] * r[6 + c]) * s[c] for c in range(3)]
    n = _cross(m0, m1)
    sxx0, sxy, syy0 = _dot(m0, m0), _dot(m0, m1), _dot(m1, m1)
    # det(M M^T + 0.3 I) with det(M M^T) as the sum of squared 2x2 minors (Cauchy-Binet): no
    # cancellation at anisotropy 1e6.
    det = _dot(n, n) + LOW_PASS * (sxx0 + syy0) + LOW_PASS * LOW_PASS
    ok = torch.isfinite(det) & (det > 0)
    det = torch.where(ok, det, 1.0)  # rejected Gaussians get finite stand-ins: their gradient is 0
    cxx, cyy = sxx0 + LOW_PASS, syy0 + LOW_PASS
    conic = (cyy / det, -sxy / det, cxx / det)
    outputs = (fx * u_raw + cx, fy * v_raw + cy, *conic, cxx, sxy, cyy, z, ok)
    saved = (x, y, inv_z, u, v, u_raw != u, v_raw != v, q, r, s, norm, w0, w1, m0, m1, n, det, conic, ok)
    return outputs, saved


def _ewa_backward(saved, camera, g_mx, g_my, ga, gb, gc, g_depth):
    """Gradients of means [K, 3], quats [K, 4] and log-scales [K, 3] from those of the outputs."""
    x, y, inv_z, u, v, clamped_u, clamped_v, q, r, s, norm, w0, w1, m0, m1, n, det, conic, ok = saved
    rot, _trans, fx, fy, _cx, _cy, _lim_x, _lim_y = camera
    ca, cb, cc = conic
    # conic = (cyy, -cxy, cxx) / det
    g_det = -(ga * ca + gb * cb + gc * cc) / det
    g_cxx, g_cxy, g_cyy = gc / det, -gb / det, ga / det
    # det = |n|^2 + 0.3 (|m0|^2 + |m1|^2) + 0.09 with n = m0 x m1
    n_m0, m1_n = _cross(n, m0), _cross(m1, n)
    gm0 = [2 * g_cxx * m0[i] + g_cxy * m1[i] + g_det * (2 * m1_n[i] + 2 * LOW_PASS * m0[i]) for i in range(3)]
    gm1 = [2 * g_cyy * m1[i] + g_cxy * m0[i] + g_det * (2 * n_m0[i] + 2 * LOW_PASS * m1[i]) for i in range(3)]
    # M = W (Rq S): m_ic = sum_k w_ik r_kc s_c
    gw0 = [sum(gm0[c] * r[3 * k + c] * s[c] for c in range(3)) for k in range(3)]
    gw1 = [sum(gm1[c] * r[3 * k + c] * s[c] for c in range(3)) for k in range(3)]
    g_rs = [[w0[k] * gm0[c] + w1[k] * gm1[c] for c in range(3)] for k in range(3)]  # d/d(r_kc s_c)
    g_r = [g_rs[k][c] * s[c] for k in range(3) for c in range(3)]
    g_log_scales = [sum(g_rs[k][c] * r[3 * k + c] for k in range(3)) * s[c] for c in range(3)]
    g_unit = _rotation_vjp(q, g_r)
    radial = sum(qi * gi for qi, gi in zip(q, g_unit))
    g_quats = [(gi - qi * radial) / norm for qi, gi in zip(q, g_unit)]  # through q / |q|
    # W = J R: gJ_ik = sum_c gW_ic R_kc
    g_j00 = sum(gw0[c] * rot[0][c] for c in range(3))
    g_j02 = sum(gw0[c] * rot[2][c] for c in range(3))
    g_j11 = sum(gw1[c] * rot[1][c] for c in range(3))
    g_j12 = sum(gw1[c] * rot[2][c] for c in range(3))
    # J: j00 = fx/z, j02 = -fx u/z, j11 = fy/z, j12 = -fy v/z; u = clamp(x/z) (fixed where clamped)
    g_u = torch.where(clamped_u, 0.0, -fx * inv_z * g_j02)
    g_v = torch.where(clamped_v, 0.0, -fy * inv_z * g_j12)
    g_inv_z = fx * g_j00 - fx * u * g_j02 + fy * g_j11 - fy * v * g_j12
    # The centre (fx x/z + cx, fy y/z + cy) uses the unclamped ratios.
    g_u_raw = fx * g_mx + g_u
    g_v_raw = fy * g_my + g_v
    g_cam = [g_u_raw * inv_z, g_v_raw * inv_z, -(g_u_raw * x + g_v_raw * y + g_inv_z) * inv_z * inv_z]
    if g_depth is not None:
        g_cam[2] = g_cam[2] + g_depth
    g_means = [sum(g_cam[i] * rot[i][c] for i in range(3)) for c in range(3)]  # p_cam = R p + t
    # Rejected Gaussians may hold inf * 0 above: their gradient is 0.
    return tuple(torch.where(ok[:, None], torch.stack(g, -1), 0.0) for g in (g_means, g_quats, g_log_scales))


class _EWA(torch.autograd.Function):
    """EWA projection on per-component float64 columns, with a hand-written backward.

    Autograd through small [K, 2, 3] matrix products spent most of a view's time on bookkeeping; here
    every step is one elementwise pass over a cache-sized chunk of Gaussians (each pass spread over
    torch's threads). Returns
    [K] columns: the centre mx, my and the conic a, b, c (differentiable), the covariance xx, xy, yy,
    the depth and ok (det > 0 and finite).
    """

    @staticmethod
    def forward(ctx, means, quats, log_scales, camera):
        k = means.shape[0]
        chunks = [(i, min(i + CHUNK, k)) for i in range(0, k, CHUNK)] or [(0, 0)]

        parts = [_ewa_forward(means[i:j], quats[i:j], log_scales[i:j], camera) for i, j in chunks]
        outputs = [torch.cat(column) for column in zip(*(out for out, _ in parts))]
        ctx.chunks, ctx.saved, ctx.camera = chunks, [saved for _, saved in parts], camera
        ctx.mark_non_differentiable(*outputs[5:])
        return tuple(outputs)

    @staticmethod
    def backward(ctx, g_mx, g_my, ga, gb, gc, _g_cxx, _g_cxy, _g_cyy, g_depth, _g_ok):
        grads = [
            _ewa_backward(
                saved,
                ctx.camera,
                g_mx[i:j],
                g_my[i:j],
                ga[i:j],
                gb[i:j],
                gc[i:j],
                None if g_depth is None else g_depth[i:j],
            )
            for (i, j), saved in zip(ctx.chunks, ctx.saved)
        ]
        return (*(torch.cat(g) for g in zip(*grads)), None)


def _ewa_frozen(cam, covariances, camera):
    """What :class:`_EWA` outputs, for geometry that needs no gradient: from camera-space centres [K, 3] and the
    splats' world covariances [K, 6] (:func:`splat_covariances` in float64, made once for every view).

    The same float64 EWA in a few operations a splat: the covariance in camera space is one [K, 6] x [6, 6] product,
    and with the Jacobian's rows fx/z (e0 - u e2) and fy/z (e1 - v e2), cxx = (fx/z)^2 (S00 - 2u S02 + u^2 S22) and
    likewise. The determinant's cancellation (cxx cyy - cxy^2 of a needle) costs eps x cxx cyy, far below the
    low-pass's share of it, 0.3 (cxx + cyy), at any size a splat can have on screen."""
    rot, _trans, fx, fy, cx, cy, lim_x, lim_y = camera
    rows = torch.tensor(rot, dtype=torch.float64, device=cam.device)
    forms = torch.stack([_quadratic_forms(rows[i], rows[j]) for i, j in _PAIRS], 1)  # [6, 6]
    s00, s11, s22, s01, s02, s12 = (covariances @ forms).unbind(-1)
    x, y, z = cam.unbind(-1)
    inv_z = 1.0 / z
    u_raw, v_raw = x * inv_z, y * inv_z
    u, v = u_raw.clamp(-lim_x, lim_x), v_raw.clamp(-lim_y, lim_y)
    jx, jy = fx * inv_z, fy * inv_z
    sxx0 = jx * jx * (s00 - 2.0 * u * s02 + u * u * s22)
    syy0 = jy * jy * (s11 - 2.0 * v * s12 + v * v * s22)
    sxy = jx * jy * (s01 - v * s02 - u * s12 + u * v * s22)
    det = (sxx0 * syy0 - sxy * sxy).clamp_min(0.0) + LOW_PASS * (sxx0 + syy0) + LOW_PASS * LOW_PASS
    ok = torch.isfinite(det) & (det > 0)
    det = torch.where(ok, det, 1.0)
    cxx, cyy = sxx0 + LOW_PASS, syy0 + LOW_PASS
    return fx * u_raw + cx, fy * v_raw + cy, cyy / det, -sxy / det, cxx / det, cxx, sxy, cyy, z, ok


def _on_screen(means_cam, log_scales, fx, fy, cx, cy, width, height, lim_x, lim_y):
    """Conservative cull: False only for Gaussians whose alpha >= 1/255 ellipse surely misses the image.

    Power <= 2 ln 255 reaches at most 3.33 of the largest 2D standard deviation, which is at most
    ||J||_F sigma_max with the clamped Jacobian, plus the low-pass.
    """
    x, y, z = means_cam.unbind(-1)
    sigma = torch.exp(log_scales.amax(-1))
    j2 = (fx * fx * (1 + lim_x * lim_x) + fy * fy * (1 + lim_y * lim_y)) / (z * z)
    reach = math.sqrt(2.0 * math.log(255.0)) * torch.sqrt(j2 * sigma * sigma + LOW_PASS) + 1.0
    mx, my = fx * x / z + cx, fy * y / z + cy
    return (mx + reach > 0) & (mx - reach < width) & (my + reach > 0) & (my - reach < height)


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
    covariances: torch.Tensor | None = None,  # [N, 6] float64 splat_covariances, when the geometry has no gradient
) -> Projected:
    """EWA splatting of 3D Gaussians (Zwicker et al.; graphdeco's computeCov2D).

    Culls non-finite Gaussians, those with z <= near and those surely off screen *before* any
    differentiable arithmetic on them, so that their gradients are exactly zero rather than NaN. Geometry that needs
    no gradient, given its ``covariances`` (made once for a scene rendered from many views), takes a shorter path
    (:func:`_ewa_frozen`, the same to ~1e-12).
    """
    f64 = torch.float64
    w2c = world_to_camera.to(means.device, f64)
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    lim_x = FRUSTUM_GUARD * width / (2.0 * fx)
    lim_y = FRUSTUM_GUARD * height / (2.0 * fy)
    with torch.no_grad():
        finite = torch.isfinite(means).all(-1) & torch.isfinite(quats).all(-1) & torch.isfinite(log_scales).all(-1)
        if valid is not None:
            finite &= valid
        cam = torch.where(finite[:, None], means.detach().to(f64) @ rot.T + trans, torch.ones((), dtype=f64))
        front = finite & (cam[:, 2] > near)
        seen = _on_screen(cam, log_scales.detach().to(f64), fx, fy, cx, cy, width, height, lim_x, lim_y)
        index = torch.nonzero(front & seen).squeeze(-1)
    camera = (rot.tolist(), trans.tolist(), fx, fy, cx, cy, lim_x, lim_y)
    frozen = covariances is not None and not (
        torch.is_grad_enabled() and any(t.requires_grad for t in (means, quats, log_scales))
    )
    if frozen:
        with torch.no_grad():
            covariances = covariances.to(means.device, f64)
            pieces = [
                _ewa_frozen(cam.index_select(0, part), covariances.index_select(0, part), camera)
                for part in [index[:0], *index.split(CHUNK)]
            ]
            columns = [torch.cat(column) for column in zip(*pieces)]
    else:
        columns = _EWA.apply(
            torch.index_select(means, 0, index).to(f64),
            torch.index_select(quats, 0, index).to(f64),
            torch.index_select(log_scales, 0, index).to(f64),
            camera,
        )
    ok = columns[-1]
    keep = torch.nonzero(ok).squeeze(-1)
    if keep.numel() < ok.numel():
        index, columns = index[keep], [torch.index_select(c, 0, keep) for c in columns]
    return Projected(index, *columns[:-1])


def splat_covariances(
    quats: torch.Tensor, log_scales: torch.Tensor, dtype: torch.dtype = torch.float32
) -> torch.Tensor:  # -> [N, 6]
    """The 3D covariance (R S)(R S)^T of each Gaussian as its six entries xx, yy, zz, xy, xz, yz: what
    :func:`projected_mean_variance` (float32) and :func:`project_gaussians` (float64) reuse for every view."""
    tiny = 1e-300 if dtype == torch.float64 else 1e-30
    q = (quats.to(dtype) / quats.to(dtype).norm(dim=-1, keepdim=True).clamp_min(tiny)).unbind(-1)
    m = torch.stack(_rotation_columns(q), -1).reshape(-1, 3, 3) * torch.exp(log_scales.to(dtype))[:, None, :]
    rows = m.unbind(1)  # each [N, 3]: row i of R S
    return torch.stack([(rows[i] * rows[j]).sum(-1) for i, j in _PAIRS], -1)


def _quadratic_forms(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # [3], [3] -> [6]
    """Coefficients of a^T S b over the six entries of a symmetric S (as splat_covariances orders them)."""
    return torch.stack([a[i] * b[j] + (a[j] * b[i] if i != j else 0.0) for i, j in _PAIRS])


def projected_mean_variance(
    means: torch.Tensor,  # [N, 3] world, Gaussians in front of the camera (z > near)
    covariances: torch.Tensor,  # [N, 6] splat_covariances(quats, log_scales)
    world_to_camera: torch.Tensor,  # [4, 4]
    fx: float,
    fy: float,
    width: int,
    height: int,
) -> torch.Tensor:  # -> [N] float32, pixels^2
    """The mean of the two eigenvalues of each Gaussian's 2D covariance on screen, the low-pass included:
    (cxx + cyy) / 2 of :func:`project_gaussians` (the same clamped EWA Jacobian), in float32, without gradients,
    culling or the conic, for statistics of the splats' size on screen.

    With the Jacobian's rows fx/z (r0 - u r2) and fy/z (r1 - v r2) (r_i the camera rotation's rows),
    cxx = (fx/z)^2 (r0' S r0 - 2u r0' S r2 + u^2 r2' S r2) + 0.3 and cyy likewise: the five view-constant
    quadratic forms of each S are one [N, 6] x [6, 5] product, then a few operations per Gaussian."""
    w2c = world_to_camera.to(means.device, torch.float32)
    rot = w2c[:3, :3]
    cam = means.float() @ rot.T + w2c[:3, 3]
    inv_z = 1.0 / cam[:, 2]
    lim_x, lim_y = FRUSTUM_GUARD * width / (2.0 * fx), FRUSTUM_GUARD * height / (2.0 * fy)
    u = (cam[:, 0] * inv_z).clamp(-lim_x, lim_x)
    v = (cam[:, 1] * inv_z).clamp(-lim_y, lim_y)
    r0, r1, r2 = rot.unbind(0)
    coefficients = torch.stack(
        [_quadratic_forms(a, b) for a, b in ((r0, r0), (r0, r2), (r2, r2), (r1, r1), (r1, r2))], 1
    )  # [6, 5]
    s00, s02, s22, s11, s12 = (covariances.float() @ coefficients).unbind(-1)
    cxx = (fx * inv_z).square() * (s00 - 2.0 * u * s02 + u * u * s22)
    cyy = (fy * inv_z).square() * (s11 - 2.0 * v * s12 + v * v * s22)
    return 0.5 * (cxx + cyy) + LOW_PASS
