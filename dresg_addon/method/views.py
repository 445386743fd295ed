"""Active-view selection by capped Gaussian coverage (Sec. 4.3).

On a scene, :func:`select_active_views` renders each camera once for :func:`visibility_matrix` and runs
the selection below on it (the Select Views operator and the CLI call it too, with a config).

Input: the visibility matrix w [V, N], w_{v,i} = how strongly Gaussian i is visibly observed in
candidate view v (projected alpha x opacity, depth-consistent samples only; the rasterizer computes
it). Dense numpy / torch arrays and torch sparse (COO or CSR) tensors are accepted; entries <= 0 mean
"not seen".

The greedy maximisation of the capped coverage (a facility-location function, hence monotone and
submodular) is run lazily: a view's gain from an earlier, smaller set bounds its current gain, so
only views whose bound reaches the top are re-evaluated. The picks are exactly those of the plain
greedy loop (``select_views_reference``), ties going to the lowest view index.

Equation numbers follow the order of the equations in ``paper/DReSG.tex``; each citation also names
the LaTeX label.
"""

from __future__ import annotations

import heapq
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from ..raster import ColorOnlyRenderer, RasterSettings, geometry_tensors, render
from ..raster.projection import splat_covariances
from ..scene.camera import Camera
from ..scene.gaussians import GaussianScene
from ..util.errors import CameraError, CancelledError, ConfigError, NumericalError

COVERAGE_REACHED = "coverage reached"
GAIN_BELOW_THRESHOLD = "gain below threshold"
ALL_VIEWS_USED = "all views used"
VIEW_LIMIT_REACHED = "view limit reached"


@dataclass(frozen=True)
class ViewSelectionSettings:
    min_support: float = 1e-4  # w_min
    target_fraction: float = 0.98  # rho
    coverage_stop: float = 0.9999  # stop once sum_i c_i / |T| reaches this
    min_gain: float = 0.001  # stop when the best marginal gain / |T| falls below this
    max_views: int | None = None  # optional hard cap (previews, memory)

    def __post_init__(self) -> None:
        if not self.min_support > 0.0:
            raise ConfigError(f"minimum support w_min must be > 0, got {self.min_support}")
        if not 0.0 < self.target_fraction <= 1.0:
            raise ConfigError(f"target fraction rho must be in (0, 1], got {self.target_fraction}")
        if not 0.0 < self.coverage_stop <= 1.0:
            raise ConfigError(f"coverage stop must be in (0, 1], got {self.coverage_stop}")
        if not self.min_gain >= 0.0:
            raise ConfigError(f"minimum gain must be >= 0, got {self.min_gain}")
        if self.max_views is not None and self.max_views < 1:
            raise ConfigError(f"max views must be at least 1, got {self.max_views}")


@dataclass(frozen=True)
class ViewSelection:
    views: tuple[int, ...]  # selected view indices, in pick order (the deterministic active-view order)
    coverage: tuple[float, ...]  # sum_i c_i(A) / |T| after each pick
    gains: tuple[float, ...]  # marginal gain / |T| of each pick
    stop_reason: str  # COVERAGE_REACHED, GAIN_BELOW_THRESHOLD, ALL_VIEWS_USED or VIEW_LIMIT_REACHED
    num_targets: int  # |T|
    blind_views: tuple[int, ...]  # candidate views that see no Gaussian of T


def target_support(max_visibility: np.ndarray, min_support: float, target_fraction: float) -> np.ndarray:
    """Eq. 13 (``eq:target-support``): q_i = max(rho m*_i, w_min), with m*_i = max_v w_{v,i}."""
    return np.maximum(target_fraction * max_visibility, min_support)


def capped_coverage(visibility: np.ndarray, support: np.ndarray) -> np.ndarray:
    """Eq. 14 (``eq:view-coverage``) for one view: c_i({v}) = min(w_{v,i} / q_i, 1).

    For a set A, c_i(A) = max_{u in A} c_i({u}) (the cap commutes with the max); c_i(empty) = 0.
    """
    return np.minimum(visibility / support, 1.0)


def select_views(visibility, settings: ViewSelectionSettings | None = None) -> ViewSelection:
    """Eqs. 13-15: greedy active-view selection by capped coverage.

    ``visibility`` is w [V, N] (dense numpy/torch or torch sparse). T = {i : m*_i >= w_min}. Each
    step adds v* = argmax_{v not in A} sum_{i in T} [c_i(A + {v}) - c_i(A)] (Eq. 15,
    ``eq:greedy-view-selection``), lowest index on ties. The first pick is always made; after that
    the loop stops before a pick whose gain / |T| is below ``min_gain``, and after a pick that brings
    the coverage sum_i c_i / |T| to ``coverage_stop``. Raises CameraError when no camera sees any
    Gaussian with w >= w_min.
    """
    return _select_from_rows(*_visibility_rows(visibility), settings or ViewSelectionSettings())


def _select_from_rows(
    rows: list[tuple[np.ndarray, np.ndarray]], num_gaussians: int, settings: ViewSelectionSettings
) -> ViewSelection:
    """:func:`select_views` on each view's (indices, positive values)."""
    ratios, num_targets, blind = _coverage_ratios(rows, num_gaussians, settings)

    covered = np.zeros(num_gaussians, dtype=np.float32)  # c_i(A)

    def gain_of(v: int) -> float:
        idx, r = ratios[v]
        return float(np.maximum(r - covered[idx], 0.0).sum(dtype=np.float64))

    # Lazy greedy: heap of (-gain bound, view, round the bound was computed in).
    heap = [(-float(r.sum(dtype=np.float64)), v, 0) for v, (_, r) in enumerate(ratios)]
    heapq.heapify(heap)
    views: list[int] = []
    coverage: list[float] = []
    gains: list[float] = []
    reason = ALL_VIEWS_USED
    while heap:
        if settings.max_views is not None and len(views) >= settings.max_views:
            reason = VIEW_LIMIT_REACHED
            break
        neg_bound, v, computed_in = heapq.heappop(heap)
        if computed_in != len(views):
            heapq.heappush(heap, (-gain_of(v), v, len(views)))
            continue
        gain = -neg_bound
        if views and gain / num_targets < settings.min_gain:
            reason = GAIN_BELOW_THRESHOLD
            break
        idx, r = ratios[v]
        covered[idx] = np.maximum(covered[idx], r)
        views.append(v)
        gains.append(gain / num_targets)
        coverage.append(float(covered.sum(dtype=np.float64)) / num_targets)  # exact sum of 1s when complete
        if coverage[-1] >= settings.coverage_stop:
            reason = COVERAGE_REACHED
            break
    return ViewSelection(tuple(views), tuple(coverage), tuple(gains), reason, num_targets, blind)


def select_views_reference(visibility: np.ndarray, settings: ViewSelectionSettings | None = None) -> ViewSelection:
    """Plain greedy loop over a dense [V, N] matrix, re-evaluating every view each round (test reference)."""
    settings = settings or ViewSelectionSettings()
    w = np.asarray(visibility, dtype=np.float64)
    m_star = w.max(0)
    targets = m_star >= settings.min_support
    if not targets.any():
        raise CameraError("no camera sees any Gaussian")
    c_single = capped_coverage(
        w[:, targets], target_support(m_star[targets], settings.min_support, settings.target_fraction)
    )
    num_targets = int(targets.sum())
    covered = np.zeros(num_targets)
    views: list[int] = []
    coverage: list[float] = []
    gains: list[float] = []
    reason = ALL_VIEWS_USED
    while len(views) < w.shape[0]:
        if settings.max_views is not None and len(views) >= settings.max_views:
            reason = VIEW_LIMIT_REACHED
            break
        candidate_gains = [
            -1.0 if v in views else float(np.maximum(c_single[v] - covered, 0.0).sum()) for v in range(w.shape[0])
        ]
        v = int(np.argmax(candidate_gains))  # first maximum: lowest index
        if views and candidate_gains[v] / num_targets < settings.min_gain:
            reason = GAIN_BELOW_THRESHOLD
            break
        covered = np.maximum(covered, c_single[v])
        views.append(v)
        gains.append(candidate_gains[v] / num_targets)
        coverage.append(float(covered.sum() / num_targets))
        if coverage[-1] >= settings.coverage_stop:
            reason = COVERAGE_REACHED
            break
    blind = tuple(v for v in range(w.shape[0]) if not (c_single[v] > 0).any())
    return ViewSelection(tuple(views), tuple(coverage), tuple(gains), reason, num_targets, blind)


def _coverage_ratios(
    rows: list[tuple[np.ndarray, np.ndarray]], num_gaussians: int, settings: ViewSelectionSettings
) -> tuple[list[tuple[np.ndarray, np.ndarray]], int, tuple[int, ...]]:
    """Per view, (indices in T, c_i({v}) as float32); |T|; views that see nothing of T."""
    m_star = np.zeros(num_gaussians, dtype=np.float32)
    for idx, val in rows:
        m_star[idx] = np.maximum(m_star[idx], val)
    in_targets = m_star >= settings.min_support
    num_targets = int(in_targets.sum())
    if num_targets == 0:
        raise CameraError(
            f"none of the {len(rows)} cameras sees any of the {num_gaussians} Gaussians "
            f"(no visibility reaches {settings.min_support:g}); check the camera poses and the scene's scale"
        )
    support = target_support(m_star, settings.min_support, settings.target_fraction).astype(np.float32)
    ratios = []
    blind = []
    for v, (idx, val) in enumerate(rows):
        keep = in_targets[idx]
        idx, val = idx[keep], val[keep]
        ratios.append((idx, capped_coverage(val, support[idx]).astype(np.float32)))
        if idx.size == 0:
            blind.append(v)
    return ratios, num_targets, tuple(blind)


def _visibility_rows(visibility) -> tuple[list[tuple[np.ndarray, np.ndarray]], int]:
    """Per view, (indices, values) of its positive entries; plus N. Checks shape and finiteness."""
    if isinstance(visibility, torch.Tensor) and visibility.layout in (torch.sparse_coo, torch.sparse_csr):
        if visibility.ndim != 2:
            raise ValueError(f"visibility must be [V, N], got shape {tuple(visibility.shape)}")
        num_views, num_gaussians = visibility.shape
        if visibility.layout == torch.sparse_coo:
            coo = visibility.detach().coalesce()  # sums duplicates, sorts by (view, Gaussian)
            view_of, col = coo.indices().cpu().numpy()
            val = coo.values().cpu().numpy().astype(np.float32)
            crow = np.searchsorted(view_of, np.arange(num_views + 1))
        else:
            crow = visibility.crow_indices().cpu().numpy()
            col = visibility.col_indices().cpu().numpy()
            val = visibility.values().detach().cpu().numpy().astype(np.float32, copy=False)
        segments = [(col[crow[v] : crow[v + 1]], val[crow[v] : crow[v + 1]]) for v in range(num_views)]
    else:
        visibility = visibility.detach() if isinstance(visibility, torch.Tensor) else np.asarray(visibility)
        shape = tuple(visibility.shape)
        if len(shape) != 2:
            raise ValueError(f"visibility must be [V, N], got shape {shape}")
        num_views, num_gaussians = shape
        segments = []
        for v in range(num_views):
            row = visibility[v]
            row = row.float().cpu().numpy() if isinstance(row, torch.Tensor) else np.asarray(row)
            idx = np.flatnonzero(row)
            segments.append((idx, row[idx].astype(np.float32)))
    if num_views < 1:
        raise CameraError("there are no candidate cameras to select views from")
    rows = []
    for idx, val in segments:
        if not np.isfinite(val).all():
            raise NumericalError("the visibility matrix has non-finite values")
        if (val < 0).any():
            raise ValueError("the visibility matrix has negative values")
        positive = val > 0
        rows.append((idx, val) if positive.all() else (idx[positive], val[positive]))
    return rows, num_gaussians


# --- On a scene: the visibility matrix from the rasterizer, and the active views of a run ------------------


@dataclass
class ActiveViews:
    indices: list[int]  # chosen cameras, in pick order (the deterministic active-view order)
    coverage: list[float]  # total capped coverage after each pick
    per_view_coverage: list[float]  # capped coverage each camera gives on its own
    reason: str  # why the selection stopped
    blind: list[int] = field(default_factory=list)  # cameras that see nothing
    seen: float = 1.0  # share of the (selected) splats the chosen cameras see: the rest a run leaves as they are


def scaled_cameras(cameras: Sequence[Camera], scale: float) -> list[Camera]:
    """The cameras at ``scale`` times their resolution (the CLI's ``--render-scale``, the panel's Fit Scale)."""
    if scale == 1.0:
        return list(cameras)
    return [c.resized(max(1, round(c.width * scale)), max(1, round(c.height * scale))) for c in cameras]


def visibility_matrix(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    settings: RasterSettings,
    *,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
    device: str | torch.device = "cpu",
    renderers: list | None = None,
    blend_weights: list | None = None,
) -> torch.Tensor:
    """w [V, N] (sparse CSR, int32 indices, on the CPU): each Gaussian's depth-consistent visible weight
    sum_p T alpha in each view (Sec. 4.3), rendered on ``device``.

    ``progress(done, total)`` is called once per camera, after its render (done = 1 .. total); setting ``cancel``
    stops with CancelledError. Given a list, ``renderers`` gets each camera's colour-only renderer from the same
    render (:class:`~dresg_addon.raster.ColorOnlyRenderer`), so that a fit of these views renders none again;
    ``blend_weights`` gets each camera's [N] float32 blend weights (every sample's T alpha, not only the
    depth-consistent ones: what ``refine.screen_axes`` measures), so that a split of these views renders none again.
    """
    means, quats, log_scales, logits = (t.to(device) for t in geometry_tensors(scene))
    covariances = splat_covariances(quats, log_scales, torch.float64)
    colors = torch.zeros_like(means)
    cols, vals = [], []
    keep = renderers is not None
    for v, camera in enumerate(cameras):
        if cancel is not None and cancel.is_set():
            raise CancelledError("view selection cancelled")
        with torch.no_grad():
            out = render(
                means, quats, log_scales, logits, colors, camera, settings, "depth_consistent", keep, covariances
            )
        if keep:
            renderers.append(ColorOnlyRenderer(means, quats, log_scales, logits, camera, settings, output=out))
        if blend_weights is not None:
            blend_weights.append(out.blend_weights.cpu().float())
        visibility = out.visibility.cpu()
        nz = torch.nonzero(visibility > 0).squeeze(-1)
        cols.append(nz.to(torch.int32))  # a 2M-splat scene's 16 views: 24M entries, 0.2 GB as int32 and float32
        vals.append(visibility[nz].float())
        if progress is not None:
            progress(v + 1, len(cameras))
    crow = torch.zeros(len(cameras) + 1, dtype=torch.int32)
    crow[1:] = torch.cumsum(torch.tensor([c.numel() for c in cols], dtype=torch.int64), 0).to(torch.int32)
    col, val = torch.cat(cols), torch.cat(vals)
    cols.clear(), vals.clear()
    return torch.sparse_csr_tensor(crow, col, val, (len(cameras), len(scene)), check_invariants=False)


def select_active_views(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    config,  # StylizeConfig: this is an entry point (the Select Views operator, the CLI) as well as a step
    *,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
    mask: np.ndarray | None = None,  # [N] bool: only these splats count (a stylized selection)
    device: str | torch.device = "cpu",  # where the coverage renders run
    near: float | None = None,  # the near plane, for a scene in tiny units (None: the rasterizer's)
    renderers: list | None = None,  # gets every camera's colour-only renderer (visibility_matrix)
    blend_weights: list | None = None,  # gets every camera's blend weights (visibility_matrix)
) -> ActiveViews:
    """Sec. 4.3: greedy capped-coverage selection (Eqs. 13-15) on the rasterizer's visibility weights.

    ``progress`` and ``cancel`` as for :func:`visibility_matrix` (one render per camera is the cost: the greedy
    selection after the last one takes a few % of the renders' time). With a
    ``mask`` coverage counts the selected splats only, so the views chosen are the ones that see them.
    """
    if not cameras:
        raise CameraError("no cameras: add cameras to the scene, give a cameras file, or use orbit cameras")
    w = visibility_matrix(
        scene,
        cameras,
        config.raster(near),
        progress=progress,
        cancel=cancel,
        device=device,
        renderers=renderers,
        blend_weights=blend_weights,
    )
    # Row by row from here: a [V, N] array of a 2M-splat scene, or its coordinates, would be GBs.
    rows, _ = _visibility_rows(w)
    if mask is not None:  # splats outside the selection are seen by no view, as far as coverage goes
        selected = np.asarray(mask, bool)
        rows = [(idx[selected[idx]], val[selected[idx]]) for idx, val in rows]
    settings = ViewSelectionSettings(max_views=config.max_views or None)
    chosen = _select_from_rows(rows, len(scene), settings)
    most = np.zeros(len(scene), dtype=np.float64)
    for idx, val in rows:
        most[idx] = np.maximum(most[idx], val)
    targets = most >= settings.min_support
    support = target_support(most, settings.min_support, settings.target_fraction)
    per_view = []
    for idx, val in rows:
        aimed = targets[idx]
        coverage = capped_coverage(val[aimed].astype(np.float64), support[idx[aimed]])
        per_view.append(float(coverage.sum() / max(targets.sum(), 1)))
    seen_weight = np.zeros(len(scene), dtype=np.float64)
    for v in chosen.views:
        idx, val = rows[v]
        seen_weight[idx] = np.maximum(seen_weight[idx], val)
    count = int(np.count_nonzero(mask)) if mask is not None else len(scene)
    seen = float((seen_weight >= settings.min_support).sum()) / max(count, 1)
    return ActiveViews(
        list(chosen.views), list(chosen.coverage), per_view, chosen.stop_reason, list(chosen.blind_views), seen
    )
