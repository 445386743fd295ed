"""DReSG end to end: Algorithm 1 of the paper as a short loop of named steps.

:func:`stylize` is the library call (the CLI and the Blender operators are thin layers over it); its
body is the algorithm, one line per step, each a method of :class:`Stylization` that cites its section.
Progress, cancel, checkpoints and the log hang off the run (:mod:`.bookkeeping`) between the steps.
Nothing here imports bpy.

What a scene does not need is left out:
- Gaussians that no active view sees are neither rasterized nor optimised during fitting (the log says
  how many); their colours stay as they were.
- With geometry offsets off (the default off the ``paper`` preset), fitting takes the colour-only fast
  path: each view's image is a cached sparse matrix times the colours, and the fit is solved as the
  bounded least-squares problem it then is, over all views at once, instead of taken in Adam steps.
- SH rest bands are never allocated for a scene without them; with them, the stylized colour goes to the
  DC term and the rest is zeroed or kept (``StylizeConfig.sh_rest``).
- diffusers is imported only for the ``sd15`` backend; with one active view there is no projection.
- The stages stop early once the style distance stops improving, or once a stage's fit no longer moves
  the scene (``Plan.early_stop``), judged only on stages that propose at full detail
  (``ProposalBackend.full_detail``).

What differs by medium (paint, ink) is the medium's (:mod:`.medium`), and by proposal backend the backend's
registry entry's (:mod:`.backends`): the loop names neither.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from ..scene.camera import Camera, view_name
from ..scene.gaussians import GaussianScene, blend_colors
from ..util.errors import CameraError, ConfigError, NumericalError
from ..util.machine import peak_rss_mb, release_free_memory
from . import views as view_selection
from .backends import backend, light_note
from .bookkeeping import (
    BEST_VIEWS_STAGE_FIT_COST,
    FIRST_FIT_COST,
    Progress,
    RunHooks,
    RunRecord,
    StageUpdate,
    prior_costs,
    run_id,
)
from .color_solve import ViewsInTurn, covered_rmse
from .color_transfer import covariance_color_transform, coverage_weight, luminance
from .config import Plan, StylizeConfig, check_run_settings
from .fitting import (
    BoundedColorFit,
    FitState,
    MultiViewFit,
    ViewRenderer,
    feature_extractor,
    fit_residual,
    result_scene,
    seen_gaussians,
    splat_footprint,
)
from .losses import FitLossWeights
from .marks import (
    CarriedMarks,
    Surfaces,
    carried_targets,
    emphasis_gains,
    emphasized,
    paint_view,
    painting_band_deviation,
    vote_view,
)
from .medium import medium_for
from .optim import FitOptimizerSettings, make_fit_optimizer, scene_extent
from .refine import split_wide_splats
from .schedule import Stage, stage_gammas, stage_timesteps
from .style_distance import sliced_wasserstein_patches
from .targets import proposal_residual, residual_target
from .views import ActiveViews

EARLY_STOP_WINDOW = 2  # stages over which the style distance must improve (one stage may pause, e.g. a coarse one)
COVERED = 0.5  # alpha above which a pixel counts as covered (fit_residual's)
STILL_SCENE = 0.005  # RMSE a stage's fit must move the covered pixels by (about one 8-bit level in 0.8) to count


@dataclass
class StylizeResult:
    scene: GaussianScene
    selection: ActiveViews
    log: list[dict]
    seconds: float
    stylized: int = 0  # splats the run fitted: the selected (or all) splats that an active view sees
    # [M] the input splat each output splat comes from, when splats were split (refine.py): i for i < the input's
    # count, the children after them; None when the scene kept its splats
    parents: np.ndarray | None = None


def stylize(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    style_rgb: np.ndarray,  # [H, W, 3] float32 in [0, 1]
    config: StylizeConfig | None = None,
    *,
    views: Sequence[int] | None = None,
    content_images: dict[int, np.ndarray] | None = None,  # camera index -> photo [H, W, 3]
    progress: Callable[[Progress], None] | None = None,
    on_stage: Callable[[StageUpdate], None] | None = None,
    cancel: threading.Event | None = None,
    checkpoint_dir: str | os.PathLike | None = None,
    log_path: str | os.PathLike | None = None,
    save_views_dir: str | os.PathLike | None = None,
    messages: Callable[[str], None] | None = None,
    strength: float = 1.0,
    mask: np.ndarray | None = None,  # [N] bool, or the indices of the splats to stylize
    device: str | torch.device | None = None,  # where the networks run (sd15, DINO); None: sd15's GPU, DINO's CPU
    dino_path: str = "",  # local DINO weights for the Adam fit's feature term (geometry on); empty: patch features
    plan: Plan | None = None,  # the method's schedule; None: the preset's (benchmarks and tests run variants with it)
    near: float | None = None,  # the rasterizer's near plane, for a scene in tiny units (None: the rasterizer's)
) -> StylizeResult:
    """Algorithm 1 of the paper, returning the stylized scene (the input is never modified).

    ``views`` fixes the active cameras (indices into ``cameras``); otherwise they are chosen by coverage.
    ``strength`` in [0, 1] blends the result's colours with the input's (1: fully stylized); it is applied
    to the result only, so a run resumed at another strength reuses its checkpoint. ``mask`` stylizes a
    selection: only those splats are optimised (and count for view selection), every other one comes back
    bit-identical. ``device`` is where the networks run (the sd15 proposals, DINO features); the rasterizer
    and the colour fit run on the CPU. Deterministic for ``config.seed`` on the CPU; no global random state is
    touched.
    """
    if not (math.isfinite(strength) and 0.0 <= strength <= 1.0):
        raise ConfigError(f"invalid setting: strength must be in [0, 1] (got {strength})")
    config = config or StylizeConfig()
    mask = selection_mask(mask, len(scene), config)
    hooks = RunHooks(progress, on_stage, cancel, messages)
    record = RunRecord(checkpoint_dir, log_path, save_views_dir)
    run = Stylization(scene, style_rgb, config, hooks, record, mask, device, dino_path, plan, near)
    # Between steps, the memory the allocator keeps from the last one's temporaries goes back to the system
    # (release_free_memory: 4.3 -> 2.5 GB resident over a 2.18M-splat run's stages).
    run.select_views(cameras, views)  # Sec. 4.3, Eqs. 13-15: active views by capped coverage
    release_free_memory()
    run.refine()  # splats as fine as the marks: the ones the views draw wider are split, the render kept
    run.prepare(content_images)  # seen Gaussians, base renders, content views, proposal states
    release_free_memory()
    for stage in run.remaining_stages():  # Sec. 4.2: the DDIM states in stages, gamma_n per stage
        run.propose(stage)  # Sec. 4.1: an attention-guided proposal per view
        targets = run.residual_targets(stage)  # Eqs. 10-12: render-relative residual targets
        release_free_memory()
        run.fit(stage, targets)  # Eqs. 16-20: multi-view fitting, PCGrad-fused colour gradients
        release_free_memory()
        run.feed_back(stage)  # Algorithm 1, last line: re-encode the fitted renders
        run.emphasize_marks(stage)  # the last stage fitted again, asking for the marks the splats drew weaker
        if run.finish_stage(stage):  # log, checkpoint, live update; True: the early stop
            break
    run.post_stage()  # covariance colour transfer toward the style, then fitting to it
    result = run.result()
    if strength < 1.0:  # the split scene's children carry their parent's colours: the blend is exact for them too
        result.scene = blend_colors(run.scene, result.scene, strength)
    return result


def selection_mask(mask, count: int, config: StylizeConfig) -> np.ndarray | None:
    """A [count] bool array from a bool mask or an index list (None stays None); ConfigError when it cannot be,
    or when the run would move geometry (the selection's neighbours are drawn with fixed colours only)."""
    if mask is None:
        return None
    if config.optimize_geometry:
        raise ConfigError("stylizing a selection needs geometry frozen (a colour-only preset, or --no-geometry)")
    array = np.asarray(mask)
    if array.dtype == bool:
        if array.shape != (count,):
            raise ConfigError(f"the selection mask has {array.size} entries for {count} splats")
        selected = array.copy()
    elif np.issubdtype(array.dtype, np.integer) and array.ndim == 1:
        if array.size and (array.min() < 0 or array.max() >= count):
            raise ConfigError(f"the selection's indices must be in [0, {count}) (got {array.min()}..{array.max()})")
        selected = np.zeros(count, bool)
        selected[array] = True
    else:
        raise ConfigError("the selection must be a bool mask or a list of splat indices")
    if not selected.any():
        raise ConfigError("the selection is empty: select some splats to stylize")
    return selected


def stage_improvement(distances: Sequence[float], window: int = EARLY_STOP_WINDOW) -> float | None:
    """Relative drop of the style distance over the last ``window`` stages, (d[-1 - window] - d[-1]) / d[-1 - window].

    ``distances[0]`` is the base renders'; None while fewer than ``window`` stages have run, or when the
    earlier distance is 0 (nothing left to improve).
    """
    if len(distances) <= window or distances[-1 - window] <= 0:
        return None
    return (distances[-1 - window] - distances[-1]) / distances[-1 - window]


def scene_brightness(images: Sequence[torch.Tensor], coverages: Sequence[torch.Tensor]) -> float:
    """Mean Rec. 709 luminance of the covered pixels (coverage > COVERED) of ``images`` [3, H, W] together; 1 when
    none is covered (nothing to hold the light of)."""
    total, count = 0.0, 0
    for image, coverage in zip(images, coverages):
        covered = coverage > COVERED
        total += float(luminance(image[None])[0, 0][covered].double().sum())
        count += int(covered.sum())
    return total / count if count else 1.0


def style_size(config: StylizeConfig) -> tuple[int, int]:
    """(height, width) the painting is resampled to: the proposal size x Stroke Size, each side rounded."""
    return (
        max(1, round(config.stroke_size * config.proposal_height)),
        max(1, round(config.stroke_size * config.proposal_width)),
    )


def _resize(image: torch.Tensor, height: int, width: int) -> torch.Tensor:  # [3, H, W]
    if image.shape[-2:] == (height, width):
        return image
    return torch.nn.functional.interpolate(
        image[None], size=(height, width), mode="bilinear", antialias=True, align_corners=False
    )[0].clamp(0, 1)


def _checked_style(style_rgb) -> np.ndarray:  # -> [H, W, 3] float32 in [0, 1]
    style_rgb = np.asarray(style_rgb, dtype=np.float32)
    if style_rgb.ndim != 3 or style_rgb.shape[2] != 3 or not np.isfinite(style_rgb).all():
        raise ConfigError(f"style image must be a finite [H, W, 3] array, got shape {style_rgb.shape}")
    return np.clip(style_rgb, 0.0, 1.0)  # HDR styles (EXR) would give targets outside displayable colours


@dataclass
class _StageWork:
    """What one stage produced, for its log entry and its live update."""

    started: float
    energies: list[float] = field(default_factory=list)
    proposal_seconds: float = 0.0
    images: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    losses: list[float] = field(default_factory=list)
    renders: list = field(default_factory=list)  # the views before the fit, then after it
    targets: list = field(default_factory=list)  # what the fit was asked for (the last stage's second fit asks again)
    painted: ViewsInTurn | None = None  # ink: the views' painting in turn of the stage's proposals
    fields: list = field(default_factory=list)  # where in the painting each view's proposal comes from (marks.py)
    closure: dict = field(default_factory=dict)  # target gap, fit residual, optimum, share closed, movement
    fitted_seconds: float = 0.0
    distance: float = 0.0
    stop_reason: str = ""


class Stylization:
    """One run of Algorithm 1: the state that flows from step to step, and one method per step."""

    def __init__(
        self,
        scene: GaussianScene,
        style_rgb,
        config: StylizeConfig,
        hooks: RunHooks,
        record: RunRecord,
        mask: np.ndarray | None = None,  # [N] bool: the selection to stylize (None: every splat)
        device: str | torch.device | None = None,  # where the networks run, as stylize() says
        dino_path: str = "",  # as stylize() says
        plan: Plan | None = None,  # as stylize() says
        near: float | None = None,  # as stylize() says
    ):
        self.scene, self.hooks, self.record, self.mask = scene, hooks, record, mask
        self.device, self.dino_path = device, dino_path
        self.style_rgb = _checked_style(style_rgb)
        self.entry = backend(config.proposal)
        self.medium = medium_for(config, self.style_rgb, hooks.note)
        self.config, self.plan = config, plan = self.medium.settle(
            config, plan or config.plan(), self.entry, hooks.note
        )
        check_run_settings(config, plan)
        self.raster = config.raster(near)
        self.size = (config.proposal_height, config.proposal_width)
        self.stages = stage_timesteps(config.stages, plan.updates_per_stage)
        self.gammas = stage_gammas(plan.schedule, self.stages)
        hooks.plan(len(self.stages), self.post_steps() > 0, prior_costs(config, plan, self.entry))

    # --- Before the stages ---------------------------------------------------------------------------------

    def select_views(self, cameras: Sequence[Camera], views: Sequence[int] | None) -> None:
        """Sec. 4.3: the active views by capped coverage (Eqs. 13-15), or the given ones."""
        hooks, nan = self.hooks, float("nan")
        self.rendered: list | None = None  # the active views' colour-only renderers, when the selection made them
        self.blend_weights: list | None = None  # the active views' blend weights, when the selection kept them
        if views is None:
            hooks.model.set_counts(cameras=len(cameras), views=min(len(cameras), self.config.max_views or len(cameras)))

            def each_camera(done: int, total: int) -> None:
                hooks.report(0, done, total, "select", nan, f"selecting views: {done}/{total} cameras rendered")

            each_camera(0, len(cameras))
            # When every camera may be active, the fit's colour-only maps come from the selection's renders (the
            # most the fit holds anyway); with more cameras than views, the chosen ones are rendered again. A run
            # that splits keeps the views' blend weights instead: the split measures in them and makes maps stale
            # (the 2M-splat bonsai's selection: 48 s and 2.3 GB, against 55-62 s and 3.7 GB with the maps).
            cap = self.config.max_views or len(cameras)
            keep = not self.config.optimize_geometry and len(cameras) <= cap
            renderers = [] if keep and not self.splits() else None
            weights = [] if self.splits() else None
            self.selection = view_selection.select_active_views(
                self.scene,
                cameras,
                self.config,
                progress=each_camera,
                cancel=hooks.cancel,
                mask=self.mask,
                near=self.raster.near,
                renderers=renderers,
                blend_weights=weights,
            )
            if renderers is not None:
                self.rendered = [renderers[v] for v in self.selection.indices]
            if weights is not None:
                self.blend_weights = [weights[v] for v in self.selection.indices]
        else:
            hooks.model.set_counts(cameras=0, views=len(views))
            bad = [v for v in views if not 0 <= v < len(cameras)]
            if bad or not views:
                raise CameraError(f"active views {list(views)} do not index the {len(cameras)} cameras")
            self.selection = ActiveViews(list(views), [], [], "given")
        self.cameras = [cameras[v] for v in self.selection.indices]
        self.names = [view_name(cameras[v], v) for v in self.selection.indices]
        hooks.model.set_counts(views=len(self.cameras))
        how = "as given" if views is not None else f"picked by coverage: {self.selection.reason}"
        self.hooks.note(f"active views: {len(self.cameras)} of {len(cameras)} cameras ({how})")
        self.hooks.check_cancel()

    def refine(self) -> None:
        """Splats as fine as the marks (:func:`~.refine.split_wide_splats`): those the active views draw wider than
        the backend's strokes are split into children that render as they did, adding at most
        :meth:`split_budget` splats; the selection and the input's colours carry over to the children."""
        self.parents = None
        drawn, self.blend_weights = self.blend_weights, None
        if not self.splits():
            return
        cap = self.split_budget()
        self.hooks.report(0, 0, 1, "select", float("nan"), "finding the splats wider than the marks")
        marks = self.entry.stroke_sigma(self.config.stroke_size) * self.fit_scale() * self.plan.split_width
        # drawn: the selection's blend weights; None when the views were given (the split renders its own)
        split = split_wide_splats(self.scene, self.cameras, marks, cap, self.raster, self.mask, drawn)
        self.hooks.check_cancel()
        if split.added == 0:
            return
        self.hooks.note(split.summary)
        self.scene, self.parents = split.scene, split.parent_index
        if self.mask is not None:  # a selected splat's children are selected
            self.mask = self.mask[self.parents]

    def splits(self) -> bool:
        """Whether the run splits the splats wider than the marks (:meth:`refine`): the plan allows some and the
        backend has a stroke scale."""
        return self.split_budget() > 0 and self.entry.stroke_sigma is not None

    def split_budget(self) -> int:
        """Splats the split may add: the plan's ``split_cap`` share of the scene, and at least its ``split_floor``
        (none when the share is 0)."""
        if self.plan.split_cap == 0:
            return 0
        return max(int(self.plan.split_cap * len(self.scene)), self.plan.split_floor)

    def fit_scale(self) -> float:
        """Fit pixels per proposal pixel, averaged over the active views."""
        proposal_pixels = self.config.proposal_width * self.config.proposal_height
        return float(np.mean([math.sqrt(c.width * c.height / proposal_pixels) for c in self.cameras]))

    def prepare(self, content_images: dict[int, np.ndarray] | None) -> None:
        """The seen Gaussians and their fit, how wide they are on screen, the proposal references, and the proposal
        states (resumed or new)."""
        views = len(self.cameras)
        steps = views + 3  # a render per view to find the splats it sees, the fit, the synthesis, the base's distance

        def setup(step: int, what: str) -> None:
            self.hooks.report(0, step, steps, "setup", float("nan"), f"set-up: {what}")
            self.hooks.check_cancel()

        setup(0, f"finding the splats the views see (0/{views} views rendered)")
        base_renders = self._set_up_fit(
            lambda done: setup(
                done,
                f"finding the splats the views see ({done}/{views} views rendered)"
                if done < views
                else "building the colour fit",
            )
        )
        setup(views + 1, "preparing the synthesis")
        self._footprint_note()
        self._set_up_proposals(base_renders, content_images)
        setup(views + 2, "style distance of the base renders")
        self._resume_or_encode(base_renders)

    def _set_up_fit(self, each_view: Callable[[int], None] | None = None) -> list[torch.Tensor]:
        """The Gaussians the active views see, their fit state, renderer and optimiser; the base renders.
        ``each_view(done)`` after each view's render (the last one: the fit's set-up follows)."""
        config, say = self.config, self.hooks.say
        raster = self.raster
        seen, fast = seen_gaussians(
            self.scene, self.cameras, raster, config.optimize_geometry, each_view, self.rendered
        )
        self.rendered = None  # the renderer narrows them to the fit's columns
        left_out = len(self.scene) - seen.numel()
        if self.mask is not None:
            seen = seen[torch.from_numpy(self.mask)[seen]]
            if seen.numel() == 0:
                raise CameraError("the active cameras see none of the selected Gaussians")
            say(
                f"optimising {seen.numel()} of {len(self.scene)} Gaussians: the {int(self.mask.sum())} selected, "
                f"{int(self.mask.sum()) - seen.numel()} of them unseen by the active views"
            )
        else:
            say(
                f"optimising {seen.numel()} of {len(self.scene)} Gaussians "
                f"({left_out} unseen by the active views are left out)"
            )
        self.renderer = ViewRenderer(
            self.scene,
            self.cameras,
            seen,
            raster,
            config.sh_rest == "keep",
            fast,
            self.mask is not None,
            self.plan.proxy_sigma,
        )
        proxies = self.renderer.proxies
        if proxies is not None:
            shared = int(torch.bincount(proxies.column, minlength=proxies.count).gt(1).sum())
            grouped = seen.numel() - (proxies.count - shared)
            say(
                f"{grouped} of them narrower than {self.plan.proxy_sigma:g} px share {shared} colours during the fit "
                f"({proxies.count} in all)"
            )
        self.state = state = FitState.start(self.scene, seen, config.optimize_geometry, proxies)
        weights = FitLossWeights()
        if not config.optimize_geometry:
            say(f"colour fit: bounded least squares over the {len(self.cameras)} active views, solved each stage")
            features = None  # Eq. 16's L1, DSSIM, TV and feature terms shape gradient fits only
        else:
            features = feature_extractor(weights.feature, self.dino_path, say, self.device or "cpu")
        # Mean offsets are relative to the scene's extent (optim.scene_extent): lr and bound x extent, so a scene of
        # extent 1 gets the paper's absolute numbers and a scene scaled by s moves its splats s times as far.
        seen_numpy = seen.numpy()
        self.extent = scene_extent(self.scene.means[seen_numpy], self.scene.log_scales[seen_numpy])
        settings = FitOptimizerSettings(extent=self.extent)
        if config.optimize_geometry:
            say(
                f"scene extent {self.extent:.6g}: mean offsets lr {settings.mean_lr:.3g}, "
                f"bound +-{settings.scene_bounds.means:.3g}"
            )
        geometry_params = [p for p in (state.d_log_scales, state.d_quats) if p is not None]
        mean_params = [state.d_means] if state.d_means is not None else []
        optimizer = make_fit_optimizer([state.colors], geometry_params, settings, mean_params)
        base_renders = self.renderer.base(state)
        self.solver = None if config.optimize_geometry else BoundedColorFit(self.renderer, state, self.medium)
        self.fitter = MultiViewFit(
            self.renderer,
            state,
            optimizer,
            settings.scene_bounds,
            weights,
            features,
            base_renders,
            self.plan.ablation.pcgrad,
        )
        return base_renders

    def _footprint_note(self) -> None:
        """How wide the splats are on screen (``footprint_px`` in the first stage's log entry); one line when they are
        wider than the strokes. The strokes' scale is in proposal pixels, the footprint in fit pixels: a proposal
        pixel is sqrt(fit pixels / proposal pixels) fit pixels, averaged over the views."""
        self.footprint = splat_footprint(self.renderer)
        note = self.medium.footprint_note(self.footprint, self.entry, self.config, self.fit_scale())
        if note:
            self.hooks.note(note)

    def _set_up_proposals(self, base_renders: list[torch.Tensor], content_images) -> None:
        """The proposal backend and its fixed references at the proposal size: style, contents, coverage."""
        style = torch.from_numpy(self.style_rgb).permute(2, 0, 1).contiguous()
        self.style = _resize(style, *style_size(self.config))  # Stroke Size: the painting's scale against the view
        self.contents = []
        for i, v in enumerate(self.selection.indices):
            photo = None if content_images is None else content_images.get(v)
            image = (
                base_renders[i] if photo is None else torch.from_numpy(np.asarray(photo, np.float32)).permute(2, 0, 1)
            )
            self.contents.append(_resize(image, *self.size))
        # Coverage (alpha) of each base render: the synth backend and the post stage change only what splats cover.
        with torch.no_grad():
            self.alphas = [self.renderer.alpha(v, self.state).detach() for v in range(len(self.cameras))]
        self.coverages = [_resize(a[None].expand(3, -1, -1), *self.size)[0] for a in self.alphas]
        self.fitter.covered = [a > COVERED for a in self.alphas]  # its steps' RMSE over covered pixels, for progress
        self.brightness = scene_brightness(self.contents, self.coverages)
        self.backend = self.entry.make(self.config, self.plan, self.brightness, self.device)
        self.depths = None
        if self.backend.takes_depth:
            with torch.no_grad():
                depths = [self.renderer.depth(v, self.state).detach().float() for v in range(len(self.cameras))]
            # Nearest, not bilinear: a blend of a silhouette's depth with the background's 0 is no depth at all.
            self.depths = [F.interpolate(d[None, None], size=self.size, mode="nearest")[0, 0] for d in depths]
        self.hooks.model.set_stage_costs([self.backend.relative_cost(s, *self.size) for s in self.stages])
        if not self.config.optimize_geometry:  # solved fits: the first takes more rounds, the best views more solves
            best_views_fine = self.plan.best_views > 0 and not self.plan.best_views_coarse
            fits = [
                BEST_VIEWS_STAGE_FIT_COST if best_views_fine and self.backend.full_detail(s) else 1.0
                for s in self.stages
            ]
            fits[0] *= FIRST_FIT_COST
            self.hooks.model.set_stage_costs(fits, "fit")
        self.hooks.model.set_marks_stages([s.index for s in self.stages if self.marks_wanted(s)])
        if self.plan.early_stop > 0:  # the first stage finish_stage may stop after
            may_stop = [s.index for s in self.stages[:-1] if self.backend.full_detail(s)]
            self.hooks.model.expect_stop(may_stop[0] if may_stop else None)
        note = light_note(self.entry, self.config, self.brightness)
        if note:
            self.hooks.note(note)

    def _resume_or_encode(self, base_renders: list[torch.Tensor]) -> None:
        """Resume from a checkpoint of the same run, else encode the base renders; the style distances so far."""
        resumable = self.record.checkpoint is not None
        settings = {**self.config.to_dict(), "plan": asdict(self.plan)}
        key = run_id(settings, self.scene, self.cameras, self.style, self.contents, self.mask) if resumable else ""
        saved = self.record.resume(key, self.hooks.say)
        if saved is not None:
            with torch.no_grad():
                for p, value in zip(self.state.params(), saved["params"]):
                    p.copy_(value)
            self.fitter.optimizer.load_state_dict(saved["optimizer"])
            self.states, self.hooks.first_stage = saved["states"], saved["stage"] + 1
            for entry in self.record.entries:  # the time left from the stages done, before this run times one
                self.hooks.model.adopt(entry)
        else:
            self.states = [self.backend.encode(_resize(r, *self.size)) for r in base_renders]
        # Style distances after each stage, the base renders' first (resumed runs take theirs from the log).
        log = self.record.entries
        self.distances = [entry["style_distance"] for entry in log if "style_distance" in entry]
        if not self.distances or "base_style_distance" not in log[0]:
            self.distances.insert(0, self.style_distance(base_renders))
            self.hooks.say(f"style distance of the base renders: {self.distances[0]:.4f}")
        else:
            self.distances.insert(0, log[0]["base_style_distance"])

    def remaining_stages(self) -> list[Stage]:
        return self.stages[self.hooks.first_stage - 1 :]

    # --- One stage ----------------------------------------------------------------------------------------

    def propose(self, stage: Stage) -> None:
        """Sec. 4.1: attention-guided proposals, the stage's updates (``stage.updates``), per view; each view guided by the
        ones before it as the medium says (the guides' painting of the views, when the medium makes one, is the
        fit's when the stage's targets are the proposals themselves)."""
        self.work = work = _StageWork(time.perf_counter())
        self.backend.prepare_stage(self.states, self.style, self.contents, self.coverages)
        guides = self.medium.guides(self)
        views = len(self.cameras)
        for i in range(views):
            self.hooks.check_cancel()
            message = f"painting view {i + 1}/{views} ({self.names[i]})"
            self.hooks.report(stage.index, i, views, "proposal", float("nan"), message)
            guide = guides.guide(i)
            kwargs = {"guide": guide} if guide is not None else {}
            if self.depths is not None:
                kwargs["depth"] = self.depths[i]
            self.states[i], energies = self.backend.propose(
                self.states[i], stage, self.style, self.contents[i], self.coverages[i], **kwargs
            )
            guides.proposed(i, self.backend.decode(self.states[i]).detach().float().cpu())
            if self.marks_wanted(stage):
                work.fields.append(self.backend.last_field)
            work.energies.append(energies[-1])
        if self.gammas[stage.index - 1] == 1.0:  # the targets are the proposals: what the guides painted is the fit
            work.painted = guides.painting()
        work.proposal_seconds = time.perf_counter() - work.started

    def guided(self) -> bool:
        """Whether the views' proposals are guided by the views before them (a backend that takes guides, two
        views or more)."""
        return self.backend.takes_guides and len(self.cameras) > 1

    def residual_targets(self, stage: Stage) -> list[torch.Tensor]:
        """Sec. 4.2, Eqs. 10-12: each view's render moved by gamma_n x the proposal's residual."""
        targets, gamma = [], self.gammas[stage.index - 1]
        space = "logit" if self.plan.ablation.logit_space else "image"
        self.work.renders = self.renderer.all(self.state)
        for i, image in enumerate(self.work.renders):
            decoded = self.backend.decode(self.states[i]).detach().float().cpu()
            proposal = _resize(decoded, image.shape[1], image.shape[2])
            residual = proposal_residual(proposal, image)
            targets.append(residual_target(image, residual, gamma, space))
            self.work.images[self.names[i]] = {
                "render": image.permute(1, 2, 0).numpy(),
                "proposal": proposal.permute(1, 2, 0).numpy(),
                "target": targets[-1].permute(1, 2, 0).numpy(),
                "residual": (0.5 + 0.5 * residual).clamp(0, 1).permute(1, 2, 0).numpy(),
            }
        if self.carries_marks(stage):
            painted, targets = self._carried_targets(targets, stage.index)
            for name, render, target in zip(self.names, painted, targets):
                self.work.images[name]["marks"] = render.permute(1, 2, 0).numpy()
                self.work.images[name]["target"] = target.permute(1, 2, 0).numpy()
        return targets

    def marks_wanted(self, stage: Stage) -> bool:
        """Whether this stage's marks are to come from the splats (marks.py): the plan asks for it, the colours are
        fitted alone (geometry frozen) and the stage proposes at full detail."""
        return self.plan.carry_marks and self.renderer.fast is not None and self.backend.full_detail(stage)

    def carries_marks(self, stage: Stage) -> bool:
        """Whether they do: wanted, and the backend said where every view's proposal comes from."""
        fields = self.work.fields
        return self.marks_wanted(stage) and len(fields) == len(self.cameras) and all(f is not None for f in fields)

    def _carried_targets(
        self, targets: list[torch.Tensor], stage: int
    ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Each splat's painting coordinate from the view that owns it, each view painted as the splats carry the
        painting, and each target's fine band from that painting (marks.py); (the views' paintings, the targets)."""
        splats = self.state.seen.numel()
        self.hooks.report(stage, 0, 1, "marks", float("nan"), "carrying the marks: each splat's vote")
        # The solve's samples (those fainter than SOLVE_MIN_WEIGHT left out: 39% of the bonsai's, 0.5% of its weight):
        # the same painted pixels, 99.6% of them the same colour, in 60% of the time.
        maps = self.solver.views.maps
        votes = []
        for m, fast, painting_field in zip(maps, self.renderer.fast, self.work.fields):
            votes.append(vote_view(m.samples(), fast.shape, painting_field, splats))
            self.hooks.check_cancel()
        marks = CarriedMarks.from_votes(votes)
        del votes
        source = self.work.fields[0].source
        surfaces = None
        if self.plan.marks_by_depth:
            surfaces = Surfaces(self.cameras, [fast.depth for fast in self.renderer.fast], self.work.fields)
        views = [
            paint_view(m.samples(), fast.shape, self.size, marks, source, v, surfaces)
            for v, (m, fast) in enumerate(zip(maps, self.renderer.fast))
        ]
        painted, masks = [image for image, _ in views], [mask for _, mask in views]
        sigma = self.entry.stroke_sigma(self.config.stroke_size) * self.fit_scale()
        self.hooks.say(f"marks carried by {int(marks.carried.sum())} of {splats} splats")
        return painted, carried_targets(targets, painted, self.alphas, sigma, masks)

    def fit(self, stage: Stage, targets: list[torch.Tensor]) -> None:
        """Sec. 4.3: multi-view fitting of the seen Gaussians to the targets (Eqs. 16-20); solved to its bounded
        least-squares optimum with geometry frozen, else the paper's Adam steps."""
        n = stage.index
        self.medium.at_stage(self.backend.full_detail(stage))
        self.work.closure = self._fit(targets, n, "fit", f"stage {n}, fit step")
        self.work.targets = targets
        self.work.fitted_seconds = time.perf_counter() - self.work.started
        feedback = "style distance, re-encoding the fitted views" if self.plan.ablation.feedback else "style distance"
        self.hooks.report(n, 0, 1, "feedback", float("nan"), feedback)

    def emphasize_marks(self, stage: Stage) -> None:
        """The last stage's fit again (the one that stops, or the schedule's last), each view's marks finer than
        ``Plan.emphasis_width`` stroke scales asked for as much more as the first fit lost (marks.emphasis_gains): a
        colour per splat, shared by the views, draws a share of them. After the stop's decision, which so compares
        one fit with another (a second fit's gain in the style distance read as progress ran a stage more)."""
        n, work = stage.index, self.work
        last = bool(work.stop_reason) or n == len(self.stages)
        if not (last and self.plan.marks_emphasis > 0 and self.carries_marks(stage) and self.entry.stroke_sigma):
            return
        scale = self.fit_scale()
        sigma = self.plan.emphasis_width * self.entry.stroke_sigma(self.config.stroke_size) * scale
        painting = painting_band_deviation(work.fields[0].source, sigma / scale)
        gains = emphasis_gains(work.targets, work.renders, self.alphas, sigma, painting, self.plan.marks_emphasis)
        self.hooks.say(f"marks emphasised where the splats drew them weaker: gain {min(gains):.2f}-{max(gains):.2f}")
        if max(gains) <= 0.0:  # the first fit drew what the painting holds: the same fit again would change nothing
            return
        started = time.perf_counter()
        work.closure = self._fit(emphasized(work.targets, self.alphas, gains, sigma), n, "fit", f"stage {n}, fit step")
        work.fitted_seconds += time.perf_counter() - started  # the log's fit time holds both fits
        work.distance = self.style_distance(work.renders)

    def _fit(self, targets, stage: int, phase: str, where: str, start: torch.Tensor | None = None) -> dict:
        """Fit ``targets`` (solve or Adam steps; the solve from ``start``, default the current colours); how much of
        the gap to them the fit closed, for the log.

        Progress reports one loss throughout, the fit's RMSE over covered pixels (``fit_residual`` in the log): after
        each round of a solve that of its colours, from the solve's own residuals (its maps leave out the samples
        fainter than ``SOLVE_MIN_WEIGHT``, 0.5% of the bonsai's weight; rendering the views for it cost preview 9% of
        its time), after each Adam step that of the renders the step took."""
        before = self.work.renders or self.renderer.all(self.state)
        if self.solver is not None:
            rounds = self.solver.settings.max_rounds

            def counter(index: int) -> str:
                return f"colour solve round {index} (at most {rounds})"

            solved_rounds = [0]

            covered = [alpha.reshape(-1) > COVERED for alpha in self.alphas]

            def each_round(index: int, _objective: float, _colors: torch.Tensor, residuals) -> None:
                solved_rounds[0] = index
                if self.hooks.progress is not None:
                    self.hooks.report(stage, index, rounds, phase, covered_rmse(residuals, covered), counter(index))
                self.hooks.check_cancel()

            def each_view(done: int) -> None:
                message = f"{self.medium.views_alone}: {done}/{len(targets)} views solved alone"
                self.hooks.report(stage, solved_rounds[0], rounds, phase, float("nan"), message)
                self.hooks.check_cancel()

            self.hooks.report(stage, 0, rounds, phase, float("nan"), "colour solve starting")
            self.hooks.check_cancel()
            try:
                painted = self.work.painted if phase == "fit" else None
                result = self.solver.solve(targets, each_round, start, each_view, painted)
            except NumericalError as error:
                raise NumericalError(
                    f"{error} at {where.rsplit(',', 1)[0]}, so the run stopped{self.record.kept_note()}"
                ) from None
            self.work.losses = result.objectives
            done, total, counted = len(result.objectives) - 1, rounds, counter(len(result.objectives) - 1)
            iterations = result.iterations
        else:
            steps = self.plan.fit_steps if phase == "fit" else self.plan.post_steps
            self.work.losses = self._fit_steps(targets, steps, stage, phase, where)
            done, total, counted = steps, steps, f"fit step {steps}/{steps}"
            iterations = steps
        after = self.renderer.all(self.state)
        self.work.renders = after
        gap, left = fit_residual(before, targets, self.alphas), fit_residual(after, targets, self.alphas)
        self.hooks.report(stage, max(done, total), total, phase, left, counted)  # the fit's end: on to the next
        return {
            "target_gap": gap,
            "fit_residual": left,
            "gap_closed": 1.0 - left / gap if gap > 0 else 1.0,
            "fit_moved": fit_residual(after, before, self.alphas),
            "fit_iterations": iterations,
        }

    def feed_back(self, stage: Stage) -> None:
        """Algorithm 1, last line: re-encode the fitted renders (unless the ablation keeps the first latents);
        their style distance, and how far the fit moved them, decide the early stop."""
        renders = self.work.renders
        self.work.distance = self.style_distance(renders)
        self.distances.append(self.work.distance)
        improvement = stage_improvement(self.distances)
        early_stop, moved = self.plan.early_stop, self.work.closure.get("fit_moved")
        if early_stop > 0 and stage.index < len(self.stages) and self.backend.full_detail(stage):
            if improvement is not None and improvement < early_stop:
                change = f"improved by {improvement:.1%} (< {early_stop:.1%})"
                if improvement < 0:  # the first full-detail stage mostly: its marks change the look
                    change = f"rose by {-improvement:.1%} instead of falling by {early_stop:.1%}"
                self.work.stop_reason = (
                    f"over the last {EARLY_STOP_WINDOW} stages the style distance {change}; the remaining stages are "
                    "left out"
                )
            elif moved is not None and moved < STILL_SCENE:
                self.work.stop_reason = (
                    f"the stage's fit moved the views by {moved:.4f} RMSE (< {STILL_SCENE}); the remaining stages "
                    "are left out"
                )
        if self.plan.ablation.feedback:
            self.states = [self.backend.encode(_resize(r, *self.size)) for r in renders]

    def finish_stage(self, stage: Stage) -> bool:
        """The stage's log entry, checkpoint, saved images and live update; True when the stages stop early."""
        n, work = stage.index, self.work
        entry = {
            "stage": n,
            "t": stage.state,
            "gamma": self.gammas[n - 1],
            "energy": float(np.mean(work.energies)),
            "fit_loss_first": work.losses[0] if work.losses else None,
            "fit_loss_last": work.losses[-1] if work.losses else None,
            "fit_losses": work.losses,
            **work.closure,
            "stage_seconds": work.fitted_seconds,
            "proposal_seconds": work.proposal_seconds,
            "feedback_seconds": time.perf_counter() - work.started - work.fitted_seconds,
            "seconds": self.hooks.elapsed(),
            "peak_rss_mb": peak_rss_mb(),
            "views": len(self.cameras),
            "gaussians_optimised": self.state.splat_count,
            "scene_extent": self.extent,
            **(
                {"footprint_px": self.footprint, "medium": self.config.medium, "brightness": self.brightness}
                if n == 1
                else {}
            ),
            "style_distance": work.distance,
            "base_style_distance": self.distances[0],
        }
        if work.stop_reason:
            entry["early_stop"] = True
            self.hooks.note(f"stopping after stage {n} of {len(self.stages)}: {work.stop_reason}")
        self.record.save_images(n, work.images)
        self.record.append(entry)
        self.record.save_checkpoint(n, self.state.params(), self.fitter.optimizer, self.states)
        self.hooks.stage_done(lambda: self._stage_update(n, work.images))
        return bool(work.stop_reason)

    # --- After the stages ---------------------------------------------------------------------------------

    def post_stage(self) -> None:
        """Covariance colour transfer of the renders toward the style, then fitting to it."""
        if self.post_steps() <= 0:
            return
        self.hooks.report(len(self.stages) + 1, 0, 1, "post", float("nan"), "colour transfer")
        self.hooks.check_cancel()
        renders = self.renderer.all(self.state)
        style = torch.from_numpy(self.style_rgb).permute(2, 0, 1).contiguous()
        # Statistics over covered pixels only, and the background left as rendered: a black background
        # in the statistics would wash the covered colours out, and recolouring it would light floaters.
        transform = covariance_color_transform(torch.stack(renders), style, render_mask=torch.stack(self.alphas))
        targets = [
            r + coverage_weight(a)[None] * (transform.apply_to_images(r).clamp(0, 1) - r)
            for r, a in zip(renders, self.alphas)
        ]
        started = time.perf_counter()
        self.work = _StageWork(started, renders=renders)
        # The map is one affine colour change, so the splats' own colours mapped by it nearly reach the targets
        # in every view: the solve starts there and its anchor holds splats the views barely see there, rather
        # than at their colours before the map (which left the fit 1.5x the optimum's residual on the demo).
        mapped = transform.apply_to_colors(self.state.colors.detach()).clamp(0.0, 1.0)
        closure = self._fit(targets, len(self.stages) + 1, "post", "post stage step", mapped)
        losses = self.work.losses
        self.record.append(
            {
                "stage": "post",
                "fit_loss_first": losses[0],
                "fit_loss_last": losses[-1],
                "fit_losses": losses,
                **closure,
                "stage_seconds": time.perf_counter() - started,
                "seconds": self.hooks.elapsed(),
                "peak_rss_mb": peak_rss_mb(),
            }
        )
        self.hooks.stage_done(lambda: self._stage_update(len(self.stages) + 1, {}))

    def post_steps(self) -> int:
        """The post stage's fit steps (0: no post stage)."""
        return self.plan.post_steps

    def result(self) -> StylizeResult:
        scene = result_scene(self.scene, self.state, self.config.sh_rest == "zero", self.mask is not None)
        seconds = self.hooks.elapsed()
        log = self.record.entries
        last_loss = log[-1].get("fit_residual", float("nan")) if log else float("nan")  # the fit RMSE, as reported
        self.hooks.report(len(self.stages), 1, 1, "done", last_loss, f"done in {seconds:.1f} s")
        return StylizeResult(scene, self.selection, log, seconds, self.state.splat_count, self.parents)

    # --- Shared by the steps ------------------------------------------------------------------------------

    def _fit_steps(self, targets, steps: int, stage: int, phase: str, where: str) -> list[float]:
        """Adam steps; the log keeps each step's Eq. 16 loss, progress the RMSE over covered pixels of its renders."""
        losses = []
        for step in range(steps):
            self.hooks.check_cancel()
            try:
                losses.append(self.fitter.step(targets, f"{where} {step + 1}"))
            except NumericalError as error:
                raise NumericalError(f"{error}{self.record.kept_note()}") from None
            if step + 1 < steps:  # the last step's report is the fit's end, with the RMSE after it
                counter = f"fit step {step + 1}/{steps}"
                self.hooks.report(stage, step + 1, steps, phase, self.fitter.covered_rmse, counter)
        return losses

    def style_distance(self, renders: list[torch.Tensor]) -> float:
        """Style distance of the active views: 7x7 patch SW to the style at the proposal size, covered pixels."""
        small = [_resize(r, *self.size) for r in renders]
        return float(sliced_wasserstein_patches(small, self.style, masks=self.coverages, seed=self.config.seed).mean())

    def _stage_update(self, stage: int, images) -> StageUpdate:
        geometry = self.config.optimize_geometry
        scene = result_scene(self.scene, self.state, self.config.sh_rest == "zero", self.mask is not None)
        return StageUpdate(
            stage,
            scene.sh_dc,
            scene.means if geometry else None,
            scene.log_scales if geometry else None,
            scene.quats if geometry else None,
            images,
            self.parents,
            scene if self.parents is not None else None,
        )
