"""Splats as fine as the marks, only where the views need them: a render-preserving split before stylizing.

A splat wider on screen than the painting's strokes shows one colour over its whole footprint, so no colour fit
can draw a mark on it. :func:`split_wide_splats` replaces each such splat by a grid of narrower children that
render (almost) as the parent did, so that stylizing can colour them apart.

Which splats. Each view's blend weight per splat (the sum over its pixels of T alpha, the ``visibility`` a render
gives) says how much that view sees it. A splat's screen sigma along each of its axes (the standard deviation of
its projected Gaussian along the projected axis, pixels at the fit size) is the blend-weighted RMS over the views:
the views that see it most decide. It is split when its longest axis is wider than the stroke scale, and only when
some view draws it strongly: its blend weight there over its footprint's area 2 pi sqrt(det Sigma_2D) (the mean
weight it has on the pixels it covers; its opacity for a splat nothing hides) is at least ``MIN_DRAWN``. Faint
veils and floaters, and what lies hidden behind the surface, stay as they are.

How. Along its two longest axes (in the views' measure) a splat becomes an odd k1 x k2 grid of children in its
own plane; its third axis, rotation and colours (SH, normals, extras) are the children's. Per axis with k > 1 the
grid spacing h and the child sigma c = 0.8 h are such that the equal mixture keeps the parent's variance,
c^2 + h^2 (k^2 - 1) / 12 = sigma^2 (child sigma 0.70, 0.49, 0.37, 0.30 of the parent's at k = 3, 5, 7, 9), so
the mean and the covariance are kept. Alpha compositing is not additive, so the children's opacities are not
the mixture's weights: they are solved so that the children's composited coverage 1 - prod(1 - a_c g_c) matches
the parent's o g (both cut at 1/255 and clamped at 0.99 as the rasterizer does) on the parent's normalised
plane, where every parent of the same opacity and grid looks the same. The solve is a multiplicative fixed point
on the optical depths (each child's peak scaled by the ratio of the parent's to the children's depth under its
footprint), tabulated over opacity per grid. Measured in that plane, the largest coverage error is 0.026
(3 x 3), 0.06 (5 x 5), 0.07 (7 x 7), 0.08 (9 x 9) at opacity 0.99 and below 0.03 under opacity 0.5; an
equal-weight grid with the opacities of the mixture weights (or their optical-depth version) is off by 0.3-0.7
at high opacity, and an even grid (no child at the centre) by about twice as much as the odd one next to it.

Per axis k is the smallest odd count whose child sigma is at most the stroke scale, up to ``MAX_PER_AXIS``, and
no more than keeps the children as wide on screen as the splat's unsplit thickness (its third axis, with the
0.3 px^2 low-pass) in every view that draws it at least ``STRONG_VIEW`` as much as its best view: children finer
than that pile onto each other where a view sees them edge-on and composite more opaque than the parent (a splat
some such view sees edge-on is left whole). Splats wider than ``MAX_PER_AXIS`` allows keep children wider than a
mark. Both are counted in the summary. The splats split are taken in the order of the views' blend weight on them
(what the images show most first) while the count added stays under the cap.

What the render keeps (``bench/refine.py``: 16 orbit views at 448x320, 16 novel views between them, stroke sigma 4.5
px). The bonsai: 1,185 splats split into 8,529 (+2.7%); RMSE over the covered pixels 0.0033 on the fit and on the
novel views (0.0057 in the worst view), no pixel off by more than 0.092, 0.006% of them by more than 0.05. The demo
scene: nothing split (its splats are about 1 px in these views); with a stroke sigma of 0.9 px, +35% (the cap) at
RMSE 0.0041, at most 0.110. Rendered alone, the bonsai's split splats change about twice as much: the rest of the
scene hides part of it. What is left is not in the plane: children sort by their own centres' depth, so on a tilted
surface some pass behind a neighbour their parent was in front of (on Luigi, large splats on a small high-contrast
object, +25%, RMSE 0.020, single pixels up to 0.7). Against the opacities of an equal mixture, on 4 fit and 4 novel
bonsai views (an earlier, wider choice of 2,071 splats): fitted 0.0045 / 0.0054 RMSE (fit / novel), the mixture's
weights as opacities 0.0053 / 0.0062, as optical depths 0.0069 / 0.0080 (pixels up to 0.19 off); a child sigma of
0.6 h or 1.0 h instead of 0.8 h within 0.0003 of it.

Output order: the input splats in their order, each split splat's slot holding its centre child, then the other
children, parent by parent. ``parent_index[i]`` is the input splat output splat i comes from (i itself for the
first ``len(scene)``), so colours, selections, vertex groups and a Restore carry over by indexing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cache

import numpy as np
import torch

from ..raster import RasterSettings, geometry_tensors, render, scene_covariances
from ..raster.projection import FRUSTUM_GUARD, LOW_PASS, _rotation_columns
from ..scene.camera import Camera
from ..scene.gaussians import GaussianScene
from ..util.errors import ConfigError

CHILD_RATIO = 0.8  # child sigma / grid spacing: smaller ripples the coverage, larger widens the children
MAX_PER_AXIS = 9  # children per axis at most (81 per splat)
MIN_DRAWN = 0.1  # a splat whose best view draws it with less weight than this per pixel of its footprint stays
STRONG_VIEW = 0.5  # views drawing a splat at least this share of its best view's weight hold its children's width
ALPHA_MIN, ALPHA_MAX = 1.0 / 255.0, 0.99  # the rasterizer's alpha test and clamp
# The opacity table: logits -5 to 7 (a splat fainter than o = 0.007 is never drawn enough to be split), on a 33 x 33
# plane: its largest coverage errors are within 0.001 of a table at half the step on 49 x 49 points (5x the time).
_TABLE_LOGITS = np.linspace(-5.0, 7.0, 13)
_PLANE_EXTENT, _PLANE_POINTS, _SOLVE_ITERATIONS = 4.0, 33, 40


@dataclass
class SplitResult:
    scene: GaussianScene  # the split scene
    parent_index: np.ndarray  # [M] int64: the input splat each output splat comes from (i for i < len(input))
    summary: str  # e.g. "split 412 wide splats into 18,300"
    split: int  # splats split
    added: int  # splats added (M - len(input))
    still_wide: int  # wide splats left wider than the marks: children held wide, or left whole (edge-on, the cap)


def split_wide_splats(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    stroke_sigma: float,
    max_added: int,
    settings: RasterSettings | None = None,
    only: np.ndarray | None = None,  # [N] bool: the splats that may be split (a selection); None: any
    blend_weights: Sequence[torch.Tensor] | None = None,  # per camera [N], when its render was made (screen_axes)
) -> SplitResult:
    """Split the splats the ``cameras`` see wider than ``stroke_sigma`` into children at most that wide (render
    kept; see the module notes).

    ``stroke_sigma``: the marks' scale in pixels of the cameras' images (the fit size); for the synth backend
    ``backends.synth_stroke_sigma(stroke_size)`` times the fit size over the proposal size. ``max_added``: at most
    this many splats are added. ``settings``: the renders that measure the views (default ``RasterSettings()``). A
    scene with nothing wider than the marks comes back unchanged (the same object)."""
    number = isinstance(stroke_sigma, int | float | np.floating) and not isinstance(stroke_sigma, bool)
    if not (number and math.isfinite(stroke_sigma) and stroke_sigma > 0):
        raise ConfigError(f"the stroke scale {stroke_sigma!r} must be a positive number of pixels")
    if isinstance(max_added, bool) or not isinstance(max_added, int | np.integer) or max_added < 0:
        raise ConfigError(f"the cap on splats added {max_added!r} must be a whole number >= 0")
    if not cameras:
        raise ConfigError("splitting wide splats needs at least one camera")
    n = len(scene)
    axes_px, view_weights, drawn = screen_axes(scene, cameras, settings, blend_weights)  # [N, 3], [V, N], [N]
    weight = view_weights.sum(0, dtype=np.float64)
    order = np.argsort(-axes_px, axis=1, kind="stable")  # axes, longest first
    long_axes = order[:, :2]
    lengths = np.take_along_axis(axes_px, long_axes, 1)  # [N, 2]
    candidates = (lengths[:, 0] > stroke_sigma) & (drawn >= MIN_DRAWN) & ~scene.invalid_mask()
    candidates &= (np.abs(scene.means).max(1) < 1e30) & (scene.log_scales.max(1) < 60.0)  # children stay finite
    if only is not None:
        candidates &= np.asarray(only, bool)
    counts = np.stack([_per_axis(lengths[:, 0], stroke_sigma), _per_axis(lengths[:, 1], stroke_sigma)], 1)
    wide = np.nonzero(candidates)[0]
    floor = _thickness(scene, cameras, view_weights, wide, order[wide])  # [W, 2]
    for axis in range(2):
        counts[wide, axis] = np.minimum(counts[wide, axis], _at_most(floor[:, axis]))
    edge_on = int(np.sum(counts[wide, 0] * counts[wide, 1] == 1))
    wide = wide[counts[wide, 0] * counts[wide, 1] > 1]
    wide = wide[np.argsort(-weight[wide], kind="stable")]  # what the views show most first
    chosen, budget = [], int(max_added)
    for i in wide:
        extra = int(counts[i, 0] * counts[i, 1]) - 1
        if extra <= budget:
            chosen.append(i)
            budget -= extra
    chosen = np.asarray(chosen, dtype=np.int64)
    left_out = len(wide) - len(chosen)
    limited = int(np.sum(np.max(lengths[chosen] * _ratio(counts[chosen]), 1) > stroke_sigma))
    notes = []
    if limited:
        notes.append(f"{limited:,} of them still wider than the marks")
    if edge_on:
        notes.append(f"{edge_on:,} left whole, seen nearly edge-on")
    if left_out:
        notes.append(f"{left_out:,} left whole by the cap of {max_added:,} added")
    notes = " (" + "; ".join(notes) + ")" if notes else ""
    if len(chosen) == 0:
        summary = "no splat is wider than the marks" if not (edge_on or left_out) else "no splat split" + notes
        return SplitResult(scene, np.arange(n, dtype=np.int64), summary, 0, 0, edge_on + left_out)
    out = _assemble(scene, chosen, _children(scene, chosen, long_axes[chosen], counts[chosen]))
    parent_index = np.concatenate([np.arange(n), np.repeat(chosen, counts[chosen, 0] * counts[chosen, 1] - 1)])
    summary = f"split {len(chosen):,} wide splats into {len(parent_index) - n + len(chosen):,}" + notes
    still_wide = limited + edge_on + left_out
    return SplitResult(out, parent_index, summary, len(chosen), len(parent_index) - n, still_wide)


def screen_axes(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    settings: RasterSettings | None = None,
    blend_weights: Sequence[torch.Tensor] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per splat: [N, 3] its screen sigma along each of its three axes (pixels), the blend-weighted RMS over the
    views that draw it; [V, N] float32 its blend weight in each view; [N] the largest over the views of its blend
    weight over its footprint's area 2 pi sqrt(det Sigma_2D) (about its opacity where nothing hides it, less
    where something in front does). Zeros for the splats no view draws. ``blend_weights``: each camera's [N] blend
    weights (every sample's T alpha) when a render made them already (the view selection's); else each camera is
    rendered."""
    settings = settings or RasterSettings()
    means, quats, log_scales, logits = geometry_tensors(scene)
    n = len(scene)
    if blend_weights is not None and len(blend_weights) != len(cameras):
        raise ValueError(f"screen_axes: {len(blend_weights)} views' blend weights for {len(cameras)} cameras")
    sum_w = torch.zeros(n, dtype=torch.float64)
    view_weights = torch.zeros(len(cameras), n)
    sum_sq = torch.zeros(n, 3, dtype=torch.float64)
    drawn = torch.zeros(n, dtype=torch.float64)
    covariances = scene_covariances(scene) if blend_weights is None else None  # made once for all the views
    for v, camera in enumerate(cameras):
        if blend_weights is None:
            with torch.no_grad():
                zeros = torch.zeros_like(means)
                visibility = render(
                    means, quats, log_scales, logits, zeros, camera, settings, "all", covariances=covariances
                ).visibility
        else:
            visibility = blend_weights[v].reshape(n)
        view_weights[v] = visibility.float()
        index = torch.nonzero(visibility > 0).squeeze(-1)
        w = visibility[index].double()
        columns = _screen_columns(means[index], quats[index], log_scales[index], camera)  # [M, 3, 2]
        sq = columns.square().sum(-1)  # [M, 3]
        cov = torch.einsum("mia,mib->mab", columns, columns) + LOW_PASS * torch.eye(2, dtype=torch.float64)
        det = (cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2).clamp_min(1e-300)
        area = 2.0 * math.pi * det.sqrt()
        sum_w.index_add_(0, index, w)
        sum_sq.index_add_(0, index, w[:, None] * sq)
        drawn[index] = torch.maximum(drawn[index], w / area)  # a view draws each splat once
    axes = torch.where(sum_w[:, None] > 0, sum_sq / sum_w.clamp_min(1e-300)[:, None], 0.0).sqrt()
    axes = torch.nan_to_num(axes, nan=0.0, posinf=0.0)  # a splat whose screen size overflows is not split
    return axes.numpy(), view_weights.numpy(), torch.nan_to_num(drawn, nan=0.0, posinf=0.0).numpy()


def _thickness(scene, cameras, view_weights, index, axis_order) -> np.ndarray:  # -> [M, 2]
    """Per splat ``index`` and long axis: the largest, over the views that draw it at least STRONG_VIEW as much as its
    best view, of its unsplit thickness on screen (third axis, low-pass included) over that axis's screen sigma."""
    means, quats, log_scales, _ = (t[torch.from_numpy(index)] for t in geometry_tensors(scene))
    weights = view_weights[:, index]
    strong = weights >= STRONG_VIEW * weights.max(0, keepdims=True)
    out = np.zeros((len(index), 2))
    rows = np.arange(len(index))
    for v, camera in enumerate(cameras):
        sq = _screen_columns(means, quats, log_scales, camera).square().sum(-1).numpy()  # [M, 3]
        thick = np.sqrt(sq[rows, axis_order[:, 2]] + LOW_PASS)
        for axis in range(2):
            ratio = thick / np.sqrt(sq[rows, axis_order[:, axis]]).clip(1e-30)
            out[:, axis] = np.where(strong[v], np.maximum(out[:, axis], ratio), out[:, axis])
    return out


def _at_most(floor: np.ndarray) -> np.ndarray:
    """The largest odd k (at least 1) whose child sigma ratio is at least ``floor``."""
    count = np.ones(floor.shape, dtype=np.int64)
    for k in range(3, MAX_PER_AXIS + 1, 2):
        count = np.where(_ratio(k) >= floor, k, count)
    return count


def _screen_columns(means, quats, log_scales, camera: Camera) -> torch.Tensor:  # -> [M, 3, 2] float64
    """J W R S's columns: each axis's sigma vector on screen (pixels), with the rasterizer's clamped Jacobian."""
    w2c = torch.as_tensor(camera.world_to_camera, dtype=torch.float64)
    rot = w2c[:3, :3]
    cam = means.double() @ rot.T + w2c[:3, 3]
    inv_z = 1.0 / cam[:, 2]
    lim_x = FRUSTUM_GUARD * camera.width / (2.0 * camera.fx)
    lim_y = FRUSTUM_GUARD * camera.height / (2.0 * camera.fy)
    u = (cam[:, 0] * inv_z).clamp(-lim_x, lim_x)
    v = (cam[:, 1] * inv_z).clamp(-lim_y, lim_y)
    # Jacobian rows fx/z (r0 - u r2) and fy/z (r1 - v r2), r_i the camera rotation's rows.
    row_x = (camera.fx * inv_z)[:, None] * (rot[0][None] - u[:, None] * rot[2][None])
    row_y = (camera.fy * inv_z)[:, None] * (rot[1][None] - v[:, None] * rot[2][None])
    axes = _axes_world(quats, log_scales)  # [M, 3 axes, 3]
    return torch.stack([(axes * row_x[:, None]).sum(-1), (axes * row_y[:, None]).sum(-1)], -1)


def _axes_world(quats, log_scales) -> torch.Tensor:  # -> [M, 3, 3]: axis i's world vector times its scale
    q = quats.double()
    q = (q / q.norm(dim=-1, keepdim=True).clamp_min(1e-300)).unbind(-1)
    r = torch.stack(_rotation_columns(q), -1).reshape(-1, 3, 3)  # [M, row, column]
    return r.transpose(1, 2) * torch.exp(log_scales.double())[:, :, None]


def _ratio(k) -> np.ndarray:
    """Child sigma over parent sigma along an axis split into k (1 for k = 1)."""
    k = np.asarray(k, dtype=np.float64)
    return np.where(k > 1, CHILD_RATIO / np.sqrt(CHILD_RATIO**2 + (k * k - 1.0) / 12.0), 1.0)


def _per_axis(length: np.ndarray, stroke_sigma: float) -> np.ndarray:  # [N] -> [N] odd counts
    """The smallest odd k (up to MAX_PER_AXIS) whose children are at most ``stroke_sigma`` wide."""
    count = np.ones(length.shape, dtype=np.int64)
    for k in range(MAX_PER_AXIS, 1, -2):
        count = np.where(length * _ratio(k) <= stroke_sigma, k, count)
    return np.where(
        length <= stroke_sigma, 1, np.where(length * _ratio(MAX_PER_AXIS) > stroke_sigma, MAX_PER_AXIS, count)
    )


def _grid(k: int) -> tuple[np.ndarray, float]:
    """Child offsets (in parent sigmas) and child sigma along an axis split into k."""
    if k == 1:
        return np.zeros(1), 1.0
    spacing = 1.0 / math.sqrt(CHILD_RATIO**2 + (k * k - 1) / 12.0)
    return (np.arange(k) - (k - 1) / 2.0) * spacing, CHILD_RATIO * spacing


@cache
def _opacity_table(k1: int, k2: int) -> np.ndarray:  # -> [len(_TABLE_LOGITS), k1 k2] child logits
    """The children's opacities (as logits) for a parent of each table opacity split into k1 x k2: the composited
    coverage of the children matched to the parent's on the parent's normalised plane (module notes)."""
    pos1, c1 = _grid(k1)
    pos2, c2 = _grid(k2)
    line = torch.linspace(-_PLANE_EXTENT, _PLANE_EXTENT, _PLANE_POINTS, dtype=torch.float64)
    x, y = (t.reshape(-1) for t in torch.meshgrid(line, line, indexing="ij"))
    mx, my = (torch.from_numpy(t.reshape(-1)) for t in np.meshgrid(pos1, pos2, indexing="ij"))
    shape = torch.exp(-0.5 * ((x[None] - mx[:, None]) ** 2 / c1**2 + (y[None] - my[:, None]) ** 2 / c2**2))  # [K, P]
    o = torch.sigmoid(torch.from_numpy(_TABLE_LOGITS))[:, None]  # [B, 1]
    parent = (o * torch.exp(-0.5 * (x * x + y * y))[None]).clamp_max(ALPHA_MAX)
    parent = torch.where(parent >= ALPHA_MIN, parent, 0.0)
    wanted = -torch.log1p(-parent) @ shape.T  # [B, K]: the parent's optical depth under each child
    # Start: the mixture's weights as optical depths (the exact answer for faint parents).
    weights = torch.exp(-0.5 * (mx**2 + my**2))
    depth = (weights / weights.sum() / (c1 * c2))[None] * -torch.log1p(-o)
    a = (-torch.expm1(-depth)).clamp(1e-8, ALPHA_MAX)
    for _ in range(_SOLVE_ITERATIONS):
        have = -torch.log1p(-(a[:, :, None] * shape[None]).clamp_max(ALPHA_MAX)).sum(1) @ shape.T
        a = (a * wanted / have.clamp_min(1e-300)).clamp(1e-8, ALPHA_MAX)
    return torch.logit(a).numpy()


def _child_logits(k1: int, k2: int, logits: np.ndarray) -> np.ndarray:  # [B] -> [B, k1 k2]
    """The table's child logits, linearly interpolated at the parents' logits (clamped to the table's range)."""
    table = _opacity_table(k1, k2)
    at = np.clip((logits.astype(np.float64) - _TABLE_LOGITS[0]) / (_TABLE_LOGITS[1] - _TABLE_LOGITS[0]), 0, None)
    low = np.minimum(at.astype(np.int64), len(_TABLE_LOGITS) - 2)
    frac = np.clip(at - low, 0.0, 1.0)[:, None]
    return (1.0 - frac) * table[low] + frac * table[low + 1]


def _children(scene: GaussianScene, chosen: np.ndarray, long_axes: np.ndarray, counts: np.ndarray) -> dict:
    """Per chosen splat, its children's ``means`` [K, 3], ``log_scales`` [K, 3] and ``logits`` [K], its centre child
    first."""
    means = scene.means[chosen].astype(np.float64)
    log_scales = scene.log_scales[chosen].astype(np.float64)
    axes = _axes_world(torch.from_numpy(scene.quats[chosen]), torch.zeros(len(chosen), 3)).numpy()  # unit axes
    scales = np.exp(log_scales)
    per_parent = [None] * len(chosen)
    for k1, k2 in sorted({(int(a), int(b)) for a, b in counts}):
        group = np.nonzero((counts[:, 0] == k1) & (counts[:, 1] == k2))[0]
        pos1, c1 = _grid(k1)
        pos2, c2 = _grid(k2)
        u, v = (t.reshape(-1) for t in np.meshgrid(pos1, pos2, indexing="ij"))  # [K], centre at (K - 1) / 2
        a_axis, b_axis = long_axes[group, 0], long_axes[group, 1]
        rows = np.arange(len(group))
        along_a = axes[group, a_axis] * scales[group, a_axis][:, None]  # [G, 3]
        along_b = axes[group, b_axis] * scales[group, b_axis][:, None]
        child_means = means[group, None] + u[None, :, None] * along_a[:, None] + v[None, :, None] * along_b[:, None]
        child_scales = np.repeat(log_scales[group, None], len(u), 1)  # [G, K, 3]
        child_scales[rows, :, a_axis] += math.log(c1)
        child_scales[rows, :, b_axis] += math.log(c2)
        child_logits = _child_logits(k1, k2, scene.opacity_logits[chosen[group]])
        centre = (len(u) - 1) // 2
        reorder = np.r_[centre, np.delete(np.arange(len(u)), centre)]
        for g, slot in enumerate(group):
            per_parent[slot] = (child_means[g, reorder], child_scales[g, reorder], child_logits[g, reorder])
    return {
        "means": [p[0] for p in per_parent],
        "log_scales": [p[1] for p in per_parent],
        "logits": [p[2] for p in per_parent],
    }


def _assemble(scene: GaussianScene, chosen: np.ndarray, new: dict) -> GaussianScene:
    """The input with each chosen splat's slot holding its centre child, then the other children in order."""
    rest_of = [len(m) - 1 for m in new["means"]]
    repeat = np.repeat(chosen, rest_of)  # the parent of each appended child

    def column(values: np.ndarray, centre: np.ndarray, rest: np.ndarray) -> np.ndarray:
        out = values.copy()
        out[chosen] = centre.astype(values.dtype)
        return np.concatenate([out, rest.astype(values.dtype)])

    def carried(values: np.ndarray | None) -> np.ndarray | None:
        return None if values is None else np.concatenate([values, values[repeat]])

    means = column(scene.means, np.stack([m[0] for m in new["means"]]), np.concatenate([m[1:] for m in new["means"]]))
    log_scales = column(
        scene.log_scales,
        np.stack([s[0] for s in new["log_scales"]]),
        np.concatenate([s[1:] for s in new["log_scales"]]),
    )
    logits = column(
        scene.opacity_logits, np.array([g[0] for g in new["logits"]]), np.concatenate([g[1:] for g in new["logits"]])
    )
    return replace(
        scene,
        means=means,
        log_scales=log_scales,
        quats=carried(scene.quats),
        opacity_logits=logits,
        sh_dc=carried(scene.sh_dc),
        sh_rest=carried(scene.sh_rest),
        normals=carried(scene.normals),
        extras={name: np.concatenate([values, values[repeat]]) for name, values in scene.extras.items()},
    )
