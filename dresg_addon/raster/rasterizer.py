"""The fast rasterizer: exact per-row pixel spans, (pixel, depth) sort, log-space compositing.

Pipeline for one view (one small function per stage):

1. :func:`project_gaussians` (float64, per Gaussian): EWA projection and culling.
2. :func:`_row_extents`: the exact ellipse where alpha >= 1/255, i.e. power <= 2 ln(255 o).
3. :func:`_plan_bands`: split the image into row bands holding at most ``band_pairs`` pairs, so no
   tensor ever grows with pixels x Gaussians and large tensors stay within cache-friendly sizes.
4. :func:`_band_pairs`: per (Gaussian, row) the exact span of pixel centres inside the ellipse, widened
   by one pixel and filtered with the exact alpha test; sorted by (pixel, depth).
5. :class:`_Composite`: front-to-back compositing with transmittance as a float64 segmented cumulative
   sum of log(1 - alpha), and a hand-written backward (the one graphdeco uses, in log space).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch

from ..camera import Camera
from .projection import project_gaussians

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
LOG_T_MIN = math.log(T_MIN)


@dataclass(frozen=True)
class RasterSettings:
    near: float = 0.01
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Speed knobs; the defaults are the exact definition.
    dtype: torch.dtype = torch.float64  # per-sample arithmetic
    accumulate: torch.dtype = torch.float64  # the per-pixel scans (float32 scans cancel over long bands)
    tile_size: int = 0  # 0: exact per-row spans; > 0: every pixel of every tile the bounding box touches
    max_per_pixel: int = 0  # 0: no cap; > 0: at most this many samples per pixel (front-most)
    truncation_sigma: float = 0.0  # 0: none; > 0: also cut at this many standard deviations
    band_pairs: int = 2_000_000  # memory bound: pairs per row band
    depth_tolerance: float = 0.1  # relative depth difference that counts as inconsistent (visibility)


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # [H, W, 3]
    alpha: torch.Tensor  # [H, W] = 1 - final transmittance
    depth: torch.Tensor  # [H, W] expected depth of the visible samples (0 where alpha = 0); no gradient
    visibility: torch.Tensor | None  # [N] sum over pixels of T * alpha (no gradient)
    n_pairs: int  # samples composited
    contributions: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # pixel, gaussian, T*alpha


def _row_extents(means2d, cov2d, r2, height):
    """Rows [y0, y1] whose pixel centres can lie inside power <= r2 (inclusive, clamped)."""
    half = torch.sqrt(r2 * cov2d[:, 2])
    y0 = torch.clamp(torch.ceil(means2d[:, 1] - half - 0.5), min=0)
    y1 = torch.clamp(torch.floor(means2d[:, 1] + half - 0.5), max=height - 1)
    return y0.long(), y1.long()


def _col_extents(means2d, cov2d, r2, width):
    half = torch.sqrt(r2 * cov2d[:, 0])
    x0 = torch.clamp(torch.ceil(means2d[:, 0] - half - 0.5), min=0)
    x1 = torch.clamp(torch.floor(means2d[:, 0] + half - 0.5), max=width - 1)
    return x0.long(), x1.long()


def _plan_bands(y0, y1, est_per_row, height, budget):
    """Row bands [r0, r1) whose estimated pair counts stay under ``budget`` (at least one row each)."""
    if y0.numel() == 0:
        return [(0, height)]
    diff = torch.zeros(height + 1, dtype=torch.float64)
    diff.index_add_(0, y0, est_per_row)
    diff.index_add_(0, y1 + 1, -est_per_row)
    per_row = torch.cumsum(diff[:-1], 0).tolist()
    bands, start, acc = [], 0, 0.0
    for row, count in enumerate(per_row):
        if acc > 0 and acc + count > budget:
            bands.append((start, row))
            start, acc = row, 0.0
        acc += count
    bands.append((start, height))
    return bands


def _take(values, index):
    """values[index] along dim 0; index_select is several times faster than advanced indexing on CPU."""
    return torch.index_select(values, 0, index)


def _expand(counts):
    """For counts [E]: (owner [P], local offset [P]) with P = counts.sum()."""
    owner = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(owner.numel(), device=counts.device) - _take(starts, owner)
    return owner, local


def _band_pairs(means2d, cov2d, conic, opac, r2, y0, y1, r0, r1, width, settings):
    """(g, pixel, o G) of the pairs of one band with alpha >= 1/255, sorted by (pixel, depth). No gradients.

    ``g`` indexes the band's Gaussians, which arrive sorted by depth, so g is also the depth rank.
    """
    mx_g, my_g = means2d[:, 0].contiguous(), means2d[:, 1].contiguous()
    ca_g, cb_g, cc_g = (conic[:, i].contiguous() for i in range(3))
    rows_lo = torch.clamp(y0, min=r0)
    rows_hi = torch.clamp(y1, max=r1 - 1)
    n_rows = (rows_hi - rows_lo + 1).clamp_min(0)
    entry_g, local = _expand(n_rows)
    row = _take(rows_lo, entry_g) + local
    if settings.tile_size > 0:
        # Tile candidates: the bounding box widened to tile boundaries (graphdeco style), then filtered.
        tile = settings.tile_size
        x0, x1 = _col_extents(means2d, cov2d, r2, width)
        xl = _take(x0 // tile * tile, entry_g)
        xr = _take(torch.clamp((x1 // tile + 1) * tile - 1, max=width - 1), entry_g)
    else:
        # Exact span: a dx^2 + 2 b dx dy + c dy^2 <= r2 solved for dx at this row's centre.
        a, b, c = _take(ca_g, entry_g), _take(cb_g, entry_g), _take(cc_g, entry_g)
        mx = _take(mx_g, entry_g)
        dy = row.to(torch.float64) + 0.5 - _take(my_g, entry_g)
        disc = b * b * dy * dy - a * (c * dy * dy - _take(r2, entry_g))
        root = torch.sqrt(torch.clamp_min(disc, 0.0))
        xl = torch.clamp(torch.ceil(mx + (-b * dy - root) / a - 0.5), min=0).long()
        xr = torch.clamp(torch.floor(mx + (-b * dy + root) / a - 0.5), max=width - 1).long()
        xr = torch.where(disc >= 0, xr, xl - 1)
    span = (xr - xl + 1).clamp_min(0)
    pair_entry, x_local = _expand(span)
    g = _take(entry_g, pair_entry)
    x = _take(xl, pair_entry) + x_local
    y = _take(row, pair_entry)
    del pair_entry, x_local
    dtype = settings.dtype
    dx = (x.to(dtype) + 0.5) - _take(mx_g.to(dtype), g)
    dy = (y.to(dtype) + 0.5) - _take(my_g.to(dtype), g)
    power = (
        _take(ca_g.to(dtype), g) * dx * dx
        + 2.0 * _take(cb_g.to(dtype), g) * dx * dy
        + _take(cc_g.to(dtype), g) * dy * dy
    )
    raw = _take(opac.to(dtype), g) * torch.exp(-0.5 * power)  # o G before the 0.99 clamp
    keep = raw >= ALPHA_MIN
    if settings.truncation_sigma > 0:
        keep &= power <= settings.truncation_sigma**2
    keep = torch.nonzero(keep).squeeze(-1)
    g, raw = _take(g, keep), _take(raw, keep)
    pixel = (_take(y, keep) - r0) * width + _take(x, keep)
    n_g = means2d.shape[0]
    n_pix = (r1 - r0) * width
    key_dtype = torch.int32 if n_pix * max(n_g, 1) < 2**31 else torch.int64
    key = pixel.to(key_dtype) * n_g + g.to(key_dtype)
    order = torch.sort(key).indices
    return _take(g, order), _take(pixel, order), _take(raw, order)


def _segments(pixel):
    """For pairs sorted by pixel: index of each pair's segment start and end (inclusive)."""
    n = pixel.numel()
    new = torch.ones(n, dtype=torch.bool, device=pixel.device)
    new[1:] = pixel[1:] != pixel[:-1]
    starts = torch.nonzero(new).squeeze(-1)
    seg = torch.cumsum(new, 0) - 1
    ends = torch.empty_like(starts)
    ends[:-1] = starts[1:] - 1
    if ends.numel():
        ends[-1] = n - 1
    return _take(starts, seg), _take(ends, seg)


def _pixel_offsets(means2d, g, pixel, r0, width, dtype):
    """(dx, dy) [P] from each pair's Gaussian centre to its pixel centre."""
    x = pixel % width
    y = pixel // width + r0
    dx = (x.to(dtype) + 0.5) - _take(means2d[:, 0].to(dtype), g)
    dy = (y.to(dtype) + 0.5) - _take(means2d[:, 1].to(dtype), g)
    return dx, dy


def _rowdot(a, b):
    """sum over the last axis (size 3) of a * b, as three fused multiply-adds (a small-axis sum is slow)."""
    return torch.addcmul(torch.addcmul(a[:, 0] * b[:, 0], a[:, 1], b[:, 1]), a[:, 2], b[:, 2])


class _Composite(torch.autograd.Function):
    """Front-to-back compositing of one band, with the analytic backward in log space.

    Forward: T_k = exp(sum_{j<k} log(1 - a_j)) within each pixel; samples with T_k (1 - a_k) < 1e-4
    (and all behind them) are left out; C = sum T_k a_k c_k + T_final * background.
    Backward: dC/da_k = T_k c_k - (sum_{j>k} T_j a_j c_j + T_final bg) / (1 - a_k), safe since a <= 0.99.
    """

    @staticmethod
    def forward(ctx, means2d, conic, opac, colors, g, pixel, raw, depth, meta):
        r0, width, n_pix, background, dtype, accumulate, cap = meta
        alpha = torch.clamp_max(raw, ALPHA_MAX)
        unclamped = raw < ALPHA_MAX
        log1m = torch.log1p(-alpha)
        start, end = _segments(pixel)
        wide = log1m.to(accumulate)
        excl = torch.cumsum(wide, 0) - wide
        log_t = (excl - _take(excl, start)).to(dtype)
        include = (log_t + log1m) >= LOG_T_MIN
        if cap > 0:
            include &= (torch.arange(pixel.numel(), device=pixel.device) - start) < cap
        t_before = torch.exp(log_t)
        weight = torch.where(include, t_before * alpha, torch.zeros((), dtype=dtype))
        cols = colors.to(dtype)
        rgb = torch.zeros(n_pix, 3, dtype=dtype, device=colors.device)
        rgb.index_add_(0, pixel, weight[:, None] * _take(cols, g))
        log_final = torch.zeros(n_pix, dtype=dtype, device=colors.device)
        log_final.index_add_(0, pixel, torch.where(include, log1m, torch.zeros((), dtype=dtype)))
        t_final = torch.exp(log_final)
        bg = torch.tensor(background, dtype=dtype, device=colors.device)
        rgb = rgb + t_final[:, None] * bg
        with torch.no_grad():
            wsum = torch.zeros(n_pix, dtype=dtype, device=colors.device).index_add_(0, pixel, weight)
            dsum = torch.zeros(n_pix, dtype=dtype, device=colors.device).index_add_(
                0, pixel, weight * _take(depth.to(dtype), g)
            )
            pix_depth = torch.where(wsum > 0, dsum / torch.where(wsum > 0, wsum, 1.0), 0.0)
        ctx.save_for_backward(
            means2d, conic, opac, colors, g, pixel, alpha, unclamped, t_before, weight, t_final, start, end
        )
        ctx.meta = meta
        ctx.mark_non_differentiable(pix_depth, weight)
        return rgb.to(colors.dtype), t_final.to(colors.dtype), pix_depth, weight

    @staticmethod
    def backward(ctx, grad_rgb, grad_t, _grad_depth, _grad_weight):
        means2d, conic, opac, colors, g, pixel, alpha, unclamped, t_before, weight, t_final, start, end = (
            ctx.saved_tensors
        )
        r0, width, n_pix, background, dtype, accumulate, _ = ctx.meta
        gr = grad_rgb.to(dtype)
        bg = torch.tensor(background, dtype=dtype, device=gr.device)
        tail = gr @ bg
        if grad_t is not None:
            tail = tail + grad_t.to(dtype)
        tail = t_final * tail  # [n_pix]: d/dT_final contribution, times T_final
        gr_pair = _take(gr, pixel)  # [P, 3]
        dot = _rowdot(gr_pair, _take(colors.to(dtype), g))  # G_p . c_k
        cs = torch.cumsum((weight * dot).to(accumulate), 0)
        behind = (_take(cs, end) - cs).to(dtype)  # sum_{j>k} T_j a_j (G . c_j)
        included = weight > 0
        d_alpha = torch.where(
            included, t_before * dot - (behind + _take(tail, pixel)) / (1.0 - alpha), torch.zeros((), dtype=dtype)
        )
        d_alpha = torch.where(unclamped, d_alpha, torch.zeros((), dtype=dtype))
        n_g = means2d.shape[0]
        grad_colors = torch.zeros(n_g, 3, dtype=dtype, device=gr.device).index_add_(0, g, weight[:, None] * gr_pair)
        # alpha = o G: d alpha / d o = alpha / o; d alpha / d power = -alpha / 2 (both where unclamped).
        grad_opac = torch.zeros(n_g, dtype=dtype, device=gr.device).index_add_(0, g, d_alpha * alpha)
        grad_opac = grad_opac / opac.to(dtype)
        dx, dy = _pixel_offsets(means2d, g, pixel, r0, width, dtype)
        d_power = -0.5 * alpha * d_alpha
        ca, cb, cc = (_take(conic[:, i].to(dtype), g) for i in range(3))
        d_mean = torch.stack([-2.0 * (ca * dx + cb * dy), -2.0 * (cb * dx + cc * dy)], -1)
        grad_means2d = torch.zeros(n_g, 2, dtype=dtype, device=gr.device).index_add_(0, g, d_power[:, None] * d_mean)
        d_conic = torch.stack([dx * dx, 2.0 * dx * dy, dy * dy], -1)
        grad_conic = torch.zeros(n_g, 3, dtype=dtype, device=gr.device).index_add_(0, g, d_power[:, None] * d_conic)
        return (
            grad_means2d.to(means2d.dtype),
            grad_conic.to(conic.dtype),
            grad_opac.to(opac.dtype),
            grad_colors.to(colors.dtype),
            None,
            None,
            None,
            None,
            None,
        )


def render(
    means: torch.Tensor,  # [N, 3] world
    quats: torch.Tensor,  # [N, 4] (w, x, y, z)
    log_scales: torch.Tensor,  # [N, 3]
    opacity_logits: torch.Tensor,  # [N]
    colors: torch.Tensor,  # [N, 3] RGB
    camera: Camera,
    settings: RasterSettings = RasterSettings(),
    visibility: str | None = None,  # None | "all" | "depth_consistent"
    keep_contributions: bool = False,
) -> RenderOutput:
    """Render one view. Differentiable in means, quats, log_scales, opacity_logits and colors.

    Gaussians with any non-finite parameter are skipped (zero gradient). Outputs have the dtype of
    ``colors``; ``settings.dtype`` sets the per-sample arithmetic.
    """
    n = means.shape[0]
    for name, tensor, shape in (
        ("means", means, (n, 3)),
        ("quats", quats, (n, 4)),
        ("log_scales", log_scales, (n, 3)),
        ("opacity_logits", opacity_logits, (n,)),
        ("colors", colors, (n, 3)),
    ):
        if tuple(tensor.shape) != shape:
            raise ValueError(f"render: {name} has shape {tuple(tensor.shape)}, expected {shape}")
    if visibility not in (None, "all", "depth_consistent"):
        raise ValueError(f"render: visibility must be None, 'all' or 'depth_consistent', not {visibility!r}")
    device, out_dtype = colors.device, colors.dtype
    height, width = camera.height, camera.width
    w2c = torch.as_tensor(camera.world_to_camera, dtype=torch.float64, device=device)
    valid = torch.isfinite(opacity_logits.detach()) & torch.isfinite(colors.detach()).all(-1)
    proj = project_gaussians(
        means, quats, log_scales, w2c, camera.fx, camera.fy, camera.cx, camera.cy, width, height, settings.near, valid
    )
    opac = torch.sigmoid(opacity_logits[proj.index].to(torch.float64))
    with torch.no_grad():
        r2 = 2.0 * torch.log(255.0 * opac)  # alpha >= 1/255  <=>  power <= 2 ln(255 o)
        if settings.truncation_sigma > 0:
            r2 = torch.clamp_max(r2, settings.truncation_sigma**2)
        r2 = r2 * (1.0 + 1e-9) + 1e-9  # candidates only; the exact alpha test decides
        y0, y1 = _row_extents(proj.means2d, proj.cov2d, r2.clamp_min(0), height)
        x0, x1 = _col_extents(proj.means2d, proj.cov2d, r2.clamp_min(0), width)
        alive = (r2 > 0) & (y0 <= y1) & (x0 <= x1)
        order = torch.nonzero(alive).squeeze(-1)
        order = order[torch.sort(proj.depth.detach()[order], stable=True).indices]
    g_index = proj.index[order]  # [M] input indices, front to back
    means2d = proj.means2d[order]
    conic = proj.conic[order]
    cov2d = proj.cov2d.detach()[order]
    opac = opac[order]
    depth = proj.depth.detach()[order]
    cols = colors[g_index]
    r2, y0, y1 = r2[order], y0[order], y1[order]
    est = torch.clamp(2.0 * torch.sqrt(r2 * cov2d[:, 0]) + 3.0, max=width)
    bands = _plan_bands(y0, y1, est, height, settings.band_pairs)
    cap = settings.max_per_pixel
    rgb_parts, t_parts, depth_parts = [], [], []
    vis = torch.zeros(order.numel(), dtype=settings.dtype, device=device) if visibility else None
    contrib = []
    n_pairs = 0
    for r0, r1 in bands:
        n_pix = (r1 - r0) * width
        with torch.no_grad():
            in_band = torch.nonzero((y0 < r1) & (y1 >= r0)).squeeze(-1)
            g, pixel, raw = _band_pairs(
                means2d.detach()[in_band], cov2d[in_band], conic.detach()[in_band], opac.detach()[in_band],
                r2[in_band], y0[in_band], y1[in_band], r0, r1, width, settings,
            )  # fmt: skip
        meta = (r0, width, n_pix, tuple(settings.background), settings.dtype, settings.accumulate, cap)
        rgb_b, t_b, depth_b, weight = _Composite.apply(
            means2d[in_band], conic[in_band], opac[in_band], cols[in_band], g, pixel, raw, depth[in_band], meta
        )
        rgb_parts.append(rgb_b)
        t_parts.append(t_b)
        depth_parts.append(depth_b)
        n_pairs += int((weight > 0).sum())
        if visibility or keep_contributions:
            used = weight > 0
            if visibility == "depth_consistent":
                d_g, d_p = depth[in_band][g], depth_b[pixel]
                used &= (d_g - d_p).abs() <= settings.depth_tolerance * d_p
            if visibility:
                vis.index_add_(0, in_band[g[used]], weight[used])
            if keep_contributions:
                nz = weight > 0
                contrib.append((pixel[nz] + r0 * width, g_index[in_band[g[nz]]], weight[nz].float()))
    rgb = torch.cat(rgb_parts).reshape(height, width, 3)
    alpha = (1.0 - torch.cat(t_parts)).reshape(height, width)
    depth_img = torch.cat(depth_parts).reshape(height, width).to(out_dtype)
    vis_full = None
    if visibility:
        vis_full = torch.zeros(n, dtype=out_dtype, device=device)
        vis_full[g_index] = vis.to(out_dtype)
    contributions = None
    if keep_contributions:
        contributions = tuple(torch.cat(parts) for parts in zip(*contrib)) if contrib else None
    return RenderOutput(rgb, alpha, depth_img, vis_full, n_pairs, contributions)


class _SparseColor(torch.autograd.Function):
    """rgb = W @ colors for a cached sparse W [P, N]; the backward is W^T @ grad."""

    @staticmethod
    def forward(ctx, colors, matrix, matrix_t):
        ctx.matrix_t = matrix_t
        return torch.sparse.mm(matrix, colors)

    @staticmethod
    def backward(ctx, grad):
        return torch.sparse.mm(ctx.matrix_t, grad.contiguous()), None, None


class ColorOnlyRenderer:
    """Colour-only fast path for frozen geometry.

    With means, scales, rotations and opacities fixed, the image is linear in the colours:
    rgb = W c + T_final * background, where W [H*W, N] holds each sample's T * alpha. W is computed once
    per view and a colour step is a sparse multiply, forward and backward.
    """

    def __init__(
        self, means, quats, log_scales, opacity_logits, camera: Camera, settings: RasterSettings = RasterSettings()
    ):
        n = means.shape[0]
        with torch.no_grad():
            dummy = torch.zeros(n, 3, dtype=torch.float32, device=means.device)
            out = render(means, quats, log_scales, opacity_logits, dummy, camera, settings, keep_contributions=True)
        self.camera = camera
        self.shape = (camera.height, camera.width)
        empty = torch.zeros(0, dtype=torch.long, device=means.device)
        # Contributions arrive sorted by pixel (bands in order, pixels sorted within each band): CSR rows.
        self._pixel, self._gauss, self._weight = out.contributions or (empty, empty, empty.float())
        bg = torch.tensor(settings.background, dtype=torch.float32, device=means.device)
        self.background = (1.0 - out.alpha.reshape(-1, 1).float()) * bg  # [H*W, 3]
        self.alpha = out.alpha.float()
        self.depth = out.depth.float()
        self.n_pairs = out.n_pairs
        # Gaussians this view sees at all: the colour step can leave out the rest.
        self.seen = torch.zeros(n, dtype=torch.bool, device=means.device)
        self.seen[self._gauss] = True
        self._build(n)

    def _build(self, n_columns: int) -> None:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            self._build_matrices(n_columns)

    def _build_matrices(self, n_columns: int) -> None:
        n_pix = self.shape[0] * self.shape[1]
        crow = torch.zeros(n_pix + 1, dtype=torch.long, device=self._pixel.device)
        crow[1:] = torch.cumsum(torch.bincount(self._pixel, minlength=n_pix), 0)
        self.matrix = torch.sparse_csr_tensor(
            crow, self._gauss, self._weight, (n_pix, n_columns), check_invariants=False
        )
        order = torch.sort(self._gauss, stable=True).indices
        crow_t = torch.zeros(n_columns + 1, dtype=torch.long, device=self._pixel.device)
        crow_t[1:] = torch.cumsum(torch.bincount(self._gauss, minlength=n_columns), 0)
        self.matrix_t = torch.sparse_csr_tensor(
            crow_t, self._pixel[order], self._weight[order], (n_columns, n_pix), check_invariants=False
        )

    def restrict(self, keep: torch.Tensor) -> ColorOnlyRenderer:
        """Use only the Gaussians ``keep`` (sorted indices, a superset of ``seen``): colours become [len(keep), 3]."""
        column = torch.full((self.seen.numel(),), -1, dtype=torch.long, device=keep.device)
        column[keep] = torch.arange(keep.numel(), device=keep.device)
        self._gauss = column[self._gauss]
        if (self._gauss < 0).any():
            raise ValueError("restrict: every Gaussian the view sees must be kept")
        self.seen = self.seen[keep]
        self._build(keep.numel())
        return self

    def __call__(self, colors: torch.Tensor) -> torch.Tensor:  # [N, 3] -> [H, W, 3]
        rgb = _SparseColor.apply(colors.float(), self.matrix, self.matrix_t) + self.background
        return rgb.reshape(*self.shape, 3)


def render_scene(
    scene, camera: Camera, settings: RasterSettings = RasterSettings(), visibility=None, device="cpu"
) -> RenderOutput:
    """Render a :class:`~dresg_addon.scene.GaussianScene` (numpy) without gradients, in float32 output."""
    from .sh import colors_from_sh

    def t(a):
        return torch.from_numpy(a).to(device)

    means = t(scene.means)
    center = torch.as_tensor(camera.center, dtype=torch.float32, device=device)
    with torch.no_grad():
        sh_rest = None if scene.sh_rest is None else t(scene.sh_rest)
        colors = colors_from_sh(t(scene.sh_dc), sh_rest, means, center)
        return render(
            means, t(scene.quats), t(scene.log_scales), t(scene.opacity_logits), colors, camera, settings, visibility
        )
