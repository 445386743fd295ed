"""DReSG end to end (Algorithm 1): active views, proposals, render-relative targets, multi-view fitting.

One library call, :func:`stylize`, with a progress callback, a per-stage callback (for live viewport
updates), a cancel event, stage checkpoints and a JSON-lines log. The CLI and the Blender operators are
thin layers over it. Nothing here imports bpy.

What a scene does not need is left out:
- Gaussians that no active view sees are neither rasterized nor optimised during fitting (the log says
  how many); their colours stay as they were.
- With geometry offsets off (the default off the ``paper`` preset), fitting takes the colour-only fast
  path: each view's image is a cached sparse matrix times the colours.
- SH rest bands are never allocated for a scene without them; with them, the stylized colour goes to the
  DC term and the rest is zeroed or kept (``StylizeConfig.sh_rest``).
- diffusers is imported only for the ``sd15`` backend; with one active view there is no projection.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import resource
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .camera import Camera
from .config import StylizeConfig
from .errors import CameraError, CancelledError, ConfigError, NumericalError
from .raster import ColorOnlyRenderer, RasterSettings, render
from .raster.sh import SH_C0, sh_basis
from .scene import GaussianScene


@dataclass
class Progress:
    stage: int  # 0 before the first stage, stages + 1 for the post stage
    stages: int
    step: int
    steps: int
    phase: str  # "select" | "setup" | "proposal" | "fit" | "post" | "done"
    loss: float
    eta_seconds: float
    message: str


@dataclass
class StageUpdate:
    """What a stage changed, for live display: numpy arrays for the whole scene (unseen splats unchanged)."""

    stage: int
    sh_dc: np.ndarray  # [N, 3] float32
    means: np.ndarray | None  # [N, 3] with offsets applied; None when geometry is frozen
    log_scales: np.ndarray | None
    quats: np.ndarray | None
    images: dict[str, dict[str, np.ndarray]]  # view name -> render / proposal / target / residual [H, W, 3]


@dataclass
class ActiveViews:
    indices: list[int]  # chosen cameras, in pick order (the deterministic active-view order)
    coverage: list[float]  # total capped coverage after each pick
    per_view_coverage: list[float]  # capped coverage each camera gives on its own
    reason: str  # why the selection stopped
    blind: list[int] = field(default_factory=list)  # cameras that see nothing


@dataclass
class StylizeResult:
    scene: GaussianScene
    selection: ActiveViews
    log: list[dict]
    seconds: float


def _raster_settings(config: StylizeConfig) -> RasterSettings:
    return RasterSettings(near=config.near, background=tuple(config.background))


def _render_cameras(cameras: Sequence[Camera], scale: float) -> list[Camera]:
    if scale == 1.0:
        return list(cameras)
    return [c.resized(max(1, round(c.width * scale)), max(1, round(c.height * scale))) for c in cameras]


def _scene_tensors(scene: GaussianScene):
    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return t(scene.means), t(scene.quats), t(scene.log_scales), t(scene.opacity_logits)


def visibility_matrix(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    config: StylizeConfig,
    *,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
) -> torch.Tensor:
    """w [V, N] (sparse COO): each Gaussian's depth-consistent visible weight sum_p T alpha in each view (Sec. 4.3).

    ``progress(done, total)`` is called after each view; setting ``cancel`` stops with CancelledError.
    """
    means, quats, log_scales, logits = _scene_tensors(scene)
    colors = torch.zeros_like(means)
    rows, cols, vals = [], [], []
    settings = _raster_settings(config)
    for v, camera in enumerate(cameras):
        if cancel is not None and cancel.is_set():
            raise CancelledError("view selection cancelled")
        if progress is not None:
            progress(v, len(cameras))
        with torch.no_grad():
            out = render(means, quats, log_scales, logits, colors, camera, settings, visibility="depth_consistent")
        nz = torch.nonzero(out.visibility > 0).squeeze(-1)
        rows.append(torch.full_like(nz, v))
        cols.append(nz)
        vals.append(out.visibility[nz])
    index = torch.stack([torch.cat(rows), torch.cat(cols)])
    size = (len(cameras), len(scene))
    return torch.sparse_coo_tensor(index, torch.cat(vals), size, check_invariants=False).coalesce()


def select_active_views(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    config: StylizeConfig,
    *,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
) -> ActiveViews:
    """Sec. 4.3: greedy capped-coverage selection (Eqs. 13-15) on the rasterizer's visibility weights.

    ``progress`` and ``cancel`` as for :func:`visibility_matrix` (one render per camera is the cost).
    """
    from .views import ViewSelectionSettings, capped_coverage, select_views, target_support

    if not cameras:
        raise CameraError("no cameras: add cameras to the scene, give a cameras file, or use orbit cameras")
    w = visibility_matrix(
        scene, _render_cameras(cameras, config.render_scale), config, progress=progress, cancel=cancel
    )
    settings = ViewSelectionSettings(
        min_support=config.w_min,
        target_fraction=config.rho,
        coverage_stop=config.coverage_stop,
        min_gain=config.gain_threshold,
        max_views=config.max_views or None,
    )
    chosen = select_views(w, settings)
    dense_max = w.to_dense().amax(0).numpy().astype(np.float64) if len(scene) * len(cameras) <= 5e7 else None
    if dense_max is None:
        dense_max = (
            torch.zeros(len(scene), dtype=torch.float64)
            .scatter_reduce_(0, w.indices()[1], w.values().double(), "amax")
            .numpy()
        )
    targets = dense_max >= config.w_min
    support = target_support(dense_max, config.w_min, config.rho)
    per_view = []
    for v in range(len(cameras)):
        row = w[v].to_dense().numpy().astype(np.float64)
        per_view.append(float(capped_coverage(row[targets], support[targets]).sum() / max(targets.sum(), 1)))
    return ActiveViews(
        list(chosen.views), list(chosen.coverage), per_view, chosen.stop_reason, list(chosen.blind_views)
    )


# --- Fitting parameters and per-view renderers -------------------------------------------------------------


@dataclass
class _Fit:
    """The optimised state: RGB colours and bounded geometry offsets of the seen Gaussians."""

    seen: torch.Tensor  # [M] indices into the scene
    colors: torch.Tensor  # [M, 3] RGB (render colour before the view-dependent SH rest)
    d_means: torch.Tensor | None  # [M, 3]
    d_log_scales: torch.Tensor | None
    d_quats: torch.Tensor | None

    def params(self):
        return [p for p in (self.colors, self.d_means, self.d_log_scales, self.d_quats) if p is not None]

    def geometry(self):
        return [p for p in (self.d_means, self.d_log_scales, self.d_quats) if p is not None]


class _Views:
    """Renders the active views of the seen Gaussians, colour-only (cached) or with geometry."""

    def __init__(
        self,
        scene: GaussianScene,
        cameras: list[Camera],
        seen: torch.Tensor,  # [M] sorted indices of the Gaussians the active views see
        config: StylizeConfig,
        fast: list[ColorOnlyRenderer] | None,  # full-scene colour-only renderers (geometry frozen), else None
    ):
        means, quats, log_scales, logits = _scene_tensors(scene)
        self.means, self.quats = means[seen], quats[seen]
        self.log_scales, self.logits = log_scales[seen], logits[seen]
        self.cameras = cameras
        self.settings = _raster_settings(config)
        self.geometry = config.optimize_geometry
        # View-dependent colour of kept SH rest bands: a constant per-view offset on the RGB colour.
        self.offsets: list[torch.Tensor | None] = [None] * len(cameras)
        if scene.sh_rest is not None and config.sh_rest == "keep":
            rest = torch.from_numpy(scene.sh_rest[seen.numpy()]).float()
            degree = scene.sh_degree
            for v, camera in enumerate(cameras):
                dirs = self.means - torch.as_tensor(camera.center, dtype=torch.float32)
                dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
                basis = sh_basis(dirs, degree)[:, 1:]  # [M, K]
                self.offsets[v] = (basis[:, :, None] * rest).sum(1)
        # Colour-only: the full-scene renderers that found the seen set, narrowed to it (no second rasterization).
        self.fast = None if self.geometry else [f.restrict(seen) for f in fast]

    def __call__(self, v: int, fit: _Fit) -> torch.Tensor:  # -> [3, H, W]
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

    def alpha(self, v: int, fit: _Fit) -> torch.Tensor:  # -> [H, W]
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


EARLY_STOP_WINDOW = 2  # stages over which the style distance must improve (one stage may pause, e.g. a coarse one)


def stage_improvement(distances: Sequence[float], window: int = EARLY_STOP_WINDOW) -> float | None:
    """Relative drop of the style distance over the last ``window`` stages, (d[-1 - window] - d[-1]) / d[-1 - window].

    ``distances[0]`` is the base renders'; None while fewer than ``window`` stages have run, or when the
    earlier distance is 0 (nothing left to improve).
    """
    if len(distances) <= window or distances[-1 - window] <= 0:
        return None
    return (distances[-1 - window] - distances[-1]) / distances[-1 - window]


def _proposal_backend(config: StylizeConfig):
    """The configured proposal backend; the run's seed and content weight w_c go to every backend that has them."""
    from .proposal import EnergyTerms, make_backend

    if config.proposal == "synth":
        weight = config.content_weight if config.use_content_query else 0.0
        return make_backend("synth", seed=config.seed, content_weight=weight)
    backend = make_backend("sd15", model_path=config.model_path)
    backend.learning_rate = config.latent_lr
    backend.terms = EnergyTerms(
        config.content_weight, config.use_content_query, config.use_style_keys, config.use_style_values
    )
    return backend


def _feature_extractor(config: StylizeConfig, log: Callable[[str], None]):
    """The fit loss's feature term: DINO when local weights are given, else the weight-free patch features."""
    if config.lambda_feature <= 0:
        return None
    if config.dino_path:
        from .dino import DinoFeatures

        log(f"feature loss: DINO from {config.dino_path}")
        return DinoFeatures(config.dino_path)
    from .losses import patch_feature_maps

    log("feature loss: weight-free patch features (no DINO weights given)")
    return patch_feature_maps


def _resize(image: torch.Tensor, height: int, width: int) -> torch.Tensor:  # [3, H, W]
    if image.shape[-2:] == (height, width):
        return image
    return torch.nn.functional.interpolate(
        image[None], size=(height, width), mode="bilinear", antialias=True, align_corners=False
    )[0].clamp(0, 1)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _run_id(
    config: StylizeConfig,
    scene: GaussianScene,
    cameras: Sequence[Camera],  # the active cameras
    style: torch.Tensor,  # [3, h, w] at the proposal resolution
    contents: Sequence[torch.Tensor],  # [3, h, w] content image per active view
) -> str:
    """What a checkpoint must match to be resumed: the settings, the scene, the active cameras and the images."""
    h = hashlib.sha256(json.dumps(config.to_dict(), sort_keys=True, default=str).encode())
    for array in (scene.means, scene.log_scales, scene.quats, scene.opacity_logits, scene.sh_dc, scene.sh_rest):
        if array is not None:
            h.update(np.ascontiguousarray(array).tobytes())
    for camera in cameras:
        h.update(repr((camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)).encode())
        h.update(np.ascontiguousarray(camera.world_to_camera).tobytes())
    for image in (style, *contents):
        h.update(image.contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


# --- The loop ----------------------------------------------------------------------------------------------


def check_run_settings(config: StylizeConfig) -> None:
    """Raise ConfigError for settings that are valid on their own but cannot run (checked before any work)."""
    if config.proposal == "synth" and not (config.use_style_keys and config.use_style_values):
        raise ConfigError(
            "the w/o K_s and w/o V_s ablations change the attention energy; the synth backend has none "
            "(use --proposal sd15 for them)"
        )
    if config.proposal == "sd15":
        if not config.model_path:
            raise ConfigError("the sd15 proposal backend needs a local model path (--model PATH)")
        if config.proposal_width % 8 or config.proposal_height % 8:
            raise ConfigError(
                f"the sd15 proposal size must be a multiple of 8 (got {config.proposal_width}x"
                f"{config.proposal_height}), e.g. 448x320"
            )


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
) -> StylizeResult:
    """Algorithm 1 of the paper, returning the stylized scene (the input is never modified).

    ``views`` fixes the active cameras (indices into ``cameras``); otherwise they are chosen by coverage.
    Deterministic for ``config.seed`` on the CPU.
    """
    from .color_transfer import covariance_color_transform, coverage_weight
    from .losses import FitLossWeights, fit_loss
    from .metrics import sliced_wasserstein_patches
    from .optim import (
        FitOptimizerSettings,
        GeometryBounds,
        check_finite_gradients,
        make_fit_optimizer,
        project_geometry_offsets_,
        scene_extent,
    )
    from .pcgrad import pcgrad_fuse
    from .schedule import stage_gammas, stage_timesteps
    from .targets import proposal_residual, residual_target

    config = config or StylizeConfig()
    start_time = time.perf_counter()
    say = messages or (lambda _message: None)
    style_rgb = np.asarray(style_rgb, dtype=np.float32)
    if style_rgb.ndim != 3 or style_rgb.shape[2] != 3 or not np.isfinite(style_rgb).all():
        raise ConfigError(f"style image must be a finite [H, W, 3] array, got shape {style_rgb.shape}")
    style_rgb = np.clip(style_rgb, 0.0, 1.0)  # HDR styles (EXR) would give targets outside displayable colours
    check_run_settings(config)
    ph, pw = config.proposal_height, config.proposal_width
    torch.manual_seed(config.seed)
    stages = stage_timesteps(config.stages, config.updates_per_stage, config.ddim_steps)
    gammas = stage_gammas(config.schedule, stages)
    n_stages = len(stages)
    first_stage = 1  # > 1 when resuming from a checkpoint
    post_share = 0.5 if config.post_steps else 0.0  # the post stage's cost in stages, for the ETA

    def report(stage, step, steps, phase, loss, message=""):
        if progress is None:
            return
        # Work done by this run in stages (the post stage counts post_share), extrapolated linearly.
        fraction = step / max(steps, 1)
        done = n_stages + post_share * fraction if stage > n_stages else max(stage - 1 + fraction, 0.0)
        done -= first_stage - 1
        total = n_stages - (first_stage - 1) + post_share
        elapsed = time.perf_counter() - start_time
        rate = elapsed / done if done > 0 else float("nan")
        eta = 0.0 if phase == "done" else rate * max(total - done, 0.0)
        progress(Progress(stage, n_stages, step, steps, phase, float(loss), eta, message))

    def check_cancel():
        if cancel is not None and cancel.is_set():
            raise CancelledError("stylization cancelled")

    # Active views (Sec. 4.3).
    report(0, 0, 1, "select", float("nan"), "selecting views by coverage")
    if views is None:
        selection = select_active_views(scene, cameras, config)
    else:
        bad = [v for v in views if not 0 <= v < len(cameras)]
        if bad or not views:
            raise CameraError(f"active views {list(views)} do not index the {len(cameras)} cameras")
        selection = ActiveViews(list(views), [], [], "given")
    active = [_render_cameras([cameras[v]], config.render_scale)[0] for v in selection.indices]
    names = [cameras[v].name or f"view_{v:03d}" for v in selection.indices]
    say(f"active views: {len(active)} of {len(cameras)} ({selection.reason})")
    check_cancel()

    # Gaussians seen by the active views; the rest is left out of fitting.
    report(0, 0, 1, "setup", float("nan"), "preparing renders")
    means, quats, log_scales, logits = _scene_tensors(scene)
    settings = _raster_settings(config)
    fast = None
    if config.optimize_geometry:
        seen_mask = torch.zeros(len(scene), dtype=torch.bool)
        for camera in active:
            with torch.no_grad():
                vis = render(
                    means, quats, log_scales, logits, torch.zeros_like(means), camera, settings, visibility="all"
                )
            seen_mask |= vis.visibility > 0
    else:
        fast = [ColorOnlyRenderer(means, quats, log_scales, logits, camera, settings) for camera in active]
        seen_mask = torch.stack([f.seen for f in fast]).any(0)
    seen = torch.nonzero(seen_mask).squeeze(-1)
    if seen.numel() == 0:
        raise CameraError("the active cameras see none of the scene's Gaussians")
    say(
        f"optimising {seen.numel()} of {len(scene)} Gaussians ({len(scene) - seen.numel()} unseen by the active views are left out)"
    )
    base_colors = torch.from_numpy(np.maximum(0.5 + SH_C0 * scene.sh_dc, 0.0).astype(np.float32))[seen]
    geometry = config.optimize_geometry
    fit = _Fit(
        seen,
        base_colors.clone().requires_grad_(True),
        torch.zeros(seen.numel(), 3, requires_grad=True) if geometry else None,
        torch.zeros(seen.numel(), 3, requires_grad=True) if geometry else None,
        torch.zeros(seen.numel(), 4, requires_grad=True) if geometry else None,
    )
    renderer = _Views(scene, active, seen, config, fast)
    features = _feature_extractor(config, say)
    weights = FitLossWeights(dssim=config.lambda_ssim, tv=config.lambda_tv, feature=config.lambda_feature)
    # Mean offsets are relative to the scene's extent (config docstring): lr and bound x extent.
    seen_numpy = seen.numpy()
    extent = config.scene_extent or scene_extent(scene.means[seen_numpy], scene.log_scales[seen_numpy])
    fit_settings = FitOptimizerSettings(
        config.color_lr,
        config.geometry_lr,
        bounds=GeometryBounds(config.mean_bound, config.log_scale_bound, config.quat_bound),
        extent=extent,
    )
    bounds = fit_settings.scene_bounds
    if geometry:
        say(f"scene extent {extent:.6g}: mean offsets lr {fit_settings.mean_lr:.3g}, bound +-{bounds.means:.3g}")
    geometry_params = [p for p in (fit.d_log_scales, fit.d_quats) if p is not None]
    mean_params = [fit.d_means] if fit.d_means is not None else []
    optimizer = make_fit_optimizer([fit.colors], geometry_params, fit_settings, mean_params)

    with torch.no_grad():
        base_renders = [renderer(v, fit).detach().clone() for v in range(len(active))]
        base_features = [features(r[None]).detach() for r in base_renders] if features else None

    # Proposal backend and its fixed references at the proposal resolution.
    backend = _proposal_backend(config)
    style_t = _resize(torch.from_numpy(style_rgb).permute(2, 0, 1).contiguous(), ph, pw)
    contents = []
    for i, v in enumerate(selection.indices):
        photo = None if content_images is None else content_images.get(v)
        image = (
            base_renders[i] if photo is None else torch.from_numpy(np.asarray(photo, dtype=np.float32)).permute(2, 0, 1)
        )
        contents.append(_resize(image, ph, pw))
    # Coverage (alpha) of each base render: the synth backend and the post stage change only what splats cover.
    with torch.no_grad():
        alphas = [renderer.alpha(v, fit).detach() for v in range(len(active))]
    coverages = [_resize(a[None].expand(3, -1, -1), ph, pw)[0] for a in alphas]

    # Resume from a checkpoint of the same run.
    checkpoint = Path(checkpoint_dir) / "checkpoint.pt" if checkpoint_dir else None
    run_id = _run_id(config, scene, active, style_t, contents) if checkpoint is not None else ""
    log = []
    states = None
    if checkpoint is not None and checkpoint.exists():
        saved = _load_checkpoint(checkpoint)
        if saved is None:
            say(f"ignoring the unreadable checkpoint {checkpoint}; starting over")
        elif saved.get("run_id") != run_id:
            say(f"the checkpoint {checkpoint} is from other settings, scene, cameras or style; starting over")
        else:
            with torch.no_grad():
                for p, value in zip(fit.params(), saved["params"]):
                    p.copy_(value)
            optimizer.load_state_dict(saved["optimizer"])
            states, first_stage, log = saved["states"], saved["stage"] + 1, saved["log"]
            say(f"resuming after stage {saved['stage']} from {checkpoint}")
    if states is None:
        states = [backend.encode(_resize(r, ph, pw)) for r in base_renders]
    last_saved = first_stage - 1  # the stage the checkpoint file holds (0: none of this run)
    log_file = Path(log_path) if log_path else None
    if log_file is not None:
        from .fileutil import atomic_write_bytes

        atomic_write_bytes(log_file, "".join(json.dumps(entry) + "\n" for entry in log).encode())

    def current_renders():
        with torch.no_grad():
            return [renderer(v, fit).detach() for v in range(len(active))]

    def fit_step(targets, loss_weights, where: str) -> float:
        """One Adam step of Eq. 16 over all views, colour gradients fused by PCGrad (Eqs. 17-20)."""
        optimizer.zero_grad(set_to_none=True)
        color_grads, geometry_grads, total = [], [[] for _ in fit.geometry()], 0.0
        for v in range(len(active)):
            image = renderer(v, fit)
            render_features = features(image[None]) if features else None
            loss = fit_loss(
                image, targets[v], base_features[v] if features else None, render_features, loss_weights
            ).total
            grads = torch.autograd.grad(loss, fit.params(), allow_unused=True)
            color_grads.append(grads[0] if grads[0] is not None else torch.zeros_like(fit.colors))
            for slot, p, g in zip(geometry_grads, fit.geometry(), grads[1:]):
                slot.append(g if g is not None else torch.zeros_like(p))
            total += float(loss.detach())
        if not math.isfinite(total):
            kept = f"; {checkpoint} keeps the last good stage, {last_saved}" if checkpoint and last_saved else ""
            raise NumericalError(f"the fit loss became non-finite at {where}, so the run stopped{kept}")
        stacked = torch.stack(color_grads)
        fit.colors.grad = (
            pcgrad_fuse(stacked, config.pcgrad_eps).gradient if config.pcgrad and len(active) > 1 else stacked.mean(0)
        )
        for p, slot in zip(fit.geometry(), geometry_grads):
            p.grad = torch.stack(slot).mean(0)  # geometry gradients are averaged over views
        check_finite_gradients(fit.params())
        optimizer.step()
        with torch.no_grad():
            fit.colors.clamp_(0.0, 1.0)
            project_geometry_offsets_(fit.d_means, fit.d_log_scales, fit.d_quats, bounds)
        return total / len(active)

    def stage_update(stage, images) -> StageUpdate:
        scene_now = _result_scene(scene, fit, config)
        return StageUpdate(
            stage,
            scene_now.sh_dc,
            scene_now.means if geometry else None,
            scene_now.log_scales if geometry else None,
            scene_now.quats if geometry else None,
            images,
        )

    def style_distance(renders) -> float:
        """Style distance of the active views: 7x7 patch SW to the style at the proposal size, covered pixels."""
        small = [_resize(r, ph, pw) for r in renders]
        return float(sliced_wasserstein_patches(small, style_t, masks=coverages, seed=config.seed).mean())

    # Style distances after each stage, the base renders' first (resumed runs take theirs from the log).
    distances = [entry["style_distance"] for entry in log if "style_distance" in entry]
    if not distances or "base_style_distance" not in log[0]:
        distances.insert(0, style_distance(current_renders()))
        say(f"style distance of the base renders: {distances[0]:.4f}")
    else:
        distances.insert(0, log[0]["base_style_distance"])

    for stage in stages[first_stage - 1 :]:
        n = stage.index
        stage_start = time.perf_counter()
        # Attention-guided proposals (Sec. 4.1): one fresh-Adam step per timestep, per view.
        energies = []
        backend.prepare_stage(states, style_t, contents, coverages)
        for i in range(len(active)):
            check_cancel()
            report(
                n, i, len(active), "proposal", energies[-1] if energies else float("nan"), f"proposal for {names[i]}"
            )
            states[i], values = backend.propose(states[i], stage.timesteps, style_t, contents[i], coverages[i])
            energies.append(values[-1])
        proposal_seconds = time.perf_counter() - stage_start
        # Render-relative residual targets (Sec. 4.2, Eqs. 10-12).
        renders = current_renders()
        targets, images = [], {}
        for i, image in enumerate(renders):
            proposal = _resize(backend.decode(states[i]).detach().float().cpu(), image.shape[1], image.shape[2])
            residual = proposal_residual(proposal, image)
            targets.append(residual_target(image, residual, gammas[n - 1], "logit" if config.logit_space else "image"))
            images[names[i]] = {
                "render": image.permute(1, 2, 0).numpy(),
                "proposal": proposal.permute(1, 2, 0).numpy(),
                "target": targets[-1].permute(1, 2, 0).numpy(),
                "residual": (0.5 + 0.5 * residual).clamp(0, 1).permute(1, 2, 0).numpy(),
            }
        # Multi-view fitting (Sec. 4.3).
        losses = []
        for step in range(config.fit_steps):
            check_cancel()
            losses.append(fit_step(targets, weights, f"stage {n}, fit step {step + 1}"))
            report(n, step + 1, config.fit_steps, "fit", losses[-1])
        entry = {
            "stage": n,
            "t": stage.state,
            "gamma": gammas[n - 1],
            "energy": float(np.mean(energies)),
            "fit_loss_first": losses[0] if losses else None,
            "fit_loss_last": losses[-1] if losses else None,
            "fit_losses": losses,
            "stage_seconds": time.perf_counter() - stage_start,
            "proposal_seconds": proposal_seconds,
            "seconds": time.perf_counter() - start_time,
            "peak_rss_mb": _peak_rss_mb(),
            "views": len(active),
            "gaussians_optimised": int(seen.numel()),
            "scene_extent": extent,
        }
        log.append(entry)
        if save_views_dir:
            _save_stage_images(save_views_dir, n, images)
        # Feedback: re-encode the fitted render (Algorithm 1, last line).
        renders = current_renders()
        distance = style_distance(renders)
        distances.append(distance)
        entry.update(style_distance=distance, base_style_distance=distances[0])
        improvement = stage_improvement(distances)
        stop = config.early_stop > 0 and n < n_stages and improvement is not None and improvement < config.early_stop
        if stop:
            entry["early_stop"] = True
            say(
                f"stopping after stage {n} of {n_stages}: over the last {EARLY_STOP_WINDOW} stages the style "
                f"distance improved by {improvement:.1%} (< {config.early_stop:.1%}); the remaining stages are left out"
            )
        if config.feedback:
            states = [backend.encode(_resize(r, ph, pw)) for r in renders]
        if checkpoint is not None:
            _save_checkpoint(checkpoint, run_id, n, fit, optimizer, states, log)
            last_saved = n
        if log_file is not None:
            with open(log_file, "a") as handle:
                handle.write(json.dumps(entry) + "\n")
        if on_stage is not None:
            on_stage(stage_update(n, images))
        if stop:
            break

    # Post stage: covariance colour transfer of the renders toward the style, then fitting to it.
    if config.post_steps > 0:
        check_cancel()
        renders = current_renders()
        stack = torch.stack(renders)
        style_chw = torch.from_numpy(style_rgb).permute(2, 0, 1).contiguous()
        # Statistics over covered pixels only, and the background left as rendered: a black background
        # in the statistics would wash the covered colours out, and recolouring it would light floaters.
        transform = covariance_color_transform(stack, style_chw, render_mask=torch.stack(alphas))
        targets = [
            r + coverage_weight(a)[None] * (transform.apply_to_images(r).clamp(0, 1) - r)
            for r, a in zip(renders, alphas)
        ]
        losses = []
        post_start = time.perf_counter()
        for step in range(config.post_steps):
            check_cancel()
            losses.append(fit_step(targets, weights, f"post stage step {step + 1}"))
            report(n_stages + 1, step + 1, config.post_steps, "post", losses[-1])
        entry = {
            "stage": "post",
            "fit_loss_first": losses[0],
            "fit_loss_last": losses[-1],
            "fit_losses": losses,
            "stage_seconds": time.perf_counter() - post_start,
            "seconds": time.perf_counter() - start_time,
            "peak_rss_mb": _peak_rss_mb(),
        }
        log.append(entry)
        if log_file is not None:
            with open(log_file, "a") as handle:
                handle.write(json.dumps(entry) + "\n")
        if on_stage is not None:
            on_stage(stage_update(n_stages + 1, {}))
    result = _result_scene(scene, fit, config)
    seconds = time.perf_counter() - start_time
    report(n_stages, 1, 1, "done", log[-1]["fit_loss_last"] if log else float("nan"), f"done in {seconds:.1f} s")
    return StylizeResult(result, selection, log, seconds)


def _result_scene(scene: GaussianScene, fit: _Fit, config: StylizeConfig) -> GaussianScene:
    """The input scene with the fitted colours in the DC term (and offsets applied); never modifies ``scene``."""
    seen = fit.seen.numpy()
    colors = fit.colors.detach().numpy().astype(np.float64)
    sh_dc = scene.sh_dc.copy()
    sh_dc[seen] = ((colors - 0.5) / SH_C0).astype(np.float32)
    out = replace(scene, sh_dc=sh_dc)
    if scene.sh_rest is not None and config.sh_rest == "zero":
        out = replace(out, sh_rest=np.zeros_like(scene.sh_rest))
    if fit.d_means is not None:
        means, log_scales, quats = scene.means.copy(), scene.log_scales.copy(), scene.quats.copy()
        means[seen] += fit.d_means.detach().numpy()
        log_scales[seen] += fit.d_log_scales.detach().numpy()
        quats[seen] += fit.d_quats.detach().numpy()
        out = replace(out, means=means, log_scales=log_scales, quats=quats)
    return out


def _load_checkpoint(path: Path) -> dict | None:
    """A checkpoint written by :func:`_save_checkpoint`, or None when it cannot be read."""
    try:
        saved = torch.load(path, weights_only=True)  # tensors and plain containers only: no pickled code
    except Exception:  # a truncated or foreign file of any kind: the run starts over instead
        return None
    return saved if isinstance(saved, dict) else None


def _save_checkpoint(path: Path, run_id: str, stage: int, fit: _Fit, optimizer, states, log) -> None:
    from .fileutil import atomic_write_with

    payload = {
        "run_id": run_id,
        "stage": stage,
        "params": [p.detach().clone() for p in fit.params()],
        "optimizer": optimizer.state_dict(),
        "states": [s.detach().clone() for s in states],
        "log": log,
    }
    atomic_write_with(path, lambda tmp: torch.save(payload, tmp))


def _save_stage_images(folder, stage: int, images: dict[str, dict[str, np.ndarray]]) -> None:
    from .imageio import write_image

    for name, kinds in images.items():
        safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)
        for kind, image in kinds.items():
            write_image(Path(folder) / f"stage{stage:02d}" / f"{safe}_{kind}.png", np.ascontiguousarray(image))
