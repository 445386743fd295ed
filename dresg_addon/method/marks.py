"""Marks the views agree on: each splat carries where in the painting its colour comes from.

Fitting one set of colours to views whose strokes do not line up averages the strokes away: a least-squares blend
of N layouts keeps about 1/sqrt(N) of their contrast. Patch-based video stylization keeps marks coherent by carrying
the correspondence into the painting instead of the colour (Benard et al. 2013, Jamriska et al. 2019); here the
splats carry it.

A backend that copies the painting's pixels says where each pixel of its proposal comes from
(``ProposalBackend.last_field``, a :class:`~.proposal.synth.PaintingField`). Each splat then votes, over the pixels
a view draws it on and weighted by its blend weight there, for the translation from the view into the painting:
the field is piecewise a translation (one per copied patch), so the vote is a mode, not a mean
(:func:`vote_view`). Its painting coordinate is its centre moved by that translation. The first view (in the views'
order) whose vote has at least half the weight of the strongest owns the splat (:class:`CarriedMarks`): views take
whole surfaces in turn, so neighbouring splats share an owner and its marks run on across them. Each view is then
painted as the splats carry the painting (:func:`paint_view`): a pixel takes what the first view that sees its
surface point (by depth) shows there, that view's copy of the painting carried over the surface in every view, so
the strokes sit on the surface and keep their length; where no view's field sees it, the painting at the coordinate
of the splat drawn most there, moved by the pixel's place against that splat's centre.

The fit sees a target through the splats, a colour each and shared by the views, so it draws a share of the marks
finer than about half a stroke; the last stage, if it carries marks, is fitted again with that band asked for as
much more as the first fit lost, up to the painting's own strength (:func:`emphasis_gains`, :func:`emphasized`).

What the painting's raw pixels do not hold (the scene's forms and light, the palette's regions) is in the
proposals' coarse bands, which the views agree on; so each view's target keeps its coarse bands and takes its fine
band, below the stroke scale, from its painting as the splats carry it (:func:`carried_targets`).
The colour solve over the views then levels what is left between them, the seams (Waechter et al. 2014 level
theirs the same way), instead of averaging the marks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..scene.camera import Camera
from ..scene.warp import DEPTH_TOLERANCE
from .proposal.synth import PaintingField, low_pass

COVERED = 0.5  # alpha above which a pixel's fine band comes from the splats' marks
OWNER_SHARE = 0.5  # a splat's marks from the first view whose vote is at least this share of the strongest's
SAMPLES_AT_ONCE = 2_000_000  # a view's samples worked on at a time (a 2.2M-splat scene's view holds several million)


@dataclass
class ViewVote:
    """One view's vote for each splat (columns of the view's colour map): where in the painting its centre lies, and
    how much blend weight agreed on it (0: the view drew it on no pixel its field covers)."""

    coordinates: torch.Tensor  # [N, 2] float32 (row, column) of the painting source: the centre moved by its vote
    agreed: torch.Tensor  # [N] the blend weight of the splat's pixels that voted for the winning translation


def vote_view(
    contributions: tuple[torch.Tensor, torch.Tensor, torch.Tensor],  # (fit pixel, splat, T alpha) of a view
    fit_shape: tuple[int, int],  # (H, W) of the view's render
    field: PaintingField,  # at the proposal size
    splats: int,
) -> ViewVote:
    """Each splat's mode translation into the painting over its pixels in this view, weighted by blend weight, and the
    painting coordinate of its centre under it. Worked on a range of splats at a time (all of a splat's samples in
    one), so that a dense view's vote holds a fraction of its samples' temporaries."""
    pixel, splat, weight = contributions
    shift = torch.zeros(splats, 2, dtype=torch.long)
    best = torch.zeros(splats, dtype=torch.float64)
    step = math.ceil(splats / max(1, math.ceil(pixel.numel() / SAMPLES_AT_ONCE)))  # splats per range
    for start in range(0, splats, step):
        count = min(step, splats - start)
        if count == splats:
            part = contributions
        else:
            pick = torch.nonzero((splat >= start) & (splat < start + count))[:, 0]
            part = (pixel[pick], splat[pick] - start, weight[pick])
        shift[start : start + count], best[start : start + count] = _mode_translations(part, fit_shape, field, count)
    centres = splat_centres(contributions, fit_shape, field.rows.shape, splats)
    voted = best > 0
    coordinates = (centres + torch.where(voted[:, None], shift, 0).to(centres.dtype)).float()
    return ViewVote(coordinates, torch.where(voted, best, torch.zeros_like(best)).float())


def _mode_translations(contributions, fit_shape, field: PaintingField, splats: int):  # -> shift [N, 2], weight [N]
    """Each splat's most-voted (row, column) translation from its proposal pixels into the painting, and the blend
    weight that voted for it (0: none of its pixels is covered by the field)."""
    pixel, splat, weight = contributions
    height, width = fit_shape
    rows_p, cols_p = field.rows.shape
    y = (pixel // width) * rows_p // height  # the fit pixel's proposal pixel
    x = (pixel % width) * cols_p // width
    flat = y * cols_p + x
    valid = field.valid.reshape(-1)[flat] & (weight > 0)
    source_rows, source_cols = field.source.shape[1:]
    span = source_cols + cols_p + 1
    codes = (source_rows + rows_p + 1) * span
    flat, y, x = flat[valid], y[valid], x[valid]
    dy = field.rows.reshape(-1)[flat] - y  # in [-rows_p, source_rows)
    dx = field.cols.reshape(-1)[flat] - x  # in [-cols_p, source_cols)
    del flat, y, x
    key = splat[valid] * codes + (dy + rows_p) * span + (dx + cols_p)
    del dy, dx
    keys, inverse = torch.unique(key, return_inverse=True)
    del key
    votes = torch.zeros(keys.numel(), dtype=torch.float64).index_add_(0, inverse, weight[valid].double())
    del inverse
    owner = keys // codes
    best = torch.zeros(splats, dtype=torch.float64).scatter_reduce_(0, owner, votes, "amax", include_self=True)
    winner = votes >= best[owner]
    # Ties go to the smallest key, so the vote does not depend on the order of the pixels.
    chosen = torch.full((splats,), torch.iinfo(torch.long).max, dtype=torch.long)
    chosen.scatter_reduce_(0, owner[winner], keys[winner], "amin", include_self=True)
    code = torch.where(best > 0, chosen % codes, torch.zeros_like(chosen))
    return torch.stack([code // span - rows_p, code % span - cols_p], 1), best


def splat_centres(
    contributions: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    fit_shape: tuple[int, int],
    size,
    splats: int,
    only: torch.Tensor | None = None,  # [N] bool: the splats to find (None: all)
) -> torch.Tensor:  # -> [N, 2] float64 (row, column) in pixels of ``size`` (H, W); 0 for splats the view does not draw
    """Each splat's centre as the view draws it: the blend-weighted mean of its pixels' positions (summed a slice of
    samples at a time)."""
    height, width = fit_shape
    total = torch.zeros(splats, 2, dtype=torch.float64)
    drawn = torch.zeros(splats, dtype=torch.float64)
    for start in range(0, contributions[0].numel(), SAMPLES_AT_ONCE):
        p, g, w = (t[start : start + SAMPLES_AT_ONCE] for t in contributions)
        if only is not None:
            keep = only[g]
            p, g, w = p[keep], g[keep], w[keep]
        w = w.double()
        total[:, 0].index_add_(0, g, ((p // width).double() + 0.5) * w)
        total[:, 1].index_add_(0, g, ((p % width).double() + 0.5) * w)
        drawn.index_add_(0, g, w)
    scale = torch.tensor([size[0] / height, size[1] / width], dtype=torch.float64)
    return total / drawn.clamp_min(1e-12)[:, None] * scale - 0.5


@dataclass
class CarriedMarks:
    """Each splat's painting coordinate, set by the view that owns it (``owner``, -1: none; :meth:`from_votes`)."""

    coordinates: torch.Tensor  # [N, 2] the painting source's (row, column) at the splat's centre
    owner: torch.Tensor  # [N] long

    @classmethod
    def from_votes(cls, votes: Sequence[ViewVote], share: float = OWNER_SHARE) -> CarriedMarks:
        """Each splat's owner is the first view (in the views' order) whose vote has at least ``share`` of the most
        weight any view's has: views take whole surfaces in turn, so neighbouring splats share an owner and its
        marks run on across them (the strongest view alone changes from splat to splat and speckles the marks)."""
        agreed = torch.stack([v.agreed for v in votes])  # [V, N]
        strongest = agreed.max(0).values
        eligible = (agreed >= share * strongest[None]) & (agreed > 0)
        owner = eligible.float().argmax(0)  # the first eligible view
        coordinates = torch.zeros_like(votes[0].coordinates)
        for v, vote in enumerate(votes):  # view by view: a [V, N, 2] stack of a 2M-splat scene is a quarter GB
            mine = owner == v
            coordinates[mine] = vote.coordinates[mine].to(coordinates.dtype)
        return cls(coordinates, torch.where(strongest > 0, owner, torch.full_like(owner, -1)))

    @property
    def carried(self) -> torch.Tensor:  # [N] bool
        return self.owner >= 0


@dataclass
class Surfaces:
    """Every view's camera, rendered depth (camera-space z at the camera's size, 0 where nothing) and painting field
    (at the proposal size): what painting a view through the views that see its points takes (:func:`paint_view`)."""

    cameras: Sequence[Camera]
    depths: Sequence[torch.Tensor]  # V x [H, W]
    fields: Sequence[PaintingField]


def first_views_fields(
    view: int,
    where: torch.Tensor,  # [P] the view's pixels (flat, at its camera's size)
    surfaces: Surfaces,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # -> rows [P], cols [P] into the source, found [P] bool
    """Where in the painting the first view (in the views' order) that sees each pixel's surface point shows it: the
    pixel unprojected by this view's depth, projected into each view in turn (``scene.warp``'s conventions), and that
    view's field at its proposal pixel there. A view sees the point where it is in front of it, in its image, the
    surface it draws there (depths within ``DEPTH_TOLERANCE``) and its field valid. Not found (rows and cols 0) where
    the pixel has no depth or no view sees its point."""
    camera = surfaces.cameras[view]
    f64 = torch.float64
    z = surfaces.depths[view].reshape(-1)[where].to(f64)
    u = (where % camera.width).to(f64) + 0.5
    v = (where // camera.width).to(f64) + 0.5
    points = torch.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], 1)
    rows, cols = torch.zeros_like(where), torch.zeros_like(where)
    found = torch.zeros_like(where, dtype=torch.bool)
    for other, (target, field) in enumerate(zip(surfaces.cameras, surfaces.fields)):
        pick = torch.nonzero(~found & (z > 0))[:, 0]
        if pick.numel() == 0:
            break
        transform = torch.as_tensor(target.world_to_camera @ camera.camera_to_world, dtype=f64)
        seen = points[pick] @ transform[:3, :3].T + transform[:3, 3]
        zo = seen[:, 2]
        z_safe = torch.where(zo > 0, zo, 1.0)
        # Clamped before the floor so that far off-screen points stay finite indices (they fail ``inside``).
        uo = (target.fx * seen[:, 0] / z_safe + target.cx).clamp(-1.0, target.width + 1.0)
        vo = (target.fy * seen[:, 1] / z_safe + target.cy).clamp(-1.0, target.height + 1.0)
        inside = (zo > 0) & (uo >= 0) & (uo < target.width) & (vo >= 0) & (vo < target.height)
        x = uo.floor().long().clamp(0, target.width - 1)
        y = vo.floor().long().clamp(0, target.height - 1)
        depth = surfaces.depths[other][y, x].to(f64)
        rows_p, cols_p = field.rows.shape
        yp, xp = y * rows_p // target.height, x * cols_p // target.width  # its proposal pixel, as vote_view's
        ok = inside & (depth > 0) & ((zo - depth).abs() <= DEPTH_TOLERANCE * zo) & field.valid[yp, xp]
        rows[pick] = torch.where(ok, field.rows[yp, xp], 0)
        cols[pick] = torch.where(ok, field.cols[yp, xp], 0)
        found[pick] = ok
    return rows, cols, found


def paint_view(
    contributions: tuple[torch.Tensor, torch.Tensor, torch.Tensor],  # the view's (fit pixel, splat, T alpha)
    fit_shape: tuple[int, int],
    size: tuple[int, int],  # (H, W) of the proposal, whose pixels the painting's coordinates are in
    marks: CarriedMarks,
    source: torch.Tensor,  # [3, 2 Hs, Ws] the painting and its mirror image (PaintingField.source)
    view: int | None = None,  # this view's index in ``surfaces``
    surfaces: Surfaces | None = None,  # None: each splat's translation alone
) -> tuple[torch.Tensor, torch.Tensor]:  # -> [3, H, W] at the fit size, [H, W] bool where it is painted
    """The painting as the splats carry it, seen from this view.

    With ``surfaces``, each pixel takes what the first view that sees its surface point shows there
    (:func:`first_views_fields`): that view's copy of the painting, carried on over the surface by depth. Elsewhere
    (and without ``surfaces``) it takes the painting at the coordinate of the splat drawn most there, moved by the
    pixel's place against that splat's centre in this view: a translation per splat, which in a view other than the
    splat's owner breaks the strokes at the splats' borders (foreshortening makes neighbouring splats' translations
    disagree), and the splats' owners change from splat to splat where views share a surface."""
    height, width = fit_shape

    def carried_samples():  # a slice of the samples at a time: a dense view holds several million
        for start in range(0, contributions[0].numel(), SAMPLES_AT_ONCE):
            p, g, w = (t[start : start + SAMPLES_AT_ONCE] for t in contributions)
            keep = marks.carried[g] & (w > 0)
            yield p[keep], g[keep], w[keep]

    strongest = torch.zeros(height * width)
    for p, _, w in carried_samples():
        strongest.scatter_reduce_(0, p, w, "amax", include_self=True)
    dominant = torch.full((height * width,), -1, dtype=torch.long)
    for p, g, w in carried_samples():
        top = w >= strongest[p]
        dominant.scatter_reduce_(0, p[top], g[top], "amax", include_self=True)  # ties: the larger index
    painted = dominant >= 0
    centres = splat_centres(contributions, fit_shape, size, marks.owner.numel(), marks.carried)
    where = torch.nonzero(painted)[:, 0]
    owner = dominant[where]
    scale = torch.tensor([size[0] / height, size[1] / width], dtype=torch.float64)
    position = (torch.stack([where // width, where % width], 1).double() + 0.5) * scale - 0.5
    coordinate = (marks.coordinates[owner].double() + position - centres[owner]).round().long()
    rows, cols = source.shape[1:]
    half = rows // 2
    lower = (marks.coordinates[owner, 0] >= half).long() * half  # stay in the half (painting or mirror) it is in
    row = torch.minimum(torch.maximum(coordinate[:, 0], lower), lower + half - 1)
    col = coordinate[:, 1].clamp(0, cols - 1)
    if surfaces is not None:
        carried_row, carried_col, found = first_views_fields(view, where, surfaces)
        row, col = torch.where(found, carried_row, row), torch.where(found, carried_col, col)
    image = torch.zeros(3, height * width)
    image[:, where] = source.reshape(3, -1)[:, row * cols + col]
    return image.reshape(3, height, width), painted.reshape(height, width)


def fine_band(image: torch.Tensor, coverage: torch.Tensor, sigma: float) -> torch.Tensor:
    """``image`` [3, H, W] minus its blur of ``sigma`` pixels over the covered pixels (``coverage`` [H, W] weights,
    normalised, so the background does not bleed into the silhouette's band)."""
    weight = coverage[None].clamp(0.0, 1.0)
    blurred = low_pass(image * weight, sigma) / low_pass(weight, sigma).clamp_min(1e-4)
    return image - blurred


def carried_targets(
    targets: Sequence[torch.Tensor],  # V x [3, H, W]
    painted: Sequence[torch.Tensor],  # V x [3, H, W]: each view's render of the splats' carried colours
    alphas: Sequence[torch.Tensor],  # V x [H, W]
    sigma: float,  # the stroke scale, in fit pixels
    masks: Sequence[torch.Tensor] | None = None,  # V x [H, W] bool: where ``painted`` holds marks (None: everywhere)
) -> list[torch.Tensor]:
    """Each view's target with its band finer than ``sigma`` replaced by the painted render's, on covered pixels:
    the coarse bands (forms, light, regions) stay the view's proposal's, the marks are the splats' own."""
    out = []
    for v, (target, render, alpha) in enumerate(zip(targets, painted, alphas)):
        covered = alpha > COVERED
        if masks is not None:
            covered = covered & masks[v]
        alpha = alpha * covered
        covered = covered.to(target.dtype)[None]
        swapped = target - fine_band(target, alpha, sigma) + fine_band(render, alpha, sigma)
        out.append((target + covered * (swapped - target)).clamp(0.0, 1.0))
    return out


def painting_band_deviation(source: torch.Tensor, sigma: float) -> float:
    """The standard deviation of the painting's band finer than ``sigma`` pixels of ``source`` [3, H, W]."""
    return float(fine_band(source.float(), torch.ones(source.shape[1:]), sigma).std())


def emphasis_gains(
    targets: Sequence[torch.Tensor],  # V x [3, H, W]: the stage's targets, their marks carried
    renders: Sequence[torch.Tensor],  # V x [3, H, W]: the fit's renders of them
    alphas: Sequence[torch.Tensor],  # V x [H, W]
    sigma: float,  # the band's width, in fit pixels (Plan.emphasis_width stroke scales)
    painting: float,  # the painting's deviation in the same band, at the views' scale (painting_band_deviation)
    most: float,  # the largest gain
) -> list[float]:
    """Per view, how much more of its band finer than ``sigma`` the target asks for in the second fit: k_v =
    1 / (rho_v max(tau_v, 1)) - 1 in [0, ``most``], rho_v the band's deviation in the fitted render over the target's
    (the share the splats drew), tau_v the target's over the painting's. What the splats lost comes back, up to the
    painting's own strength: a target whose foreshortened copies already hold more than the painting gets less."""
    gains = []
    for target, render, alpha in zip(targets, renders, alphas):
        covered = alpha > COVERED
        weight = alpha * covered
        wanted = fine_band(target, weight, sigma)[:, covered]
        if wanted.numel() < 2 or not painting > 0:
            gains.append(0.0)
            continue
        asked = float(wanted.std())
        drawn = float(fine_band(render, weight, sigma)[:, covered].std())
        if not (asked > 1e-6 and math.isfinite(asked) and math.isfinite(drawn)):  # no marks there to ask for
            gains.append(0.0)
            continue
        kept = drawn / asked * max(asked / painting, 1.0)
        gains.append(min(max(1.0 / max(kept, 1e-3) - 1.0, 0.0), most))
    return gains


def emphasized(
    targets: Sequence[torch.Tensor], alphas: Sequence[torch.Tensor], gains: Sequence[float], sigma: float
) -> list[torch.Tensor]:
    """Each target with its band finer than ``sigma`` (1 + gain) times as strong on covered pixels, in [0, 1]."""
    out = []
    for target, alpha, gain in zip(targets, alphas, gains):
        covered = (alpha > COVERED).to(target.dtype)
        out.append((target + gain * covered[None] * fine_band(target, alpha * covered, sigma)).clamp(0.0, 1.0))
    return out
