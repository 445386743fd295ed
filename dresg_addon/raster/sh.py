"""Spherical-harmonics colour evaluation (degrees 0-3), as in graphdeco 3DGS."""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(directions: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis of unit ``directions`` [..., 3] up to ``degree``: [..., (degree+1)^2]."""
    x, y, z = directions.unbind(-1)
    terms = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        terms += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        terms += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        terms += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(terms, dim=-1)


def colors_from_sh(
    sh_dc: torch.Tensor,  # [N, 3]
    sh_rest: torch.Tensor | None,  # [N, K, 3] or None
    means: torch.Tensor | None = None,  # [N, 3], needed when sh_rest is given
    camera_center: torch.Tensor | None = None,  # [3]
) -> torch.Tensor:
    """RGB [N, 3] = max(0, 0.5 + sum_k SH_k(dir) coeff_k), dir = normalize(mean - camera centre).

    With no ``sh_rest`` this is the view-independent DC colour and needs no geometry.
    """
    if sh_rest is None or sh_rest.shape[1] == 0:
        return torch.clamp_min(0.5 + SH_C0 * sh_dc, 0.0)
    degree = {3: 1, 8: 2, 15: 3}[sh_rest.shape[1]]
    directions = means - camera_center.to(means)
    directions = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(directions.to(sh_dc.dtype), degree)  # [N, (d+1)^2]
    coeffs = torch.cat([sh_dc[:, None, :], sh_rest], dim=1)  # [N, (d+1)^2, 3]
    return torch.clamp_min(0.5 + (basis[:, :, None] * coeffs).sum(1), 0.0)
