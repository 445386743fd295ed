"""Novel-view evaluation: the one definition of the numbers that ``dresg evaluate``, ``dresg report`` and
``bench/quality.py`` give.

A stylized scene and its base (unstylized) scene are rendered from the same cameras, in path order. Every
value is a mean over the views, on the pixels the base render covers (alpha > ``metrics.ALPHA_THRESHOLD``);
renders are the rasterizer's, not clipped.

==========================  =======  ===========================================================================
key                         better   what it is
==========================  =======  ===========================================================================
``sw_patches``              lower    sliced-Wasserstein distance of 7x7 patches to the painting at the cameras'
                                     size: a render at twice the size, area-downsampled by 2
``sw_patches_half``         lower    the same, downsampled by 4 (half the size: strokes)
``sw_patches_quarter``      lower    the same, downsampled by 8 (a quarter: flat areas, what a person takes in)
``sw_colors``               lower    sliced-Wasserstein distance of the colours to the painting
``ssim``                    higher   SSIM to the base render of the same camera
``structure``               higher   gradient-structure similarity to the base render
``texture_kept``            lower    correlation of the luminance high-pass with the base render's, 4 px inside
                                     the silhouette (1: the capture's fine texture all kept; about 0: replaced)
``texture_kept_2x``         lower    the same on renders at twice the size (8 px inside): detail finer than the
                                     fit size, which only a closer look shows (a capture's sub-pixel texture)
``shapes``                  higher   SSIM of the luminance blurred by a Gaussian of sigma 3 px (1: same forms)
``forms``                   higher   SSIM's structure term alone on that blurred luminance (1: the same forms, at any
                                     brightness and contrast of the palette)
``marks_fine``              near 1   mark contrast: the luminance band-pass (difference of Gaussians, sigma 0.6/1.2
                                     px) of the 2x render area-downsampled by 2, less what the base render's same
                                     band explains (least squares), 4 px inside the silhouette; its deviation over
                                     the painting's own at the run's Stroke Size (1: marks as strong as the
                                     painting's; about 0: none, or only the capture's texture)
``marks_mid``               near 1   the same at sigma 1.2/2.4 px
``marks_coarse``            near 1   the same at sigma 2.4/4.8 px
``mark_elongation``         near 1   how long the marks run for their width: the fine band's correlation length along
                                     the local mark direction over that across it (``metrics.mark_length``), 4 px
                                     inside the silhouette, over the painting's own at the run's Stroke Size (1:
                                     strokes as elongated as the painting's; below: fragments, dabs, blobs)
``short_rmse``              lower    view i warped into view i + 1 with the rendered depth, masked RMSE
``long_rmse``               lower    the same into view i + N // 2 (opposite views on a ring)
==========================  =======  ===========================================================================

The painting is resampled to each size it is compared at by :func:`painting_at` (its shorter side to the
render's), with the coverage of the 2x renders area-downsampled alike, so a 7x7 window sees the same share
of the painting at every scale. Mark contrast compares with the painting as the stylizer paints with it: resampled
to the view's size x Stroke Size (``loop.style_size``), whole.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..method.config import DEFAULT_PRESET, PRESETS
from ..scene.camera import Camera
from ..scene.gaussians import GaussianScene
from ..util.errors import ConfigError, NumericalError
from . import metrics

SCALES = (("sw_patches", 2), ("sw_patches_half", 4), ("sw_patches_quarter", 8))  # downsampling of the 2x render
MARK_KEYS = tuple(name for name, _, _ in metrics.MARK_BANDS)  # marks_fine, marks_mid, marks_coarse
PER_VIEW_KEYS = (
    "sw_colors",
    "ssim",
    "structure",
    "texture_kept",
    "texture_kept_2x",
    "shapes",
    "forms",
    *MARK_KEYS,
    "mark_elongation",
)
KEYS = (*(key for key, _ in SCALES), *PER_VIEW_KEYS, "short_rmse", "long_rmse")


@dataclass(frozen=True)
class Renders:
    """One scene rendered from each camera: rgb [3, H, W], alpha [H, W], depth [H, W], on the CPU."""

    rgb: list[torch.Tensor]
    alpha: list[torch.Tensor]
    depth: list[torch.Tensor]


@dataclass(frozen=True)
class BaseViews:
    """What the base scene gives every evaluation: its renders, and its 2x renders' colours [3, 2H, 2W] and coverage
    [2H, 2W]."""

    cameras: list[Camera]
    renders: Renders
    alpha_2x: list[torch.Tensor]
    rgb_2x: list[torch.Tensor]


@dataclass
class ViewEvaluation:
    """The measurements of one stylized scene; ``mean`` holds every key of :data:`KEYS`."""

    mean: dict[str, float | None]
    per_view: dict[str, list[float]]  # the keys of SCALES and PER_VIEW_KEYS, one value per camera
    short: metrics.ConsistencyResult
    long: metrics.ConsistencyResult
    renders: Renders  # the stylized scene at the cameras' size
    renders_2x: list[torch.Tensor]  # the stylized scene at twice the size [3, 2H, 2W] (figures)
    style_size: tuple[int, int]  # (width, height) of the painting the colours were compared with


def _render(scene: GaussianScene, camera: Camera, settings, device, label: str, covariances):
    from ..raster import RasterSettings, render_scene

    out = render_scene(scene, camera, settings or RasterSettings(), device=device, covariances=covariances)
    if not bool(out.rgb.isfinite().all()):
        raise NumericalError(f"{label}: the render of camera {camera.name or '?'} has non-finite values")
    return out


def render_views(
    scene: GaussianScene, cameras: Sequence[Camera], settings=None, device="cpu", label="scene", covariances=None
) -> Renders:
    """``scene`` from each of ``cameras``; NumericalError when a render has a non-finite value. ``covariances``:
    the scene's (``raster.scene_covariances``), if made already."""
    from ..raster import scene_covariances

    covariances = scene_covariances(scene, device) if covariances is None else covariances
    outs = [_render(scene, camera, settings, device, label, covariances) for camera in cameras]
    return Renders(
        [o.rgb.float().permute(2, 0, 1).cpu() for o in outs],
        [o.alpha.float().cpu() for o in outs],
        [o.depth.float().cpu() for o in outs],
    )


def _twice(camera: Camera) -> Camera:
    return camera.resized(2 * camera.width, 2 * camera.height)


def base_views(base: GaussianScene, cameras: Sequence[Camera], settings=None, device="cpu") -> BaseViews:
    """Render the base scene once for any number of :func:`evaluate_views` calls on the same cameras."""
    from ..raster import scene_covariances

    cameras = list(cameras)
    covariances = scene_covariances(base, device)
    large = [_render(base, _twice(c), settings, device, "base scene", covariances) for c in cameras]
    alpha_2x = [r.alpha.float().cpu() for r in large]
    rgb_2x = [r.rgb.float().permute(2, 0, 1).cpu() for r in large]
    renders = render_views(base, cameras, settings, device, "base scene", covariances)
    return BaseViews(cameras, renders, alpha_2x, rgb_2x)


def check_camera_sizes(cameras: Sequence[Camera], patch: int = 7) -> None:
    """ConfigError unless every camera, at a quarter of its size (the coarsest patch scale), holds a patch."""
    small = [c for c in cameras if min(c.width, c.height) // 4 < patch]
    if small:
        c = small[0]
        raise ConfigError(
            f"camera {c.name or '?'} is {c.width}x{c.height}: at a quarter of that size (the coarsest style scale) "
            f"it is smaller than a patch ({patch} px); use at least {4 * patch} pixels a side"
        )


def painting_at(painting: torch.Tensor, width: int, height: int) -> torch.Tensor:  # [3, h, w] -> [3, h', w']
    """The painting resampled (aspect kept) so that its shorter side matches the shorter side of a width x
    height render."""
    from ..util.imageio import resize_image

    h, w = painting.shape[1:]
    factor = min(width, height) / min(w, h)
    return resize_image(painting, max(1, round(w * factor)), max(1, round(h * factor)))


def painting_for_marks(painting: torch.Tensor, width: int, height: int, stroke_size: float) -> torch.Tensor:
    """The painting as the stylizer paints a width x height view with it: resampled (stretched) to that size x Stroke
    Size, each side rounded, as ``loop.style_size`` and the loop's resampling do."""
    size = (max(1, round(stroke_size * height)), max(1, round(stroke_size * width)))
    if tuple(painting.shape[1:]) == size:
        return painting
    resized = F.interpolate(painting[None], size=size, mode="bilinear", antialias=True, align_corners=False)
    return resized[0].clamp(0, 1)


def path_consistency(
    renders: Renders,
    cameras: Sequence[Camera],
    depth_tolerance: float = metrics.DEPTH_TOLERANCE,
    alpha_threshold: float = metrics.ALPHA_THRESHOLD,
) -> tuple[metrics.ConsistencyResult, metrics.ConsistencyResult]:
    """Short- (gap 1) and long-range (gap N // 2) :func:`~.metrics.consistency_rmse` along the camera path."""
    images = [rgb.permute(1, 2, 0) for rgb in renders.rgb]
    n = len(cameras)
    return tuple(
        metrics.consistency_rmse(
            images, renders.depth, renders.alpha, list(cameras), gap, depth_tolerance, alpha_threshold
        )
        for gap in (1, max(1, n // 2))
    )


def evaluate_views(
    stylized: GaussianScene,
    base: BaseViews,
    painting: np.ndarray,  # [H, W, 3]
    settings=None,
    device="cpu",
    *,
    patch: int = 7,
    projections: int = 128,
    seed: int = 0,
    color_samples: int = 65536,
    patch_samples: int = 16384,
    depth_tolerance: float = metrics.DEPTH_TOLERANCE,
    alpha_threshold: float = metrics.ALPHA_THRESHOLD,
    stroke_size: float = PRESETS[DEFAULT_PRESET].stroke_size,
) -> ViewEvaluation:
    """Measure ``stylized`` against the painting and the base scene on ``base.cameras`` (the keys of :data:`KEYS`).

    ``settings`` (RasterSettings) and ``device`` are the rasterizer's; ``depth_tolerance`` and
    ``alpha_threshold`` are the consistency warp's occlusion and opacity tests; ``stroke_size`` is the run's Stroke
    Size (the painting's scale for mark contrast; the default preset's for scenes no stylizer run made); the rest
    are the sliced Wasserstein distances' (:mod:`dresg_addon.method.style_distance`).
    """
    cameras = base.cameras
    check_camera_sizes(cameras, patch)
    if isinstance(stroke_size, bool) or not isinstance(stroke_size, int | float) or not 0.0 < stroke_size < math.inf:
        raise ConfigError(f"stroke size must be a positive number, got {stroke_size!r}")
    from ..raster import scene_covariances

    covariances = scene_covariances(stylized, device)
    ours = render_views(stylized, cameras, settings, device, "stylized scene", covariances)
    masks = base.renders.alpha
    painting_t = torch.from_numpy(painting).permute(2, 0, 1).contiguous()
    style = painting_at(painting_t, cameras[0].width, cameras[0].height)
    large = [_render(stylized, _twice(c), settings, device, "stylized scene", covariances).rgb for c in cameras]
    large = [image.float().permute(2, 0, 1).cpu() for image in large]
    per_view, downsampled = {}, {}
    for key, factor in SCALES:
        small = [F.avg_pool2d(image[None], factor)[0] for image in large]
        alphas = [F.avg_pool2d(mask[None, None], factor)[0, 0] for mask in base.alpha_2x]
        downsampled[factor] = small, alphas
        reference = painting_at(painting_t, small[0].shape[2], small[0].shape[1])
        per_view[key] = metrics.sliced_wasserstein_patches(
            small, reference, patch, projections, seed, patch_samples, masks=alphas
        )
    per_view["sw_colors"] = metrics.sliced_wasserstein_colors(
        ours.rgb, style, projections, seed, color_samples, masks=masks
    )
    pairs = list(zip(ours.rgb, base.renders.rgb, masks))
    for key, measure in (
        ("ssim", metrics.ssim_per_image),
        ("structure", metrics.gradient_structure_similarity),
        ("texture_kept", metrics.texture_kept),
        ("shapes", metrics.shape_similarity),
        ("forms", metrics.forms_similarity),
    ):
        per_view[key] = torch.stack([measure(a, b, mask=m) for a, b, m in pairs])
    per_view.update(zip(MARK_KEYS, _mark_contrast(painting_t, *downsampled[2], base.rgb_2x, stroke_size).T))
    per_view["mark_elongation"] = _mark_elongation(painting_t, *downsampled[2], stroke_size)
    per_view["texture_kept_2x"] = torch.stack(
        [metrics.texture_kept(a, b, mask=m, erode=8) for a, b, m in zip(large, base.rgb_2x, base.alpha_2x)]
    )
    short, long = path_consistency(ours, cameras, depth_tolerance, alpha_threshold)
    mean = {key: float(per_view[key].mean()) for key in KEYS[:-2]}
    return ViewEvaluation(
        {**mean, "short_rmse": short.rmse, "long_rmse": long.rmse},
        {key: [float(v) for v in values] for key, values in per_view.items()},
        short,
        long,
        ours,
        large,
        (int(style.shape[2]), int(style.shape[1])),
    )


def _mark_elongation(
    painting: torch.Tensor,  # [3, h, w]
    renders: list[torch.Tensor],  # the stylized 2x renders area-downsampled by 2, [3, H, W]
    alphas: list[torch.Tensor],  # the base's 2x coverage area-downsampled alike, [H, W]
    stroke_size: float,
) -> torch.Tensor:  # [views]
    """Every view's marks' length over their width (:func:`~.metrics.mark_length`, along / across) at the fit size,
    over the painting's at its Stroke Size (0 where either has no marks to measure)."""

    def elongation(image: torch.Tensor, mask=None) -> float:
        along, across = metrics.mark_length(image, mask)
        return along / across if across > 0 else 0.0

    own, values = {}, []
    for image, alpha in zip(renders, alphas):
        height, width = image.shape[1:]
        if (width, height) not in own:
            own[width, height] = elongation(painting_for_marks(painting, width, height, stroke_size))
        values.append(elongation(image, alpha) / own[width, height] if own[width, height] > 0 else 0.0)
    return torch.tensor(values, dtype=torch.float64)


def _mark_contrast(
    painting: torch.Tensor,  # [3, h, w]
    renders: list[torch.Tensor],  # the stylized 2x renders area-downsampled by 2, [3, H, W]
    alphas: list[torch.Tensor],  # the base's 2x coverage area-downsampled alike, [H, W]
    base_2x: list[torch.Tensor],  # the base's 2x renders [3, 2H, 2W]
    stroke_size: float,
) -> torch.Tensor:  # [views, len(MARK_KEYS)]
    """:func:`~.metrics.mark_contrast` of every view at the fit size, against the painting at its Stroke Size."""
    at_size = {}
    values = []
    for image, alpha, base in zip(renders, alphas, base_2x):
        height, width = image.shape[1:]
        if (width, height) not in at_size:
            at_size[width, height] = painting_for_marks(painting, width, height, stroke_size)
        base_small = F.avg_pool2d(base[None], 2)[0]
        values.append(metrics.mark_contrast(image, base_small, at_size[width, height], mask=alpha))
    return torch.stack(values)
