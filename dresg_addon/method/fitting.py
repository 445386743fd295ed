"""Multi-view fitting (Sec. 4.3): what is optimised, how each active view renders it, and one step of it.

- :func:`seen_gaussians`: the Gaussians the active views see; the rest is left out of fitting.
- :class:`FitState`: RGB colours and bounded geometry offsets of the seen Gaussians.
- :class:`ViewRenderer`: each active view's image of a state, colour-only (a cached sparse matrix per
  view, geometry frozen) or a full render with the offsets applied.
- :class:`BoundedColorFit`: with geometry frozen, the fit as the bounded least-squares problem it is,
  solved over all views at once (:mod:`.color_solve`).
- :class:`MultiViewFit`: one Adam step of the fit loss (Eq. 16) over all views, the colour gradients
  fused by PCGrad (Eqs. 17-20) and geometry gradients averaged, then colours clamped and offsets
  projected into their bounds (geometry on, or ``color_fit="adam"``).
- :func:`pixel_widths`, :func:`splat_footprint`: how wide the splats drawn in the active views are on screen (for the
  Stroke Size note and :func:`~.color_solve.fit_split`).
- :func:`fit_residual`: how far renders are from their targets (RMSE over covered pixels), for the log.
- :func:`result_scene`: the input scene with the fitted state written back.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from ..raster import ColorOnlyRenderer, RasterSettings, geometry_tensors, render
from ..raster.projection import projected_mean_variance, splat_covariances
from ..raster.sh import SH_C0, sh_basis
from ..scene.camera import Camera
from ..scene.gaussians import GaussianScene
from ..util.errors import CameraError, NumericalError
from . import losses, pcgrad
from .color_solve import (
    FIT_SOLVE,
    ColorSolveResult,
    ColorSolveSettings,
    LinearViews,
    ViewsInTurn,
    solve_colors,
    view_average_colors,
)
from .optim import GeometryBounds, check_finite_gradients, project_geometry_offsets_
from .proxies import ProxyColumns, proxy_columns


@dataclass
class FitState:
    """The optimised state: RGB colours and bounded geometry offsets of the fit's columns: the seen Gaussians, or with
    proxies (:mod:`.proxies`) one per seen Gaussian at least a pixel wide and one per cell of narrower ones."""

    seen: torch.Tensor  # [M] indices into the scene: each column's Gaussian (a cell's: its representative)
    colors: torch.Tensor  # [M, 3] RGB (render colour before the view-dependent SH rest)
    d_means: torch.Tensor | None  # [M, 3]
    d_log_scales: torch.Tensor | None
    d_quats: torch.Tensor | None
    # With proxies: (every seen Gaussian's index into the scene, its column); None: one column per seen Gaussian.
    members: tuple[torch.Tensor, torch.Tensor] | None = None

    @classmethod
    def start(
        cls, scene: GaussianScene, seen: torch.Tensor, geometry: bool, proxies: ProxyColumns | None = None
    ) -> FitState:
        """The scene's own colours (SH DC as RGB) and zero offsets (None with geometry frozen); a cell's colour is the
        mean of its members'."""
        base_colors = torch.from_numpy(scene.base_colors.astype(np.float32))[seen]
        members = None
        if proxies is not None and proxies.grouped:
            members = (seen, proxies.column)
            sums = torch.zeros(proxies.count, 3, dtype=torch.float64).index_add_(
                0, proxies.column, base_colors.double()
            )
            counts = torch.bincount(proxies.column, minlength=proxies.count).clamp_min(1)
            base_colors, seen = (sums / counts[:, None]).float(), seen[proxies.representative]

        def offsets(width):
            return torch.zeros(seen.numel(), width, requires_grad=True) if geometry else None

        return cls(seen, base_colors.clone().requires_grad_(True), offsets(3), offsets(3), offsets(4), members)

    @property
    def splat_count(self) -> int:
        """How many of the scene's Gaussians the fit colours."""
        return int(self.seen.numel() if self.members is None else self.members[0].numel())

    def splat_colors(self) -> tuple[np.ndarray, np.ndarray]:
        """(scene indices [K], their colours [K, 3]) of every Gaussian the fit colours: a cell's members all take
        its colour."""
        colors = self.colors.detach()
        if self.members is None:
            return self.seen.numpy(), colors.numpy()
        index, column = self.members
        return index.numpy(), colors[column].numpy()

    def params(self):
        return [p for p in (self.colors, self.d_means, self.d_log_scales, self.d_quats) if p is not None]

    def geometry(self):
        return [p for p in (self.d_means, self.d_log_scales, self.d_quats) if p is not None]


def seen_gaussians(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    settings: RasterSettings,
    geometry: bool,
    each_view: Callable[[int], None] | None = None,  # (views rendered so far), after each view: progress
    rendered: list[ColorOnlyRenderer] | None = None,  # the cameras' colour-only renderers, if made already
) -> tuple[torch.Tensor, list[ColorOnlyRenderer] | None]:
    """The sorted indices [M] of the Gaussians the cameras see, and with geometry frozen the cameras'
    full-scene colour-only renderers (which found them, so the fit needs no second rasterization)."""
    means, quats, log_scales, logits = geometry_tensors(scene)
    fast = None
    if rendered is not None and not geometry:
        fast = list(rendered)
        if each_view is not None:
            each_view(len(fast))
        seen_mask = torch.stack([f.seen for f in fast]).any(0)
    elif geometry:
        seen_mask = torch.zeros(len(scene), dtype=torch.bool)
        for done, camera in enumerate(cameras, 1):
            with torch.no_grad():
                vis = render(
                    means, quats, log_scales, logits, torch.zeros_like(means), camera, settings, visibility="all"
                )
            seen_mask |= vis.visibility > 0
            if each_view is not None:
                each_view(done)
    else:
        fast = []
        covariances = splat_covariances(quats, log_scales, torch.float64)
        for done, camera in enumerate(cameras, 1):
            fast.append(ColorOnlyRenderer(means, quats, log_scales, logits, camera, settings, covariances=covariances))
            if each_view is not None:
                each_view(done)
        seen_mask = torch.stack([f.seen for f in fast]).any(0)
    seen = torch.nonzero(seen_mask).squeeze(-1)
    if seen.numel() == 0:
        raise CameraError("the active cameras see none of the scene's Gaussians")
    return seen, fast


class ViewRenderer:
    """Renders the active views of the seen Gaussians, colour-only (cached) or with geometry."""

    def __init__(
        self,
        scene: GaussianScene,
        cameras: list[Camera],
        seen: torch.Tensor,  # [M] sorted indices of the Gaussians the active views see
        settings: RasterSettings,
        keep_sh_rest: bool,  # render the scene's view-dependent SH rest bands on top of the fitted colour
        fast: list[ColorOnlyRenderer] | None,  # full-scene colour-only renderers (geometry frozen), else None
        selected: bool = False,  # ``seen`` is a selection: the other seen Gaussians keep their (DC) colours
        proxy_sigma: float = 0.0,  # colour-only: splats narrower than this (px) share a colour per cell (proxies.py)
    ):
        means, quats, log_scales, logits = geometry_tensors(scene)
        self.proxies: ProxyColumns | None = None
        self.cameras = cameras
        self.settings = settings
        # View-dependent colour of kept SH rest bands: a constant per-view offset on the RGB colour (no proxies then).
        self.offsets: list[torch.Tensor | None] = [None] * len(cameras)
        if scene.sh_rest is not None and keep_sh_rest:
            rest = torch.from_numpy(scene.sh_rest[seen.numpy()]).float()
            degree = scene.sh_degree
            for v, camera in enumerate(cameras):
                dirs = means[seen] - torch.as_tensor(camera.center, dtype=torch.float32)
                dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
                basis = sh_basis(dirs, degree)[:, 1:]  # [M, K]
                self.offsets[v] = (basis[:, :, None] * rest).sum(1)
        # Colour-only: the full-scene renderers that found the seen set, narrowed to it (no second rasterization).
        fixed = torch.from_numpy(scene.base_colors).float() if selected else None
        self.fast = None if fast is None else [f.restrict(seen, fixed) for f in fast]
        self.base_images: list[torch.Tensor] | None = None
        if self.fast is not None and proxy_sigma > 0 and all(o is None for o in self.offsets):
            proxies = proxy_columns(means[seen], log_scales[seen], cameras, [f.seen for f in self.fast], proxy_sigma)
            if proxies.grouped:
                # The scene as it is, rendered before its cells share colours: the runs' base renders stay exact.
                colors = torch.from_numpy(scene.base_colors.astype(np.float32))[seen]
                self.base_images = [f(colors).permute(2, 0, 1) for f in self.fast]
                self.fast = [f.merge_columns(proxies.column, proxies.count) for f in self.fast]
                self.proxies, seen = proxies, seen[proxies.representative]
        self.means, self.quats = means[seen], quats[seen]
        self.log_scales, self.logits = log_scales[seen], logits[seen]

    def __len__(self) -> int:
        return len(self.cameras)

    def __call__(self, v: int, fit: FitState) -> torch.Tensor:  # -> [3, H, W]
        colors = fit.colors if self.offsets[v] is None else fit.colors + self.offsets[v]
        colors = colors.clamp_min(0.0)
        if self.fast is not None:
            rgb = self.fast[v](colors)
        else:
            quats = self.quats + fit.d_quats
            rgb = render(
                self.means + fit.d_means,
                quats,
                self.log_scales + fit.d_log_scales,
                self.logits,
                colors,
                self.cameras[v],
                self.settings,
            ).rgb
        return rgb.permute(2, 0, 1)

    def alpha(self, v: int, fit: FitState) -> torch.Tensor:  # -> [H, W]
        """The view's coverage (1 - final transmittance), with the current geometry offsets."""
        if self.fast is not None:
            return self.fast[v].alpha
        return render(
            self.means + fit.d_means,
            self.quats + fit.d_quats,
            self.log_scales + fit.d_log_scales,
            self.logits,
            torch.zeros_like(self.means),
            self.cameras[v],
            self.settings,
        ).alpha

    def all(self, fit: FitState) -> list[torch.Tensor]:  # -> V x [3, H, W]
        """Every view's current image, without gradients."""
        with torch.no_grad():
            return [self(v, fit).detach() for v in range(len(self))]

    def base(self, fit: FitState) -> list[torch.Tensor]:  # -> V x [3, H, W]
        """Every view's image of the scene as it is (``fit`` at its start): exact with proxies too."""
        return [image.clone() for image in self.base_images] if self.base_images is not None else self.all(fit)

    def depth(self, v: int, fit: FitState) -> torch.Tensor:  # -> [H, W]
        """The view's rendered depth (0 where nothing is seen), with the current geometry offsets."""
        if self.fast is not None:
            return self.fast[v].depth
        with torch.no_grad():
            return render(
                self.means + fit.d_means,
                self.quats + fit.d_quats,
                self.log_scales + fit.d_log_scales,
                self.logits,
                torch.zeros_like(self.means),
                self.cameras[v],
                self.settings,
            ).depth

    def linear_views(self, min_weight: float = 0.0) -> LinearViews:
        """Colour-only: each view as W_v c + b_v, b_v the background plus W_v times the kept SH offset (the
        render's clamp of c + offset at 0 is left out: kept SH offsets are small). ``min_weight`` leaves out
        samples fainter than that (``ColorOnlyRenderer.linear_map``)."""
        if self.fast is None:
            raise ValueError("linear views need frozen geometry (the colour-only path)")
        maps, constants = [f.linear_map(min_weight) for f in self.fast], []
        for f, m, offset in zip(self.fast, maps, self.offsets):
            constant = f.background.reshape(-1, 3)
            constants.append(constant if offset is None else constant + m.matvec(offset))
        return LinearViews(maps, constants)


def pixel_widths(renderer: ViewRenderer) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per active view, ([P] the blending-weighted screen sigma of the splats drawn at each pixel, in pixels at the
    fit size; [P] their summed blending weight, the pixel's coverage), P = H x W, from the colour-only path's
    cached weights (nothing is rendered again). Requires that path (geometry frozen).

    A splat's sigma is sqrt of the mean of its 2D covariance's two eigenvalues, the 0.3 px^2 low-pass included
    (:func:`~dresg_addon.raster.projection.projected_mean_variance`): its RMS width, the sigma itself for a round
    splat, and for a needle between its width and its length, as a mark across it or along it is blurred. A pixel's
    value is sum_i w_i sigma_i / sum_i w_i over its samples (w = T alpha); 0 where nothing is drawn.
    """
    if renderer.fast is None:
        raise ValueError("pixel widths need frozen geometry (the colour-only path)")
    covariances = splat_covariances(renderer.quats, renderer.log_scales)
    out = []
    with torch.no_grad():
        for view, camera in zip(renderer.fast, renderer.cameras):
            drawn = torch.nonzero(view.seen).squeeze(-1)
            columns = torch.zeros(view.seen.numel(), 2)  # sigma, 1
            columns[:, 1] = 1.0
            variance = projected_mean_variance(
                renderer.means[drawn],
                covariances[drawn],
                torch.as_tensor(camera.world_to_camera),
                camera.fx,
                camera.fy,
                camera.width,
                camera.height,
            )
            columns[drawn, 0] = variance.clamp_min(0.0).sqrt()
            blended = view.map.matvec(columns)  # [P, 2]: sum_i w_i sigma_i, sum_i w_i
            weight = blended[:, 1]
            out.append((torch.where(weight > 0, blended[:, 0] / weight.clamp_min(1e-12), 0.0), weight))
    return out


def splat_footprint(renderer: ViewRenderer, min_alpha: float = 0.5) -> float | None:
    """The median, over the covered pixels (alpha > ``min_alpha``) of the active views, of :func:`pixel_widths`:
    how wide the splats drawn there are on screen, in pixels at the fit size. None without the colour-only path
    (geometry on) or without covered pixels."""
    if renderer.fast is None:
        return None
    values = []
    for view, (width, weight) in zip(renderer.fast, pixel_widths(renderer)):
        covered = (view.alpha.reshape(-1) > min_alpha) & (weight > 0)
        values.append(width[covered])
    values = torch.cat(values)
    return float(values.median()) if values.numel() else None


def feature_extractor(weight: float, dino_path: str, say: Callable[[str], None], device="cpu"):
    """The fit loss's feature term: DINO (on ``device``) when local weights are given, else the weight-free
    patch features."""
    if weight <= 0:
        return None
    if dino_path:
        from .dino import DinoFeatures

        say(f"feature loss: DINO from {dino_path}")
        return DinoFeatures(dino_path, device)
    say("feature loss: weight-free patch features (no DINO weights given)")
    return losses.patch_feature_maps


class MultiViewFit:
    """Eq. 16 over all active views, one Adam step at a time (Eqs. 17-20 fuse the colour gradients)."""

    def __init__(
        self,
        renderer: ViewRenderer,
        fit: FitState,
        optimizer: torch.optim.Optimizer,
        bounds: GeometryBounds,  # in scene units
        weights: losses.FitLossWeights,
        features,  # images [B, 3, H, W] -> feature maps, or None
        base_renders: Sequence[torch.Tensor],  # V x [3, H, W]: what the feature term compares with
        project_gradients: bool,  # PCGrad over the views' colour gradients (False: their mean)
        pcgrad_eps: float = pcgrad.PCGRAD_EPS,
    ):
        self.renderer, self.fit, self.optimizer, self.bounds = renderer, fit, optimizer, bounds
        self.weights, self.features = weights, features
        self.project_gradients, self.pcgrad_eps = project_gradients, pcgrad_eps
        with torch.no_grad():
            self.base_features = [features(r[None]).detach() for r in base_renders] if features else None
        self.covered: list[torch.Tensor] | None = None  # V x [H, W] bool: the pixels covered_rmse counts
        self.covered_rmse = float("nan")  # RMSE over the covered pixels of the last step's renders (progress)

    def step(self, targets: Sequence[torch.Tensor], where: str) -> float:  # targets: V x [3, H, W]
        """One step toward ``targets``; the mean fit loss over the views. ``where`` names the step in errors."""
        fit, views = self.fit, len(self.renderer)
        self.optimizer.zero_grad(set_to_none=True)
        color_grads, geometry_grads, total = [], [[] for _ in fit.geometry()], 0.0
        squares, count = 0.0, 0
        for v in range(views):
            image = self.renderer(v, fit)
            if self.covered is not None:
                with torch.no_grad():
                    squares += float(
                        (image.detach().double() - targets[v].double()).square().sum(0)[self.covered[v]].sum()
                    )
                    count += 3 * int(self.covered[v].sum())
            render_features = self.features(image[None]) if self.features else None
            base_features = self.base_features[v] if self.features else None
            loss = losses.fit_loss(image, targets[v], base_features, render_features, self.weights).total
            grads = torch.autograd.grad(loss, fit.params(), allow_unused=True)
            color_grads.append(grads[0] if grads[0] is not None else torch.zeros_like(fit.colors))
            for slot, p, g in zip(geometry_grads, fit.geometry(), grads[1:]):
                slot.append(g if g is not None else torch.zeros_like(p))
            total += float(loss.detach())
        if not math.isfinite(total):
            raise NumericalError(f"the fit loss became non-finite at {where}, so the run stopped")
        self.covered_rmse = math.sqrt(squares / count) if count else float("nan")
        stacked = torch.stack(color_grads)
        fuse = self.project_gradients and views > 1
        fit.colors.grad = pcgrad.pcgrad_fuse(stacked, self.pcgrad_eps).gradient if fuse else stacked.mean(0)
        for p, slot in zip(fit.geometry(), geometry_grads):
            p.grad = torch.stack(slot).mean(0)  # geometry gradients are averaged over views
        check_finite_gradients(fit.params())
        self.optimizer.step()
        with torch.no_grad():
            fit.colors.clamp_(0.0, 1.0)
            project_geometry_offsets_(fit.d_means, fit.d_log_scales, fit.d_quats, self.bounds)
        return total / views


# Samples fainter than this are left out of the solve's products (the render keeps them): 39% of the bonsai's
# samples carrying 0.5% of its weight, so each conjugate-gradient iteration costs ~40% less.
SOLVE_MIN_WEIGHT = 1e-3


class BoundedColorFit:
    """Eq. 16's squared error over all active views with geometry frozen, solved to its bounded optimum
    (:func:`.color_solve.solve_colors`) instead of a fixed number of gradient steps."""

    def __init__(
        self,
        renderer: ViewRenderer,
        fit: FitState,
        medium,  # method/medium.Medium: how each splat's colour is picked from the views, and recoloured
        settings: ColorSolveSettings = FIT_SOLVE,
    ):
        self.views = renderer.linear_views(SOLVE_MIN_WEIGHT)
        self.fit, self.medium, self.settings = fit, medium, settings

    def solve(
        self,
        targets: Sequence[torch.Tensor],
        each_round=None,
        start: torch.Tensor | None = None,
        each_view=None,
        painted: ViewsInTurn | None = None,
    ) -> ColorSolveResult:  # V x [3, H, W]
        """Solve from ``start`` (default: each splat's view average of the targets; the anchor holds to it), pick each
        splat's colour as the medium does (``painted``: the views' painting of these targets already made), and write
        the colours into the fit state."""
        if start is None:
            start = view_average_colors(self.views, targets, self.fit.colors.detach())
        start = start.detach()

        def pick(views, flat, joint):
            return self.medium.pick_colors(views, flat, joint, self.settings, each_view, painted)

        result = solve_colors(self.views, targets, start, self.settings, each_round, pick)
        result.colors = self.medium.recolor(result.colors)
        with torch.no_grad():
            self.fit.colors.copy_(result.colors)
        return result


def fit_residual(
    renders: Sequence[torch.Tensor],  # V x [3, H, W]
    targets: Sequence[torch.Tensor],  # V x [3, H, W]
    alphas: Sequence[torch.Tensor],  # V x [H, W]
    covered: float = 0.5,
) -> float:
    """RMSE between renders and targets over the covered pixels (alpha > ``covered``) of all views together;
    0 when no pixel is covered."""
    total, count = 0.0, 0
    for image, target, alpha in zip(renders, targets, alphas):
        mask = alpha > covered
        total += float((image.double() - target.double()).square().sum(0)[mask].sum())
        count += 3 * int(mask.sum())
    return math.sqrt(total / count) if count else 0.0


def result_scene(scene: GaussianScene, fit: FitState, zero_sh_rest: bool, selected: bool = False) -> GaussianScene:
    """The input scene with the fitted colours in the DC term (and offsets applied); never modifies ``scene``.

    ``zero_sh_rest`` drops the view-dependent bands of every splat, or with ``selected`` (a masked run) only
    of the fitted ones, so that every other splat stays exactly as it was."""
    painted, colors = fit.splat_colors()
    sh_dc = scene.sh_dc.copy()
    sh_dc[painted] = ((colors.astype(np.float64) - 0.5) / SH_C0).astype(np.float32)
    out = replace(scene, sh_dc=sh_dc)
    if scene.sh_rest is not None and zero_sh_rest:
        sh_rest = np.zeros_like(scene.sh_rest)
        if selected:
            sh_rest = scene.sh_rest.copy()
            sh_rest[painted] = 0.0
        out = replace(out, sh_rest=sh_rest)
    if fit.d_means is not None:
        seen = fit.seen.numpy()
        means, log_scales, quats = scene.means.copy(), scene.log_scales.copy(), scene.quats.copy()
        means[seen] += fit.d_means.detach().numpy()
        log_scales[seen] += fit.d_log_scales.detach().numpy()
        quats[seen] += fit.d_quats.detach().numpy()
        out = replace(out, means=means, log_scales=log_scales, quats=quats)
    return out
