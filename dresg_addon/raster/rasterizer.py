"""The fast rasterizer: exact per-row pixel spans, (pixel, depth) sort, log-space compositing.

Pipeline for one view (one small function per stage):

1. :func:`project_gaussians` (float64, per Gaussian): EWA projection and culling, as 1D columns.
2. :func:`_row_extents`: the rows where the ellipse alpha >= 1/255, i.e. power <= 2 ln(255 o), has pixels.
3. :func:`_plan_bands`: split the image into row bands of at most ``band_pairs`` candidate samples, so no
   tensor grows with pixels x Gaussians and the per-sample tensors stay cache-sized.
4. :func:`_row_entries`: one entry per (Gaussian, row) with the exact span of pixel centres inside the
   ellipse. On a row at offset dy the power is a (dx - s)^2 + dy^2 / cov_yy with s = dy cov_xy / cov_yy
   (completing the square), so each sample costs one multiply-add and an exp.
5. :func:`_band_samples`: the entries' samples, sorted by (pixel, depth), alpha-tested and cut at
   T < 1e-4 with a float64 scan of log(1 - alpha); only the samples that count are kept.
6. :class:`_Rasterize`: front-to-back compositing of the kept samples, band by band, and its analytic
   backward (graphdeco's, in log space). The power's gradient is summed per entry as three moments in
   the sample's offset, so the per-sample backward never recomputes pixel offsets.

Per-sample arithmetic runs in the dtype of the colours (float32 renders, float64 for gradcheck); the
scans that accumulate along a pixel stay in float64 (float32 scans cost 5e-4 for no time), which keeps
float32 renders within ~1e-6 of the float64 reference. Per-Gaussian data are kept as 1D columns: on CPU a gather of
a 1D tensor is several times faster than one of rows of a [N, 3] tensor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..scene.camera import Camera
from .projection import project_gaussians, splat_covariances
from .workers import cpu_workers, in_workers

# Memory a render holds, measured on CPU renders: outputs and per-pixel scans, and each kept candidate
# sample (its entry, sample and weight columns). Checked against the available memory before a large render.
BYTES_PER_PIXEL = 64
BYTES_PER_SAMPLE = 50
CHECKED_PIXELS = 1 << 22  # renders of fewer pixels skip the check (they fit anywhere)
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
LOG_T_MIN = math.log(T_MIN)


@dataclass(frozen=True)
class RasterSettings:
    near: float = 0.01
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Speed knobs; the defaults are the exact definition.
    dtype: torch.dtype | None = None  # per-sample arithmetic; None: the dtype of the colours
    truncation_sigma: float = 0.0  # 0: none; > 0: also cut at this many standard deviations
    band_pairs: int = 400_000  # candidate samples per row band: bounds memory, keeps tensors in cache
    depth_tolerance: float = 0.1  # relative depth difference that counts as inconsistent (visibility)


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # [H, W, 3]
    alpha: torch.Tensor  # [H, W] = 1 - final transmittance
    depth: torch.Tensor  # [H, W] expected depth of the visible samples (0 where alpha = 0); no gradient
    visibility: torch.Tensor | None  # [N] sum over pixels of T * alpha (no gradient)
    n_pairs: int  # samples composited
    contributions: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # pixel, gaussian, T*alpha
    # [N] with depth-consistent visibility: every sample's T * alpha, as visibility "all" gives it (no gradient)
    blend_weights: torch.Tensor | None = None


def _row_extents(my, cyy, r2, height):
    """Rows [y0, y1] whose pixel centres can lie inside power <= r2 (inclusive, clamped)."""
    half = torch.sqrt(r2 * cyy)
    y0 = torch.clamp(torch.ceil(my - half - 0.5), min=0)
    y1 = torch.clamp(torch.floor(my + half - 0.5), max=height - 1)
    return y0.long(), y1.long()


def _col_extents(mx, cxx, r2, width):
    half = torch.sqrt(r2 * cxx)
    x0 = torch.clamp(torch.ceil(mx - half - 0.5), min=0)
    x1 = torch.clamp(torch.floor(mx + half - 0.5), max=width - 1)
    return x0.long(), x1.long()


def _plan_bands(y0, y1, est_per_row, height, budget):
    """Row bands [r0, r1) whose estimated pair counts stay under ``budget`` (at least one row each)."""
    if y0.numel() == 0:
        return [(0, height)]
    diff = torch.zeros(height + 1, dtype=torch.float64, device=y0.device)
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


def _groups(counts):
    """For group sizes ``counts`` [G]: (owner [P], starts [G], P) with owner[p] the group of slot p.

    Like repeat_interleave(arange(G), counts), empty groups skipped, but several times faster on CPU:
    a slot's group is the number of group starts at or before it, minus one.
    """
    starts = torch.cumsum(counts, 0) - counts
    total = int(starts[-1] + counts[-1]) if counts.numel() else 0
    marks = torch.bincount(starts, minlength=total + 1)[:total]
    return torch.cumsum(marks, 0) - 1, starts, total


def _expand(counts):
    """For counts [E]: (owner [P], local offset [P]) with P = counts.sum()."""
    owner, starts, total = _groups(counts)
    local = torch.arange(total, device=counts.device) - _take(starts, owner)
    return owner, local


@dataclass
class _Fixed:
    """Per-Gaussian values the sample generation needs (no gradient), depth-sorted 1D columns."""

    mx: torch.Tensor
    my: torch.Tensor
    cxx: torch.Tensor
    cxy: torch.Tensor
    cyy: torch.Tensor
    conic_a: torch.Tensor
    log_opac: torch.Tensor
    r2: torch.Tensor
    y0: torch.Tensor
    y1: torch.Tensor
    depth: torch.Tensor


@dataclass
class _Entries:
    """One entry per (Gaussian, row) of a band, Gaussian-major (so in depth order)."""

    gauss: torch.Tensor  # [E] Gaussian index (depth rank), non-decreasing
    dy: torch.Tensor  # [E] float64 row centre minus the Gaussian's centre
    shift: torch.Tensor  # [E] float64 dx where the row's power is smallest: dx = u + shift
    span: torch.Tensor  # [E] candidate count (0: the row misses the ellipse)
    # In the per-sample dtype:
    u0: torch.Tensor  # [E] u of the first candidate
    row_min: torch.Tensor  # [E] dy^2 / cov_yy: the smallest power on the row
    log_peak: torch.Tensor  # [E] log(o) - row_min / 2: log of o G at the row's minimum
    half_a: torch.Tensor  # [E] conic_xx / 2
    pixel0: torch.Tensor  # [E] band pixel index of the first candidate


def _row_entries(fixed: _Fixed, in_band, r0, r1, width, dtype, settings) -> _Entries:
    """Per (Gaussian, row): the exact span of pixel centres with power <= r2 (or the tile span)."""
    rows_lo = torch.clamp(_take(fixed.y0, in_band), min=r0)
    n_rows = (torch.clamp(_take(fixed.y1, in_band), max=r1 - 1) - rows_lo + 1).clamp_min(0)
    local, offset = _expand(n_rows)
    gauss = _take(in_band, local)
    row = _take(rows_lo, local) + offset
    mx = _take(fixed.mx, gauss)
    dy = row.to(torch.float64) + 0.5 - _take(fixed.my, gauss)
    cyy = _take(fixed.cyy, gauss)
    a = _take(fixed.conic_a, gauss)
    shift = dy * _take(fixed.cxy, gauss) / cyy
    row_min = dy * dy / cyy  # the smallest power on this row
    centre = mx + shift  # where it is reached, in pixel coordinates
    r2 = _take(fixed.r2, gauss)
    rest = r2 - row_min
    half = torch.sqrt(torch.clamp_min(rest, 0.0) / a)
    xl = torch.clamp(torch.ceil(centre - half - 0.5), min=0).long()
    xr = torch.clamp(torch.floor(centre + half - 0.5), max=width - 1).long()
    xr = torch.where(rest >= 0, xr, xl - 1)
    return _Entries(
        gauss=gauss,
        dy=dy,
        shift=shift,
        span=(xr - xl + 1).clamp_min(0),
        u0=(xl.to(torch.float64) + 0.5 - centre).to(dtype),
        row_min=row_min.to(dtype),
        log_peak=(_take(fixed.log_opac, gauss) - 0.5 * row_min).to(dtype),
        half_a=(0.5 * a).to(dtype),
        pixel0=(row - r0) * width + xl,
    )


@dataclass
class _Samples:
    """The samples of one band that count, sorted by (pixel, depth): alpha >= 1/255, before T < 1e-4."""

    pixel: torch.Tensor  # [S] band pixel index
    entry: torch.Tensor  # [S] index into the band's entries
    gauss: torch.Tensor  # [S] Gaussian index
    u: torch.Tensor  # [S] x offset from the row's power minimum: dx = u + shift[entry]
    alpha: torch.Tensor  # [S] min(0.99, o G)
    log_t: torch.Tensor  # [S] log transmittance in front of the sample
    last: torch.Tensor  # [n_pix] index of each pixel's last sample (-1: none)
    log_final: torch.Tensor  # [n_pix] log transmittance behind all of a pixel's samples


def _at_last(values, last):
    """Per pixel: ``values`` at the pixel's last sample, 0 where it has none."""
    if values.numel() == 0:
        return torch.zeros(last.shape, dtype=values.dtype, device=values.device)
    return torch.where(last >= 0, _take(values, last.clamp_min(0)), 0.0)


def _band_samples(entries: _Entries, n_pix: int, dtype, settings) -> _Samples:
    """Expand the entries to samples, sort them by (pixel, depth), alpha-test them and end each pixel at T < 1e-4.

    Samples whose alpha rounds below 1/255 at the span's ends get alpha 0 and stay, inert (their weight
    and every gradient through them are 0), which spares a compaction.
    """
    owner, starts, total = _groups(entries.span)
    pixel = _take(entries.pixel0 - starts, owner) + torch.arange(total, device=starts.device)
    # Entries are Gaussian-major, so candidates arrive in depth order: a stable sort by pixel suffices.
    key = torch.int16 if n_pix <= 2**15 else torch.int32 if n_pix <= 2**31 else torch.int64
    pixel, order = torch.sort(pixel.to(key), stable=True)
    pixel, owner = pixel.long(), _take(owner, order)
    u = (pixel - _take(entries.pixel0, owner)).to(dtype).add_(_take(entries.u0, owner))
    power_half = _take(entries.half_a, owner).mul_(u).mul_(u)  # (power - row minimum) / 2
    raw = torch.exp_(_take(entries.log_peak, owner).sub_(power_half))  # o G before the 0.99 clamp
    if settings.truncation_sigma > 0:  # many candidates fail here
        keep = raw >= ALPHA_MIN
        keep &= 2.0 * power_half + _take(entries.row_min, owner) <= settings.truncation_sigma**2
        survivors = torch.nonzero(keep).squeeze(-1)
        pixel, owner, u, raw = (_take(t, survivors) for t in (pixel, owner, u, raw))
    else:
        raw = raw.masked_fill_(raw < ALPHA_MIN, 0.0)
    alpha = raw.clamp_max_(ALPHA_MAX)
    log1m = torch.neg(alpha).log1p_()
    counts = torch.bincount(pixel, minlength=n_pix)
    first = torch.cumsum(counts, 0) - counts
    after = torch.cumsum(log1m.to(torch.float64), 0)  # inclusive scan over the whole band
    before_pixel = _take(torch.cat([after.new_zeros(1), after]), first)  # scan value in front of each pixel
    log_after = after.sub_(_take(before_pixel, pixel))  # log T behind each sample, within its pixel
    include = log_after >= LOG_T_MIN  # a prefix of each pixel's samples
    n_kept = torch.zeros(n_pix, dtype=torch.int64, device=pixel.device).index_add_(0, pixel, include.long())
    kept_pixel, kept_first, n_total = _groups(n_kept)
    kept = _take(first - kept_first, kept_pixel) + torch.arange(n_total, device=pixel.device)
    log_t = (log_after - log1m).to(dtype)  # in front of the sample
    owner, u, alpha, log_t = (_take(t, kept) for t in (owner, u, alpha, log_t))
    has = n_kept > 0
    last = torch.where(has, kept_first + n_kept - 1, -1)
    log_final = _at_last(log_after, torch.where(has, first + n_kept - 1, -1))  # log_after is not compacted
    return _Samples(kept_pixel, owner, _take(entries.gauss, owner), u, alpha, log_t, last, log_final)


@dataclass
class _Plan:
    """What :class:`_Rasterize` needs besides the differentiable columns (no gradient flows through it)."""

    fixed: _Fixed
    bands: list[tuple[int, int]]
    width: int
    height: int
    dtype: torch.dtype
    settings: RasterSettings
    visibility: str | None
    keep_contributions: bool
    keep_samples: bool = True  # False: nothing needs the samples after compositing (no gradient, no extras)
    # Filled by the forward pass:
    n_pairs: int = 0
    visible: torch.Tensor | None = None  # [M] per depth-sorted Gaussian
    blend: torch.Tensor | None = None  # [M] every sample's weight, beside depth-consistent visibility
    contributions: list = field(default_factory=list)  # (image pixel, Gaussian rank, T * alpha) per band


class _Rasterize(torch.autograd.Function):
    """Front-to-back compositing of every band's kept samples, with the analytic backward in log space.

    Forward: C = sum_k T_k a_k c_k + T_final * background over each pixel's samples (T_k from the scan).
    Backward: dC/da_k = T_k c_k - (sum_{j>k} T_j a_j c_j + T_final bg) / (1 - a_k), safe since a <= 0.99.
    With power = a dx^2 + 2 b dx dy + c dy^2 and dL/dpower = -a_k/2 dL/da_k per sample, the mean and
    conic gradients need the sums of dL/dpower times 1, dx, dy, dx^2, dx dy, dy^2 per Gaussian; dy is
    fixed per entry and dx = u + shift, so per entry three moments in u suffice.

    Inputs are depth-sorted 1D columns: mx, my, conic a, b, c, opacity (float64) and r, g, b colours.
    """

    @staticmethod
    def forward(ctx, mx, my, ca, cb, cc, opac, red, green, blue, plan: _Plan):
        settings, dtype, width = plan.settings, plan.dtype, plan.width
        device = red.device
        n_img = plan.height * width
        cols = [c.detach().to(dtype) for c in (red, green, blue)]
        rgb = torch.zeros(3, n_img, dtype=dtype, device=device)
        log_final = torch.zeros(n_img, dtype=torch.float64, device=device)
        depth_sum = torch.zeros(n_img, dtype=dtype, device=device)
        depth = plan.fixed.depth.to(dtype)

        def band(_worker, rows):
            r0, r1 = rows
            n_pix, f = (r1 - r0) * width, plan.fixed
            in_band = torch.nonzero((f.y0 < r1) & (f.y1 >= r0)).squeeze(-1)
            entries = _row_entries(f, in_band, r0, r1, width, dtype, settings)
            s = _band_samples(entries, n_pix, dtype, settings)
            weight = torch.exp(s.log_t) * s.alpha
            for ch in range(3):  # bands own disjoint pixel ranges: workers never write the same element
                rgb[ch].narrow(0, r0 * width, n_pix).index_add_(0, s.pixel, weight * _take(cols[ch], s.gauss))
            log_final.narrow(0, r0 * width, n_pix).copy_(s.log_final)
            depth_sum.narrow(0, r0 * width, n_pix).index_add_(0, s.pixel, weight * _take(depth, s.gauss))
            if not plan.keep_samples:  # a plain render: free each band's samples as soon as it is composited
                return r0, n_pix, int(torch.count_nonzero(s.alpha)), None, None
            return r0, n_pix, entries, s, weight

        bands = in_workers(band, plan.bands, cpu_workers(device, len(plan.bands)))
        if plan.keep_samples:
            plan.n_pairs = sum(int(torch.count_nonzero(s.alpha)) for _, _, _, s, _ in bands)
        else:
            plan.n_pairs, bands = sum(count for _, _, count, _, _ in bands), []
        t_final = torch.exp(log_final).to(dtype)
        covered = -torch.expm1(log_final).to(dtype)  # the sum of each pixel's weights
        pix_depth = torch.where(covered > 0, depth_sum / torch.where(covered > 0, covered, 1.0), 0.0)
        if plan.visibility:
            plan.visible = torch.zeros(mx.numel(), dtype=dtype, device=device)
        if plan.visibility == "depth_consistent":
            plan.blend = torch.zeros(mx.numel(), dtype=dtype, device=device)
        for r0, _n_pix, _entries, s, weight in bands:
            if plan.visibility:
                used = slice(None)
                if plan.visibility == "depth_consistent":
                    plan.blend.index_add_(0, s.gauss, weight)
                    d_g, d_p = _take(depth, s.gauss), _take(pix_depth, s.pixel + r0 * width)
                    used = torch.nonzero((d_g - d_p).abs() <= settings.depth_tolerance * d_p).squeeze(-1)
                plan.visible.index_add_(0, s.gauss[used], weight[used])
            if plan.keep_contributions:
                real = torch.nonzero(weight > 0).squeeze(-1)
                plan.contributions.append(
                    (_take(s.pixel, real) + r0 * width, _take(s.gauss, real), _take(weight, real).float())
                )
        bg = torch.tensor(settings.background, dtype=dtype, device=device)
        rgb = torch.addcmul(rgb.t(), t_final[:, None], bg).contiguous()
        t_out = t_final.to(red.dtype)
        # Saved through save_for_backward: t_final may be the returned tensor, and an output kept as a
        # plain ctx attribute would form a cycle through its grad_fn that never gets freed.
        ctx.save_for_backward(ca, cb, cc, opac, t_final)
        ctx.bands, ctx.cols, ctx.plan = bands, cols, plan
        ctx.mark_non_differentiable(pix_depth)
        return rgb.to(red.dtype), t_out, pix_depth

    @staticmethod
    def backward(ctx, grad_rgb, grad_t, _grad_depth):
        ca, cb, cc, opac, t_final = ctx.saved_tensors
        plan, cols = ctx.plan, ctx.cols
        dtype, width = plan.dtype, plan.width
        device = grad_rgb.device
        f64 = torch.float64
        gr = grad_rgb.to(dtype).t().contiguous()  # [3, n_img]
        bg = torch.tensor(plan.settings.background, dtype=dtype, device=device)
        tail = bg @ gr
        if grad_t is not None:
            tail = tail + grad_t.to(dtype)
        tail = t_final * tail  # [n_img]: dL/dT_final times T_final
        n_g = ca.numel()
        workers = cpu_workers(device, len(ctx.bands))
        # Per worker: colour gradients [3, M] and sums of dL/dpower times 1, dx, dy, dx^2, dx dy, dy^2 [6, M].
        partial = [(torch.zeros(3, n_g, dtype=dtype, device=device), torch.zeros(6, n_g, dtype=f64, device=device))]
        partial += [(torch.zeros_like(partial[0][0]), torch.zeros_like(partial[0][1])) for _ in range(workers - 1)]

        def band(worker, item):
            r0, n_pix, e, s, weight = item
            grad_colors, sums = partial[worker]
            dot = None
            for ch in range(3):
                g_ch = _take(gr[ch].narrow(0, r0 * width, n_pix), s.pixel)
                grad_colors[ch].index_add_(0, s.gauss, weight * g_ch)
                term = g_ch * _take(cols[ch], s.gauss)
                dot = term if dot is None else dot.add_(term)
            scan = torch.cumsum((weight * dot).to(f64), 0)
            behind = (_take(_at_last(scan, s.last), s.pixel) - scan).to(dtype)  # sum_{j>k} T_j a_j (G . c_j)
            tail_s = _take(tail.narrow(0, r0 * width, n_pix), s.pixel)
            d_alpha = torch.exp(s.log_t) * dot - (behind + tail_s) / (1.0 - s.alpha)
            d_alpha = d_alpha.masked_fill_(s.alpha >= ALPHA_MAX, 0.0)  # clamped: no gradient
            d_power = -0.5 * s.alpha * d_alpha
            n_e = e.gauss.numel()
            m0, mu, muu = (
                torch.zeros(n_e, dtype=dtype, device=device).index_add_(0, s.entry, term).to(f64)
                for term in (d_power, d_power * s.u, d_power * s.u * s.u)
            )
            sx = mu + e.shift * m0  # sum of dL/dpower dx over the entry
            sxx = muu + e.shift * (2.0 * mu + e.shift * m0)  # ... dx^2
            for i, term in enumerate((m0, sx, e.dy * m0, sxx, e.dy * sx, e.dy * e.dy * m0)):
                sums[i].index_add_(0, e.gauss, term)

        in_workers(band, ctx.bands, workers)
        grad_colors, sums = partial[0]
        for more_colors, more_sums in partial[1:]:
            grad_colors += more_colors
            sums += more_sums
        p1, px, py, pxx, pxy, pyy = sums
        a, b, c = ca.detach(), cb.detach(), cc.detach()
        grad_mx = -2.0 * (a * px + b * py)
        grad_my = -2.0 * (b * px + c * py)
        grad_opac = -2.0 * p1 / opac.detach()  # d alpha / d o = alpha / o
        return grad_mx, grad_my, pxx, 2.0 * pxy, pyy, grad_opac, *grad_colors, None


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
    covariances: torch.Tensor | None = None,  # [N, 6] float64 splat_covariances: for many views of frozen geometry
) -> RenderOutput:
    """Render one view. Differentiable in means, quats, log_scales, opacity_logits and colors.

    Gaussians with any non-finite parameter are skipped (zero gradient). Outputs have the dtype of
    ``colors``; ``settings.dtype`` sets the per-sample arithmetic (default: that dtype too).
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
        means, quats, log_scales, w2c, camera.fx, camera.fy, camera.cx, camera.cy, width, height, settings.near, valid,
        covariances,
    )  # fmt: skip
    opac = torch.sigmoid(_take(opacity_logits, proj.index).to(torch.float64))
    with torch.no_grad():
        r2 = 2.0 * torch.log(255.0 * opac)  # alpha >= 1/255  <=>  power <= 2 ln(255 o)
        if settings.truncation_sigma > 0:
            r2 = torch.clamp_max(r2, settings.truncation_sigma**2)
        r2 = (r2 * (1.0 + 1e-9) + 1e-9).clamp_min(0.0)  # candidates only; the exact alpha test decides
        y0, y1 = _row_extents(proj.my, proj.cyy, r2, height)
        x0, x1 = _col_extents(proj.mx, proj.cxx, r2, width)
        alive = (r2 > 0) & (y0 <= y1) & (x0 <= x1)
        order = torch.nonzero(alive).squeeze(-1)
        order = _take(order, torch.sort(_take(proj.depth, order), stable=True).indices)
    g_index = _take(proj.index, order)  # [M] input indices, front to back
    geometry = [_take(t, order) for t in (proj.mx, proj.my, proj.conic_a, proj.conic_b, proj.conic_c, opac)]
    channels = [_take(colors[:, ch], g_index) for ch in range(3)]
    with torch.no_grad():
        mx, my, conic_a = (t.detach() for t in geometry[:3])
        cxx, cyy = _take(proj.cxx, order), _take(proj.cyy, order)
        fixed = _Fixed(
            mx, my, cxx, _take(proj.cxy, order), cyy, conic_a, torch.log(geometry[5].detach()),
            *(_take(t, order) for t in (r2, y0, y1, proj.depth)),
        )  # fmt: skip
        est = torch.clamp(2.0 * torch.sqrt(fixed.r2 * cxx) + 1.0, max=width)
        bands = _plan_bands(fixed.y0, fixed.y1, est, height, settings.band_pairs)
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (*geometry, *channels))
    keep_samples = needs_grad or bool(visibility) or keep_contributions
    if height * width >= CHECKED_PIXELS and device.type == "cpu":
        with torch.no_grad():
            samples = float((est * (fixed.y1 - fixed.y0 + 1).to(est.dtype)).sum())
        _check_memory(camera, samples if keep_samples else settings.band_pairs * cpu_workers(device, len(bands)))
    plan = _Plan(
        fixed, bands, width, height, settings.dtype or out_dtype, settings, visibility, keep_contributions, keep_samples
    )  # fmt: skip
    rgb, t_final, depth_img = _Rasterize.apply(*geometry, *channels, plan)
    vis_full = blend_full = None
    if visibility:
        vis_full = torch.zeros(n, dtype=out_dtype, device=device)
        vis_full[g_index] = plan.visible.to(out_dtype)
    if visibility == "depth_consistent":
        blend_full = torch.zeros(n, dtype=out_dtype, device=device)
        blend_full[g_index] = plan.blend.to(out_dtype)
    contributions = None
    if keep_contributions and plan.contributions:
        pixel, rank, weight = (torch.cat(parts) for parts in zip(*plan.contributions))
        contributions = (pixel, _take(g_index, rank), weight)
    return RenderOutput(
        rgb.reshape(height, width, 3),
        (1.0 - t_final).reshape(height, width),
        depth_img.reshape(height, width).to(out_dtype),
        vis_full,
        plan.n_pairs,
        contributions,
        blend_full,
    )


def _check_memory(camera: Camera, samples: float) -> None:
    """Raise CameraError, before allocating, when a render would need more memory than is available."""
    from ..util.errors import CameraError
    from ..util.machine import available_memory_bytes

    available = available_memory_bytes()
    needed = BYTES_PER_PIXEL * camera.height * camera.width + BYTES_PER_SAMPLE * samples
    if available is not None and needed > available:
        raise CameraError(
            f"rendering {camera.width}x{camera.height} ({camera.name or 'camera'}) needs about {needed / 1e9:.1f} GB "
            f"of memory and {available / 1e9:.1f} GB are available: render a smaller image"
        )


class _SparseColor(torch.autograd.Function):
    """rgb = W @ colors for a cached sparse W [P, N]; the backward is W^T @ grad."""

    @staticmethod
    def forward(ctx, colors, linear_map):
        ctx.linear_map = linear_map
        return torch.sparse.mm(linear_map.matrix, colors)

    @staticmethod
    def backward(ctx, grad):
        return ctx.linear_map.rmatvec(grad), None


def _index_dtype(*sizes: int) -> torch.dtype:
    # 32-bit indices where they fit: the products read every index, and half the bytes make them ~40% faster.
    return torch.int32 if max(sizes) < 2**31 - 1 else torch.int64


def _rows(crow: torch.Tensor) -> torch.Tensor:  # CSR row pointers [R + 1] -> each entry's row [nnz], their dtype
    counts = torch.diff(crow.long())
    return torch.repeat_interleave(torch.arange(counts.numel(), dtype=crow.dtype), counts, output_size=int(crow[-1]))


class SparseColorMap:
    """The linear map from colours to an image, W [P, N] (each entry a sample's T * alpha), held once as a CSR
    matrix sorted by pixel (int32 indices where they fit): ``matvec`` W c, ``rmatvec`` W^T y, ``column_energy``
    and ``squared_rmatvec`` for solvers. W^T, a second copy, is built on the first product that needs it: a map
    that only renders never holds it."""

    def __init__(self, crow: torch.Tensor, col: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]):
        self.shape = shape
        self.matrix = torch.sparse_csr_tensor(crow, col, values, shape, check_invariants=False)
        self._transposed: torch.Tensor | None = None

    @classmethod
    def from_samples(
        cls, pixel: torch.Tensor, column: torch.Tensor, weight: torch.Tensor, n_pix: int, n_columns: int
    ) -> SparseColorMap:
        """The map of samples (pixel, column, T * alpha) sorted by pixel."""
        index = _index_dtype(n_pix, n_columns, weight.numel())
        crow = torch.zeros(n_pix + 1, dtype=torch.long, device=pixel.device)
        crow[1:] = torch.cumsum(torch.bincount(pixel, minlength=n_pix), 0)
        return cls(crow.to(index), column.to(index), weight, (n_pix, n_columns))

    @property
    def nnz(self) -> int:
        return int(self.matrix.values().numel())

    @property
    def matrix_t(self) -> torch.Tensor:  # W^T [N, P] as CSR, each row's entries in pixel order
        if self._transposed is None:
            crow, col, values = self.matrix.crow_indices(), self.matrix.col_indices(), self.matrix.values()
            order = torch.sort(col, stable=True).indices
            crow_t = torch.zeros(self.shape[1] + 1, dtype=torch.long, device=col.device)
            crow_t[1:] = torch.cumsum(torch.bincount(col, minlength=self.shape[1]), 0)
            self._transposed = torch.sparse_csr_tensor(
                crow_t.to(col.dtype), _rows(crow)[order], values[order], self.shape[::-1], check_invariants=False
            )
        return self._transposed

    def samples(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """W's entries: (pixel, column) as int64 and T * alpha, sorted by pixel."""
        crow, col = self.matrix.crow_indices(), self.matrix.col_indices()
        return _rows(crow.long()), col.long(), self.matrix.values()

    def matvec(self, colors: torch.Tensor) -> torch.Tensor:  # [N, K] -> [P, K]
        return torch.sparse.mm(self.matrix, colors.contiguous())

    def rmatvec(self, pixels: torch.Tensor) -> torch.Tensor:  # [P, K] -> [N, K]
        return torch.sparse.mm(self.matrix_t, pixels.contiguous())

    def add_rmatvec(self, out: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:  # out [N, K] += W^T pixels
        """W^T y added into ``out`` in place: a solver's sum over views without a new [N, K] vector per view (a
        quarter of each product's time at 905k columns)."""
        return out.addmm_(self.matrix_t, pixels.contiguous())

    def column_energy(self) -> torch.Tensor:  # [N] float64: sum over pixels of W[p, i]^2
        values = self.matrix.values()
        energy = torch.zeros(self.shape[1], dtype=torch.float64, device=values.device)
        return energy.index_add_(0, self.matrix.col_indices(), values.double().square())

    def squared_rmatvec(self, pixels: torch.Tensor) -> torch.Tensor:  # [P, K] -> [N, K]: (W o W)^T y
        """Per Gaussian, sum over pixels of W[p, i]^2 y[p]: the diagonal of W^T diag(y) W (a preconditioner)."""
        matrix_t = self.matrix_t
        squared = self._with_values(matrix_t, matrix_t.values().square())
        return torch.sparse.mm(squared, pixels.contiguous())

    def only_columns(self, keep: torch.Tensor) -> SparseColorMap:  # keep: [N] bool
        """The map with every column but ``keep`` weighing 0: the image those Gaussians' colours draw, the others'
        samples left out (not skipped over: the transmittance each sample has stays as the full render's)."""
        matrix = self.matrix
        values = matrix.values() * keep[matrix.col_indices()].to(matrix.values().dtype)
        out = SparseColorMap(matrix.crow_indices(), matrix.col_indices(), values, self.shape)
        if self._transposed is not None:  # masked in place of sorted again
            rows_t = torch.repeat_interleave(keep, torch.diff(self._transposed.crow_indices().long()))
            out._transposed = self._with_values(self._transposed, self._transposed.values() * rows_t.to(values.dtype))
        return out

    def select(self, keep: torch.Tensor, columns: torch.Tensor | None = None, n_columns: int = 0) -> SparseColorMap:
        """The map of the samples ``keep`` ([nnz] bool) alone; with ``columns`` ([nnz], each sample's new column of
        ``n_columns``) renumbered."""
        crow, col = self.matrix.crow_indices(), self.matrix.col_indices()
        kept_before = torch.zeros(keep.numel() + 1, dtype=torch.long, device=keep.device)
        torch.cumsum(keep, 0, out=kept_before[1:])
        shape = self.shape if columns is None else (self.shape[0], n_columns)
        index = _index_dtype(*shape, keep.numel())
        col = col[keep] if columns is None else columns[keep]
        return SparseColorMap(kept_before[crow.long()].to(index), col.to(index), self.matrix.values()[keep], shape)

    @staticmethod
    def _with_values(matrix: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        return torch.sparse_csr_tensor(
            matrix.crow_indices(), matrix.col_indices(), values, matrix.shape, check_invariants=False
        )


class ColorOnlyRenderer:
    """Colour-only fast path for frozen geometry.

    With means, scales, rotations and opacities fixed, the image is linear in the colours:
    rgb = W c + T_final * background, where W [H*W, N] holds each sample's T * alpha. W is computed once
    per view (held once, as :class:`SparseColorMap`) and a colour step is a sparse multiply, forward and backward.
    """

    def __init__(
        self,
        means,
        quats,
        log_scales,
        opacity_logits,
        camera: Camera,
        settings: RasterSettings = RasterSettings(),
        output: RenderOutput | None = None,  # this camera's render with its contributions kept, if one was made
        covariances: torch.Tensor | None = None,  # as render() takes them
    ):
        n = means.shape[0]
        out = output
        if out is None or out.contributions is None:
            with torch.no_grad():
                dummy = torch.zeros(n, 3, dtype=torch.float32, device=means.device)
                out = render(means, quats, log_scales, opacity_logits, dummy, camera, settings, None, True, covariances)
        self.camera = camera
        self.shape = (camera.height, camera.width)
        empty = torch.zeros(0, dtype=torch.long, device=means.device)
        # Contributions arrive sorted by pixel (bands in order, pixels sorted within each band): CSR rows.
        pixel, gauss, weight = out.contributions or (empty, empty, empty.float())
        bg = torch.tensor(settings.background, dtype=torch.float32, device=means.device)
        self.background = (1.0 - out.alpha.reshape(-1, 1).float()) * bg  # [H*W, 3]
        self.alpha = out.alpha.float()
        self.depth = out.depth.float()
        self.n_pairs = out.n_pairs
        # Gaussians this view sees at all: the colour step can leave out the rest.
        self.seen = torch.zeros(n, dtype=torch.bool, device=means.device)
        self.seen[gauss] = True
        self.map = SparseColorMap.from_samples(pixel, gauss, weight, self.shape[0] * self.shape[1], n)

    def restrict(self, keep: torch.Tensor, fixed_colors: torch.Tensor | None = None) -> ColorOnlyRenderer:
        """Use only the Gaussians ``keep`` (sorted indices): colours become [len(keep), 3]. Without
        ``fixed_colors`` ``keep`` must hold every Gaussian the view sees; with them ([N, 3], every Gaussian's
        colour), the samples of the others are drawn in those colours into the constant background term."""
        column = torch.full((self.seen.numel(),), -1, dtype=torch.long, device=keep.device)
        column[keep] = torch.arange(keep.numel(), device=keep.device)
        gauss = self.map.matrix.col_indices()
        columns = column[gauss]
        kept = columns >= 0
        if not bool(kept.all()):
            if fixed_colors is None:
                raise ValueError("restrict: every Gaussian the view sees must be kept")
            dropped = ~kept
            pixel = _rows(self.map.matrix.crow_indices().long())[dropped]
            contribution = self.map.matrix.values()[dropped, None] * fixed_colors[gauss[dropped]].float()
            self.background = self.background.index_add(0, pixel, contribution)
        self.map = self.map.select(kept, columns, keep.numel())
        self.seen = self.seen[keep]
        return self

    def merge_columns(self, column: torch.Tensor, count: int) -> ColorOnlyRenderer:
        """Columns shared: Gaussian i (a current column) becomes column ``column[i]`` of ``count``, its samples of one
        pixel summed with those of the others there. The image of colours c is then exactly that of the Gaussians
        each painted c[column[i]]; the samples stay sorted by pixel."""
        pixel, gauss, weight = self.map.samples()
        gauss = column[gauss]
        # Only samples of shared columns can meet another of their column at a pixel: the key sort runs on those
        # alone (a few % of the samples on the bonsai), each one's duplicates summed into its first sample.
        members = torch.bincount(column, minlength=count)
        shared = torch.nonzero(members[gauss] > 1).squeeze(-1)
        keys, inverse = torch.unique(pixel[shared] * count + gauss[shared], return_inverse=True)
        n_keys, device = keys.numel(), gauss.device
        first = torch.full((n_keys,), shared.numel(), dtype=torch.long, device=device)
        first = shared[first.scatter_reduce_(0, inverse, torch.arange(shared.numel(), device=device), "amin")]
        weight = weight.clone()
        weight[first] = torch.zeros(n_keys, dtype=weight.dtype, device=device).index_add_(0, inverse, weight[shared])
        keep = torch.ones(gauss.numel(), dtype=torch.bool, device=device)
        keep[shared] = False
        keep[first] = True
        keep = torch.nonzero(keep).squeeze(-1)  # one nonzero for the three gathers below
        self.seen = torch.zeros(count, dtype=torch.bool, device=device)
        self.seen[gauss] = True
        pixel, gauss, weight = pixel.index_select(0, keep), gauss.index_select(0, keep), weight.index_select(0, keep)
        self.map = SparseColorMap.from_samples(pixel, gauss, weight, self.map.shape[0], count)
        return self

    def contributions(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """W's entries: (pixel, column, T * alpha) of every sample, sorted by pixel (derived from the map)."""
        return self.map.samples()

    def linear_map(self, min_weight: float = 0.0) -> SparseColorMap:
        """W itself, or W without the samples whose T * alpha is below ``min_weight`` (deep, faint samples: on the
        bonsai the 39% of samples under 1e-3 carry 0.5% of the weight), for solvers that apply it many times."""
        if min_weight <= 0.0:
            return self.map
        return self.map.select(self.map.matrix.values() >= min_weight)

    def __call__(self, colors: torch.Tensor) -> torch.Tensor:  # [N, 3] -> [H, W, 3]
        rgb = _SparseColor.apply(colors.float(), self.map) + self.background
        return rgb.reshape(*self.shape, 3)


def geometry_tensors(scene) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A GaussianScene's means [N, 3], quats [N, 4], log-scales [N, 3] and opacity logits [N] as float32 tensors."""

    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return t(scene.means), t(scene.quats), t(scene.log_scales), t(scene.opacity_logits)


def render_scene(
    scene,
    camera: Camera,
    settings: RasterSettings = RasterSettings(),
    visibility=None,
    device="cpu",
    covariances: torch.Tensor | None = None,  # scene_covariances(scene), when rendering many views of it
) -> RenderOutput:
    """Render a :class:`~dresg_addon.scene.gaussians.GaussianScene` (numpy) without gradients, in float32 output."""
    from .sh import colors_from_sh

    def t(a):
        return torch.from_numpy(a).to(device)

    means = t(scene.means)
    center = torch.as_tensor(camera.center, dtype=torch.float32, device=device)
    with torch.no_grad():
        sh_rest = None if scene.sh_rest is None else t(scene.sh_rest)
        colors = colors_from_sh(t(scene.sh_dc), sh_rest, means, center)
        return render(
            means, t(scene.quats), t(scene.log_scales), t(scene.opacity_logits), colors, camera, settings, visibility,
            covariances=covariances,
        )  # fmt: skip


def scene_covariances(scene, device="cpu") -> torch.Tensor:  # -> [N, 6] float64
    """The splats' world covariances, made once for a scene rendered from many views (:func:`render_scene`)."""
    return splat_covariances(torch.from_numpy(scene.quats), torch.from_numpy(scene.log_scales), torch.float64).to(
        device
    )
