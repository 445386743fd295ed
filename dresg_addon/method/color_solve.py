"""The colour fit with geometry frozen, solved as the bounded least-squares problem it is (Sec. 4.3, Eq. 16).

With means, scales, rotations and opacities fixed, view v renders rgb_v = W_v c + b_v: W_v [P, N] holds
each sample's T alpha (:class:`~dresg_addon.raster.ColorOnlyRenderer`), b_v what does not depend on the
colours (background, kept SH bands). Fitting targets t_v over all active views at once is then

    min_{c in [0, 1]}  f(c) = sum_v || W_v c + b_v - t_v ||^2.

The box matters: without it the optimum of inconsistent targets puts half the colours far outside
[0, 1] (measured on the bonsai: -22 to 33), which a render cannot show. So the solve is a projected
Newton-CG method in the manner of Moré and Toraldo's GPCG (1991): each round takes the splats that are
free (not held at a bound by a gradient pointing out of the box), runs a few conjugate-gradient
iterations on the normal equations restricted to them, damped by lambda || c - c_round ||^2 toward the
round's colours (lambda = ``ridge`` x the mean of diag(sum_v W_v^T W_v), Levenberg-Marquardt style: a
splat that a few faint samples barely constrain moves little per round) and preconditioned by their
diagonal (each splat's summed squared weights plus lambda: Jacobi), then projects the
step onto the box with a backtracking line search that guarantees the objective decreases. It stops when
a round lowers f by less than ``tolerance`` of f, or after ``max_rounds``. The three channels are solved
at once, and the matrix is never formed: one product with W_v and one with W_v^T per view and
iteration. Measured on the bonsai (8 views, a stage-3 target): 4 rounds of 8 iterations reach an
objective within 1% of 120 iterations' (RMSE 0.0557 vs 0.0553), where 30 Adam steps of the paper's
loss stop at 0.062.

Anchored (``anchor`` mu > 0), the solve minimises f(c) + mu e_bar || c - c_0 ||^2, c_0 the colours it
starts from and e_bar the mean of diag(sum_v W_v^T W_v): a proximal step. A splat the views see as much as
the average splat is pulled halfway to what they say by it, one they barely see keeps its colour, instead of
taking whatever value serves one view's faint samples and showing it from every other angle. Measured
on the demo scene (preview, 8 views, novel views between them): short-range warp RMSE 0.0497 at mu = 0,
0.0471 at mu = 0.3 (the presets' value) and 0.0453 at mu = 1 (colour transfer 0.0406), patch SW unchanged
(0.0740 / 0.0736 / 0.0735), the fit residual up to 1.17x and 1.59x the unanchored optimum's.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import torch

from ..util.errors import ConfigError, NumericalError

ARMIJO = 1e-4  # sufficient decrease of the projected line search
BACKTRACKS = 6  # halvings of the projected step before a round gives up
COVERAGE_FLOOR = 1e-3  # a pixel's coverage below this counts as this in the view average (no division by 0)
WEIGHT_FLOOR = 1e-9  # a splat with less summed weight over all views is one no view draws
BLEND_BLOCK = 65_536  # splats blended at a time (best_view_colors)
BEST_VIEW_ROUNDS = 3  # rounds of each view's own solve in the best views (within 1% of 6 on the bonsai)
PAINT_ROUNDS = 20  # each view's solve when the views paint in turn: unanchored, lines as sharp as the splats allow


@dataclass(frozen=True)
class ColorSolveSettings:
    tolerance: float = 0.005  # stop when a round lowers the objective by less than this fraction
    max_rounds: int = 6  # projected rounds (each: free set, CG, projected line search)
    cg_iterations: int = 8  # conjugate-gradient iterations per round
    ridge: float = 1e-2  # lambda / mean diag(sum_v W_v^T W_v): damping of each round's step
    anchor: float = 0.0  # mu of the proximal term mu e_bar ||c - c_0||^2 (module docstring); 0: plain least squares

    def __post_init__(self) -> None:
        checks = [
            (0.0 < self.tolerance < 1.0, "tolerance must be in (0, 1)"),
            (self.max_rounds >= 1 and self.cg_iterations >= 1, "max_rounds and cg_iterations must be >= 1"),
            (math.isfinite(self.ridge) and self.ridge > 0.0, "ridge must be finite and > 0"),
            (math.isfinite(self.anchor) and self.anchor >= 0.0, "anchor must be finite and >= 0"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"colour solver: {message}")


# A run's solve: its rounds and tolerance within 1% of 120 iterations on the bonsai, its anchor mu 0.3 (both measured
# in the module docstring).
FIT_SOLVE = ColorSolveSettings(anchor=0.3)


@dataclass
class ColorSolveResult:
    colors: torch.Tensor  # [N, 3] in [0, 1]
    iterations: int  # conjugate-gradient iterations, every round together
    objectives: list[float] = field(default_factory=list)  # f at the start and after each round


class LinearViews:
    """The active views as linear maps of the colours: image_v = W_v c + b_v, each [P_v, 3] flat.

    ``maps`` have ``matvec`` ([N, K] -> [P, K]), ``rmatvec`` ([P, K] -> [N, K]), ``add_rmatvec`` (the same added
    into an [N, K] in place) and ``column_energy`` ([N], sum of squared weights), as
    :class:`~dresg_addon.raster.rasterizer.SparseColorMap` has; ``constants`` are the b_v.
    """

    def __init__(self, maps: Sequence, constants: Sequence[torch.Tensor], columns: int | None = None):
        if len(maps) != len(constants) or not maps:
            raise ValueError("LinearViews needs one constant term per view, and at least one view")
        self.maps, self.constants = list(maps), [c.reshape(-1, 3).float() for c in constants]
        self.energy = torch.stack([m.column_energy() for m in self.maps]).sum(0).float()  # [N]
        # The mean squared weight per column, over ``columns`` columns (a view's own columns stand for all N).
        self.mean_energy = float(self.energy.double().sum() / (columns or self.energy.numel()))

    def alone(self, view: int) -> tuple[LinearViews, torch.Tensor]:
        """View ``view`` by itself over the columns it draws (a solve's vectors then hold only those), and their
        indices [K]; its ridge and anchor weigh what they would over all N columns."""
        m = self.maps[view]
        drawn = torch.nonzero(m.column_energy() > 0).squeeze(-1)
        return LinearViews([_Columns(m, drawn)], [self.constants[view]], self.energy.numel()), drawn

    def __len__(self) -> int:
        return len(self.maps)

    def images(self, colors: torch.Tensor) -> list[torch.Tensor]:  # [N, 3] -> V x [P, 3]
        return [m.matvec(colors) + b for m, b in zip(self.maps, self.constants)]

    @cached_property
    def coverages(self) -> list[torch.Tensor]:  # V x [P, 1]: each pixel's coverage W_v 1 (the render's alpha)
        return [m.matvec(torch.ones(m.shape[1], 1)) for m in self.maps]

    @cached_property
    def drawn_weights(self) -> torch.Tensor:  # [V, N, 1] float64: sum_p W_v[p, i], how much view v draws splat i
        return torch.stack([m.rmatvec(c.new_ones(c.shape)).double() for m, c in zip(self.maps, self.coverages)])

    @cached_property
    def drawn_weight(self) -> torch.Tensor:  # [N, 1] float64: how much all the views together draw a splat
        return self.drawn_weights.sum(0)


class _Columns:
    """A map restricted to some of its columns (the rest are zero in it): products on vectors of those columns only."""

    def __init__(self, m, columns: torch.Tensor):
        self.m, self.columns = m, columns
        self.shape = (m.shape[0], columns.numel())
        self._full = torch.zeros(m.shape[1], 3)  # the other columns stay 0 (the map does not read them anyway)

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1] != 3:
            return self.m.matvec(torch.zeros(self.m.shape[1], x.shape[1]).index_copy_(0, self.columns, x))
        return self.m.matvec(self._full.index_copy_(0, self.columns, x))

    def rmatvec(self, y: torch.Tensor) -> torch.Tensor:
        return self.m.rmatvec(y).index_select(0, self.columns)

    def add_rmatvec(self, out: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return out.add_(self.rmatvec(y))

    def column_energy(self) -> torch.Tensor:
        return self.m.column_energy().index_select(0, self.columns)


class _Problem:
    """f, its gradient and its damped normal-equation products for fixed targets."""

    def __init__(self, views: LinearViews, targets, ridge: float, anchor: torch.Tensor, mu: float):
        self.views = views
        self.rhs = [t - b for t, b in zip(targets, views.constants)]  # t_v - b_v
        mean_energy = max(views.mean_energy, 1e-12)
        self.ridge = ridge * mean_energy
        self.anchor, self.anchor_weight = anchor, mu * mean_energy
        diagonal = views.energy[:, None].expand(-1, 3)
        self.inverse_diagonal = 1.0 / (diagonal + self.ridge + self.anchor_weight)

    def residuals(self, x: torch.Tensor) -> list[torch.Tensor]:  # V x [P, 3]: W_v x + b_v - t_v
        return [m.matvec(x) - r for m, r in zip(self.views.maps, self.rhs)]

    def value(self, x: torch.Tensor, residuals: list[torch.Tensor]) -> float:  # f at x, from its residuals
        # Squares in float32, their sums in float64: no float64 copies of [N, 3] or [P, 3] vectors.
        total = (
            self.anchor_weight * float((x - self.anchor).square().sum(dtype=torch.float64))
            if self.anchor_weight
            else 0.0
        )
        for e in residuals:
            total += float(e.square().sum(dtype=torch.float64))
        return total

    def gradient(self, x: torch.Tensor, residuals: list[torch.Tensor]) -> torch.Tensor:  # half the gradient of f
        g = self.anchor_weight * (x - self.anchor)
        for m, e in zip(self.views.maps, residuals):
            m.add_rmatvec(g, e)
        return g

    def normal(self, p: torch.Tensor) -> torch.Tensor:  # the Hessian of f (halved) times p; one W_v, W_v^T each
        out = (self.ridge + self.anchor_weight) * p
        for m in self.views.maps:
            m.add_rmatvec(out, m.matvec(p))
        return out


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # per column, summed in float64: [N, K] -> [K]
    return (a * b).sum(0, dtype=torch.float64)


def _cg_step(
    problem: _Problem, gradient: torch.Tensor, free: torch.Tensor, iterations: int
) -> tuple[torch.Tensor, int]:
    """Jacobi-preconditioned CG on the normal equations over the ``free`` entries, from the point whose
    (half) ``gradient`` is given: the step [N, 3] toward the minimum on that face."""
    mask = free.to(gradient.dtype)
    r = -gradient * mask
    z = r * problem.inverse_diagonal
    p, rz = z.clone(), _dot(r, z)
    step = torch.zeros_like(gradient)
    for iteration in range(1, iterations + 1):
        q = problem.normal(p) * mask
        pq = _dot(p, q)
        alpha = torch.where(pq > 0, rz / pq.clamp_min(1e-300), torch.zeros_like(rz)).float()
        step.add_(p * alpha)
        r.sub_(q * alpha)
        z = r * problem.inverse_diagonal
        rz_next = _dot(r, z)
        if not bool(torch.isfinite(rz_next).all()):
            raise NumericalError("the colour solve became non-finite")
        if float(rz_next.max()) <= 0.0:
            return step, iteration
        beta = torch.where(rz > 0, rz_next / rz.clamp_min(1e-300), torch.zeros_like(rz)).float()
        p = z + p * beta
        rz = rz_next
    return step, iterations


def projected_solve(
    views: LinearViews,
    targets: Sequence[torch.Tensor],  # V x [P, 3]
    start: torch.Tensor,  # [N, 3]: the warm start
    settings: ColorSolveSettings,
    # (round, objective, colours, their residuals W_v c + b_v - t_v: V x [P, 3]) after each
    each_round: Callable[[int, float, torch.Tensor, list[torch.Tensor]], None] | None = None,
) -> ColorSolveResult:
    """min f(c) (+ the anchor term toward ``start``) over c in [0, 1]^(N x 3) by projected Newton-CG rounds
    (module docstring)."""
    x = start.detach().float().clamp(0.0, 1.0)
    problem = _Problem(views, targets, settings.ridge, x.clone(), settings.anchor)
    # The accepted point's residuals serve the next round's gradient: one product with each W_v less a round.
    residuals = problem.residuals(x)
    value = problem.value(x, residuals)
    objectives, total = [value], 0
    if not math.isfinite(value):
        raise NumericalError("the colour fit's objective became non-finite")
    for round_index in range(1, settings.max_rounds + 1):
        g = problem.gradient(x, residuals)
        free = ~(((x <= 0.0) & (g > 0)) | ((x >= 1.0) & (g < 0)))
        step, used = _cg_step(problem, g, free, settings.cg_iterations)
        total += used
        # Projected backtracking: the box-projected step must lower f (Armijo on the projected move).
        scale, accepted = 1.0, False
        for _ in range(BACKTRACKS):
            candidate = (x + scale * step).clamp(0.0, 1.0)
            candidate_residuals = problem.residuals(candidate)
            candidate_value = problem.value(candidate, candidate_residuals)
            if not math.isfinite(candidate_value):
                raise NumericalError("the colour fit's objective became non-finite")
            if candidate_value <= value + ARMIJO * 2.0 * float(_dot(g, candidate - x).sum()):
                accepted = True
                break
            scale *= 0.5
        if not accepted:
            break
        drop = value - candidate_value
        x, value, residuals = candidate, candidate_value, candidate_residuals
        objectives.append(value)
        if each_round is not None:
            each_round(round_index, value, x, residuals)
        if drop <= settings.tolerance * max(value, 1e-30):
            break
    return ColorSolveResult(x, total, objectives)


def covered_rmse(residuals: Sequence[torch.Tensor], covered: Sequence[torch.Tensor]) -> float:
    """The RMSE of residuals (V x [P, 3]) over the covered pixels (V x [P] bool) of all views together, summed in
    float64; 0 when no pixel is covered."""
    total, count = 0.0, 0
    for residual, mask in zip(residuals, covered):
        total += float(torch.where(mask[:, None], residual, 0.0).square().sum(dtype=torch.float64))
        count += 3 * int(mask.sum())
    return math.sqrt(total / count) if count else 0.0


def _covered_rmse(image: torch.Tensor, target: torch.Tensor, alpha: torch.Tensor, covered: float) -> float:
    mask = alpha.reshape(-1) > covered  # [P]
    if not bool(mask.any()):
        return 0.0
    return float((image[mask].double() - target[mask].double()).square().mean().sqrt())


def view_average_colors(
    views: LinearViews,
    targets: Sequence[torch.Tensor],  # V x [3, H, W] (or [P, 3])
    fallback: torch.Tensor,  # [N, 3]: the colour of a splat no view draws
) -> torch.Tensor:  # [N, 3] in [0, 1]
    """Each splat's view average: what the targets show where the views draw it, c_i = sum_v sum_p W_v[p, i] u_v[p]
    / sum_v sum_p W_v[p, i], with u_v = (t_v - b_v) / a_v the target less its constant term, divided by the pixel's
    coverage a_v = W_v 1 (so a splat on a silhouette gets the colour drawn there, not one darkened by the
    background). A splat no view draws keeps ``fallback``.

    Least squares from a splat's own colours keeps whatever of them the views cannot see: on a capture, the
    sub-pixel detail (the bonsai's knit, one stitch a splat) that the fit size averages away and twice it shows.
    From the view average, splats drawn into the same pixels start alike, and the anchor holds them there.
    """
    flat = _flat_targets(targets, len(views))
    numerator = torch.zeros_like(fallback, dtype=torch.float64)
    for m, b, target, coverage in zip(views.maps, views.constants, flat, views.coverages):
        drawn = ((target - b) / coverage.clamp_min(COVERAGE_FLOOR)).clamp(0.0, 1.0)
        numerator += m.rmatvec(drawn).double()  # a pixel no splat covers has no weight in any column
    weight = views.drawn_weight
    seen = weight > WEIGHT_FLOOR
    average = (numerator / weight.clamp_min(WEIGHT_FLOOR)).float().clamp(0.0, 1.0)
    return torch.where(seen, average, fallback.float())


def _flat_targets(targets: Sequence[torch.Tensor], views: int) -> list[torch.Tensor]:
    """V x [3, H, W] or [P, 3] -> V x [P, 3] float32, checked finite and one per view."""
    flat = [t.permute(1, 2, 0).reshape(-1, 3) if t.dim() == 3 else t.reshape(-1, 3) for t in targets]
    flat = [t.float() for t in flat]
    if len(flat) != views:
        raise ValueError(f"{len(flat)} targets for {views} views")
    for t in flat:
        if not torch.isfinite(t).all():
            raise NumericalError("a colour-fit target has non-finite values")
    return flat


def single_view_solutions(
    views: LinearViews,
    targets: Sequence[torch.Tensor],  # V x [P, 3]
    start: torch.Tensor,  # [N, 3]
    settings: ColorSolveSettings,
    each_view: Callable[[int], None] | None = None,  # (views solved so far) after each; it may raise to cancel
) -> list[torch.Tensor]:  # V x [N, 3]
    """Each view's own bounded least-squares colours: view v solved alone, from ``start`` (and anchored to it when
    ``settings.anchor`` > 0). A splat the view does not draw keeps its ``start`` colour. One solve per view costs
    about one joint solve."""
    solutions = []
    for v, target in enumerate(targets):
        alone, drawn = views.alone(v)
        local = projected_solve(alone, [target], start.index_select(0, drawn), settings).colors
        solutions.append(start.detach().float().clamp(0.0, 1.0).index_copy(0, drawn, local))
        if each_view is not None:
            each_view(len(solutions))
    return solutions


@dataclass(frozen=True)
class SplitRow:
    """One view's pixels on splats of one width band: how well the joint fit and the view's own fit carry them."""

    view: int
    band: str  # e.g. "< 3 px", "3-8 px", ">= 8 px"
    share: float  # of the view's covered pixels
    joint_rmse: float  # the joint least-squares optimum of all views, against this view's target
    single_rmse: float  # this view solved alone


def fit_split(
    views: LinearViews,
    targets: Sequence[torch.Tensor],  # V x [3, H, W] (or [P, 3])
    widths: Sequence[torch.Tensor],  # V x [P]: each pixel's splat width (``fitting.pixel_widths``)
    check: Sequence[int],  # the views to report
    edges: Sequence[float] = (3.0, 8.0),  # band edges in pixels, increasing
    settings: ColorSolveSettings = ColorSolveSettings(max_rounds=12),
    covered: float = 0.5,
) -> list[SplitRow]:
    """Where a fit loses its targets, by the width of the splats under each pixel: per view in ``check`` and band,
    the RMSE of the joint bounded least-squares optimum (all views) and of the view solved alone, both unanchored
    from the views' average (:func:`view_average_colors`), over the view's covered pixels (alpha > ``covered``).

    The view alone fits as well as its splats can, so its error is what the splats cannot draw (wide splats and
    fine marks); the joint one's excess over it is what the other views ask of the same splats (the targets
    disagree, or faint layers look different from each angle). A diagnostic (``bench/fit_split.py``).
    """
    if list(edges) != sorted(edges) or any(not math.isfinite(e) or e <= 0 for e in edges):
        raise ValueError(f"fit_split: band edges must be positive and increasing, got {list(edges)}")
    if any(not 0 <= v < len(views) for v in check):
        raise ValueError(f"fit_split: views {list(check)} do not index the {len(views)} views")
    flat = _flat_targets(targets, len(views))
    plain = replace(settings, anchor=0.0)
    start = view_average_colors(views, flat, torch.full((views.energy.numel(), 3), 0.5))
    joint = projected_solve(views, flat, start, plain).colors
    labels = [f"< {edges[0]:g} px"] if edges else ["all"]
    labels += [f"{lo:g}-{hi:g} px" for lo, hi in zip(edges, edges[1:])] + ([f">= {edges[-1]:g} px"] if edges else [])
    bounds = [0.0, *edges, math.inf]
    rows = []
    for v in check:
        m, b, target = views.maps[v], views.constants[v], flat[v]
        alone = projected_solve(LinearViews([m], [b]), [target], start, plain).colors
        joint_image, alone_image = m.matvec(joint) + b, m.matvec(alone) + b
        mask = views.coverages[v].reshape(-1) > covered
        count = int(mask.sum())
        width = widths[v].reshape(-1)
        for label, lo, hi in zip(labels, bounds, bounds[1:]):
            band = mask & (width >= lo) & (width < hi)
            if not bool(band.any()):
                continue
            joint_rmse = _covered_rmse(joint_image, target, band.float(), 0.5)
            single_rmse = _covered_rmse(alone_image, target, band.float(), 0.5)
            rows.append(SplitRow(v, label, int(band.sum()) / max(count, 1), joint_rmse, single_rmse))
    return rows


def best_view_colors(
    views: LinearViews,
    targets: Sequence[torch.Tensor],  # V x [P, 3]
    joint: torch.Tensor,  # [N, 3]: the joint fit
    settings: ColorSolveSettings,
    sharpness: float,
    each_view: Callable[[int], None] | None = None,  # as single_view_solutions takes it
) -> torch.Tensor:  # [N, 3] in [0, 1]
    """Each splat coloured from the views that draw it most, instead of the least-squares average of all views.

    As texturing a mesh from photos picks one view per face rather than blending all of them, which blurs
    (Waechter, Moehrle and Goesele 2014, "Let There Be Color!"), softened so that neighbours seen best from two
    views meet without a seam: c_i = sum_v w_vi c_vi / sum_v w_vi, with c_v view v's own solution anchored to
    the joint fit (:func:`single_view_solutions`), w_vi = (d_vi / max_u d_ui)^p and d_vi = sum_p W_v[p, i] how
    much view v draws splat i; p = ``sharpness`` (large: the one best view). A splat no view draws keeps its
    joint colour. The joint fit keeps what all views agree on, and on a capture that includes its own sub-pixel
    texture (the bonsai's knit); each view's own fit carries that view's marks instead.
    """
    if not (math.isfinite(sharpness) and sharpness > 0.0):
        raise ConfigError(f"colour solver: the best views' sharpness must be finite and > 0 (got {sharpness})")
    alone = single_view_solutions(views, targets, joint, replace(settings, max_rounds=BEST_VIEW_ROUNDS), each_view)
    out = torch.empty(joint.shape)
    # A block of splats at a time: the views' float64 weights of all splats at once held ~0.7 GB more at 800k.
    for first in range(0, joint.shape[0], BLEND_BLOCK):
        block = slice(first, first + BLEND_BLOCK)
        drawn = views.drawn_weights[:, block]  # [V, B, 1]
        most = drawn.amax(0, keepdim=True)  # [1, B, 1]
        # (d / max d)^p in log space: a faint view's weight underflows to 0, never to NaN
        weights = torch.where(
            drawn > WEIGHT_FLOOR,
            torch.exp(sharpness * (drawn.clamp_min(WEIGHT_FLOOR).log() - most.clamp_min(WEIGHT_FLOOR).log())),
            0.0,
        )
        total = weights.sum(0)  # [B, 1]
        colors = torch.stack([a[block] for a in alone]).double()
        blended = (weights * colors).sum(0) / total.clamp_min(WEIGHT_FLOOR)
        out[block] = torch.where(total > WEIGHT_FLOOR, blended.float(), joint[block].float()).clamp(0.0, 1.0)
    return out


def first_views(drawn: torch.Tensor, share: float) -> torch.Tensor:  # [V, N, 1] -> [N] long
    """Each splat's first view: the earliest v (in the views' order) with d_vi >= ``share`` x max_u d_ui, d_vi how
    much view v draws splat i (``LinearViews.drawn_weights``); -1 for a splat no view draws."""
    if not (math.isfinite(share) and 0.0 < share <= 1.0):
        raise ConfigError(f"colour solver: the first view's share must be in (0, 1] (got {share})")
    drawn = drawn.reshape(drawn.shape[0], -1)
    enough = (drawn >= share * drawn.amax(0, keepdim=True)) & (drawn > WEIGHT_FLOOR)
    return torch.where(enough.any(0), enough.to(torch.uint8).argmax(0), -1)


class ViewsInTurn:
    """The views painting the splats in turn: each splat is painted once, by its first view (:func:`first_views`),
    which solves its own target alone (bounded least squares, unanchored, ``rounds`` rounds) with the splats that
    earlier views painted held at their colours, and keeps the colours of the splats it is first to draw.

    Texturing a mesh from photos colours each face from one view instead of blending them all (Waechter, Moehrle
    and Goesele 2014); here the views also take turns, so a view sees, through :meth:`painted_image`, what the
    earlier ones painted exactly as the splats will show it, and can be guided to continue it. A line drawing's
    lines then line up across views to the width of a line; blended, or copied from view to view by reprojecting
    images, they blur into grey or streaks (docs/decisions/010-ink-drawn-in-turn.md).
    """

    def __init__(self, views: LinearViews, share: float, settings: ColorSolveSettings, rounds: int = PAINT_ROUNDS):
        self.views = views
        self.first = first_views(views.drawn_weights, share)
        count = views.energy.numel()
        self.colors = torch.zeros(count, 3)
        self.painted = torch.zeros(count, dtype=torch.bool)
        self.settings = replace(settings, anchor=0.0, max_rounds=rounds)  # only the solve's own settings are read

    def painted_image(self, view: int) -> tuple[torch.Tensor, torch.Tensor]:  # -> [P, 3], [P]
        """What the painted splats show in ``view``: their colour at each pixel (0 where none is drawn) and the
        share of the pixel's coverage they make."""
        m = self.views.maps[view].only_columns(self.painted)
        drawn = m.matvec(torch.ones(self.colors.shape[0], 1))[:, 0]
        image = m.matvec(self.colors) / drawn.clamp_min(COVERAGE_FLOOR)[:, None]
        coverage = self.views.coverages[view][:, 0]
        share = torch.where(coverage > COVERAGE_FLOOR, drawn / coverage.clamp_min(COVERAGE_FLOOR), 0.0)
        return image.clamp(0.0, 1.0), share.clamp(0.0, 1.0)

    def paint(self, view: int, target: torch.Tensor) -> None:  # target: [3, H, W] or [P, 3]
        """``view`` solved alone for its ``target`` with the painted splats held; its first splats keep the result."""
        (target,) = _flat_targets([target], 1)
        m = self.views.maps[view]
        held = m.only_columns(self.painted)
        free = LinearViews([m.only_columns(~self.painted)], [self.views.constants[view] + held.matvec(self.colors)])
        start = view_average_colors(free, [target], torch.full_like(self.colors, 0.5))
        colors = projected_solve(free, [target], start, self.settings).colors
        mine = self.first == view
        self.colors[mine] = colors[mine].float()
        self.painted |= mine

    def over(self, joint: torch.Tensor) -> torch.Tensor:  # [N, 3] -> [N, 3] in [0, 1]
        """The painted colours, and ``joint``'s for the splats not painted (yet, or ever: no view draws them)."""
        return torch.where(self.painted[:, None], self.colors, joint.float()).clamp(0.0, 1.0)


def first_view_colors(
    views: LinearViews,
    targets: Sequence[torch.Tensor],  # V x [P, 3]
    joint: torch.Tensor,  # [N, 3]: the joint fit
    settings: ColorSolveSettings,
    share: float,
    each_view: Callable[[int], None] | None = None,  # (views painted so far) after each; it may raise to cancel
) -> torch.Tensor:  # [N, 3] in [0, 1]
    """Each splat coloured by its first view, the views painting in turn (:class:`ViewsInTurn`); a splat no view
    draws keeps its joint colour."""
    turn = ViewsInTurn(views, share, settings)
    for view, target in enumerate(targets):
        turn.paint(view, target)
        if each_view is not None:
            each_view(view + 1)
    return turn.over(joint)


def solve_colors(
    views: LinearViews,
    targets: Sequence[torch.Tensor],  # V x [3, H, W] (or [P, 3])
    start: torch.Tensor,  # [N, 3]
    settings: ColorSolveSettings = ColorSolveSettings(),
    each_round: Callable[[int, float, torch.Tensor, list[torch.Tensor]], None] | None = None,  # as projected_solve's
    pick: Callable | None = None,  # (views, targets [P, 3], joint) -> [N, 3]: each splat's colour from the views
) -> ColorSolveResult:
    """The fitted colours in [0, 1]: bounded least squares over all views, anchored to ``start`` when
    ``settings.anchor`` > 0; then, with ``pick``, each splat's colour taken from the views as it says (the best
    views, the first view: the medium's choice, method/medium.py). ``each_round`` is called after every round of the
    joint fit (progress; it may raise to cancel)."""
    flat = _flat_targets(targets, len(views))
    anchor = start.detach().float().clamp(0.0, 1.0)
    result = projected_solve(views, flat, anchor, settings, each_round=each_round)
    if pick is not None:
        result.colors = pick(views, flat, result.colors)
    return result
