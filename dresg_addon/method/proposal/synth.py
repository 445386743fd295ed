"""The weight-free ``synth`` proposal backend: example-based synthesis that pastes the painting's strokes.

Style transfer by texture synthesis (Elad and Milanfar, "Style Transfer via Texture Synthesis", IEEE
TIP 2017), built on the EM texture optimisation of Kwatra et al. (SIGGRAPH 2005). One synthesis pass at
a pyramid level and a patch size is:

1. matching: each estimate patch on a grid (gap smaller than the patch, random grid offset per pass) to
   its nearest style patch, L2 distance in a PCA subspace of the style's patches, searched exhaustively
   by chunked matrix multiplies (:func:`nearest_patches`);
2. robust aggregation: X~ = argmin_X sum_ij ||R_ij X - z_ij||^r by IRLS, weights ||R_ij X - z_ij||^(r-2)
   (:func:`robust_aggregate`);
3. content fusion, below the stroke scale only: X = X~ + W / (1 + W) (blur(C') - blur(X~)), C' the content
   colour-transferred to the style, W a constant plus the edge strength where the content's luminance and the
   view's rendered depth both have an edge (the scene's outlines and creases, not a texture painted on a surface:
   :func:`fusion_edges`), the blur a Gaussian of ``content_sigma`` pixels (:func:`fuse_content`,
   :func:`content_weight_map`). The scene's forms, regions and light come through where Elad and Milanfar's
   (X~ + W C') / (1 + W) brings them; the capture's own texture finer than the strokes (a knit cloth, a
   checkerboard) does not, so the texture there is the painting's. Fused at every band, it survived in the
   painting's palette: on the bonsai x Starry Night (``preview``, novel views) the capture's high-pass
   correlated 0.64 with the result, 0.24 at sigma 3;
4. colour transfer of X to the style: covariance transfer, then histogram matching along the style's
   colour principal axes (``color_transfer.match_color_histograms``).

After the last pass, with ``light_weight`` > 0, the scene's light is held: the proposal's luminance above the
content sigma pulled that share of the way to the content's, the colours matched to the painting again
(:func:`hold_light`; with ``final_match`` the colours are matched again without the hold). The fusion's pull is W / (1 + W), about 0.2 in flat regions, so there the painting's
marks set the light as well as the texture; held, the scene's shading and regions come through under the marks.

How the paper's quantities map onto it (Sec. 4.1, Algorithm 1 lines 3-5):

- State z^{r,v}: the image itself at the proposal resolution; ``encode`` and ``decode`` are the identity
  (clamped to [0, 1]). Each stage starts from that stage's render, which already carries the scene's
  earlier stylization (feedback), so the synthesis refines what the scene has become.
- One latent update = one synthesis pass; S updates per stage = S passes. The passes do not run at
  diffusion timesteps: the synthesis has its own ladder of scales, (level, patch size) pairs from coarse
  to fine (:func:`scale_ladder`: level 2 with patches 33, 21, 13, 9, then level 1, then full resolution),
  which the run walks as the paper's denoising walks from coarse features at high noise to fine ones at
  low noise. Stage n of F enters the ladder at the fraction e_n = (n - 1) / (F - 1) of its length
  (:func:`ladder_entry`): the first stage at the coarsest rung, the last at the finest, evenly between;
  its passes run from there down to full resolution and the smallest patch (:func:`pass_scales`), as a
  denoising run from the stage's noise level would (SDEdit-like). With one pass per stage (``standard``'s
  12) the run takes every rung once. Early stages re-synthesize strokes and shapes from coarse levels;
  late ones only refine brush texture at full resolution. Images too small for a level use the levels
  they have.
- Noise: the first pass of a stage matches from the estimate plus Gaussian noise of standard deviation
  ``noise x sqrt(1 - e_n)``, falling with the stage's rung as the forward process's sqrt(1 - abar) falls
  with the timestep (Elad and Milanfar start from the content plus noise of 50 grey levels), so early
  stages invent strokes in flat regions and the last does not.
- Proposal-render residual: the proposal is the synthesis, and gamma_k acts on its whole residual as in
  Eq. 12. At half strength (the target half-way to the synthesis where gamma_k is
  1) every stage's target kept half of the render's own texture, which is the capture's: on the bonsai
  x Starry Night (``preview``) the novel views kept 0.24 of it at half strength and 0.16 at full, and
  came 2-4% closer to the painting at every scale.
- A stage that ends at a coarse level (the early, noisy ones) proposes the coarse bands only, upsampled:
  the render's finer bands are not added back, since they are the capture's texture until the fine
  stages have painted over it.
- Views that agree (``guide``): the loop synthesizes the active views one after another, and each view
  after the first gets what the earlier views synthesized, reprojected into it by rendered depth
  (:mod:`..guides`). The guide is the starting estimate where it is valid and a fusion term in every
  pass, X = (X~' (1 + W) + G P) / (1 + W + G) with X~' the content-fused synthesis, so the patch matching reproduces strokes already placed
  on a surface instead of inventing new ones there (Jamriška et al. 2019 guide a video's frames by the
  previous one in the same way). Without it each view pastes strokes, and at coarse levels whole motifs
  of the painting (a cypress, a village), in its own places, and fitting one scene to all of them
  averages them into smears and ghosts.
- E^attn: the reported energy is the synthesis energy, the mean over matched patches of
  ||R_ij X - z_ij||^r per pixel value, before the pass's update.
- w_c (content weight): the weight of the content fusion, W = w_c (edge_floor + edge_gain x edge), with
  the edges taken at a coarse level (outlines and shading, not the photo's texture); the artist sets it
  as Paint <-> Scene. The content view I^{c,v} is the photo or the base render, as for every backend.
- Stroke Size: the loop hands the painting at that multiple of the view's size, and the content sigma
  scaled by it, so larger marks also take the scene's texture out up to their own size.
- Colour across views: ``prepare_stage`` fits two colour maps on all active views at once
  (``color_transfer.fit_color_map``: covariance transfer plus one histogram curve per style colour
  axis), one for the stage's renders and one for the content views; each proposal starts from its
  render recoloured by the first and fuses with its content recoloured by the second, so a surface gets
  the same colours in every view. Only the colour correction after each pass is per view (it keeps the
  palette on the painting's; leaving it out doubled the style distance on the bonsai).
- gamma_k, the residual targets, the multi-view fitting with PCGrad and the feedback are the pipeline's,
  unchanged.

Where the proposal comes from (``last_field``, for the splats to carry the marks: ``marks.py``): each pixel of the
last pass takes one of the matched patches that cover it, the boundaries between neighbouring patches cut where
their colours agree (:func:`seam_cut`: image quilting's minimum error boundary cut, Efros and Freeman 2001, with
Kwatra et al.'s seam cost, 2003), not on the straight line half-way between their centres.

Alpha-aware: with a coverage map (the render's alpha), only covered pixels take part in colour statistics
and matching (uncovered pixels are filled in smoothly from covered ones, and patches with no covered
pixel are left out), and the proposal changes a pixel by ``color_transfer.coverage_weight`` of its alpha:
the background, and faint floaters over it, stay as rendered. Deterministic for a seed: every random
draw comes from a generator seeded by the seed, the stage, the pass and a digest of the content.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, fields, replace

import numpy as np
import torch
import torch.nn.functional as F

from ...util.errors import ConfigError, NumericalError
from ..color_transfer import (
    ColorMap,
    StyleQuantiles,
    covariance_color_transform,
    coverage_weight,
    fit_color_map,
    luminance,
    match_color_histograms,
)
from ..schedule import Stage
from .base import ProposalBackend

LIBRARY_CACHE_SIZE = 12
LIBRARY_CHUNK_VALUES = 1 << 22  # patch values gathered at once while projecting a library (16 MB)
COVERED = 0.5  # coverage above which a pixel counts in colour statistics and patch selection
EDGE_SIGMA = 1.5  # blur of the content's gradient magnitude, in pixels of the working level
IRLS_EPS = 1e-6  # keeps ||R X - z||^(r - 2) finite for a patch matched exactly


@dataclass(frozen=True)
class SynthSettings:
    """Settings of the ``synth`` backend (Elad and Milanfar's values at ~400x400 where they give one)."""

    seed: int = 0
    max_levels: int = 3  # pyramid levels (factor 2); fewer when the image is small
    coarsest_side: int = 64  # a level is used only while its shorter side is at least this many pixels
    patch_sizes: tuple[int, ...] = (33, 21, 13, 9)  # large (shapes, strokes) to small (texture)
    gap_ratio: float = 0.6  # grid gap / patch size (33:20, 21:13, 13:8, 9:5)
    library_size: int = 24000  # style patches per (level, size), a horizontally flipped copy included
    pca_dims: int = 32
    pca_sample: int = 4096
    robust_power: float = 0.8  # r of the IRLS aggregation
    irls_iterations: int = 3
    content_weight: float = 0.3  # w_c of the fusion W = w_c (edge_floor + edge_gain x edge); runs pass their config's
    edge_floor: float = 0.3
    edge_gain: float = 3.0
    edge_level: int = 2  # pyramid level whose edges set the content weight (outlines, not texture)
    # The content acts only through a Gaussian of this sigma (pixels at full resolution, at Stroke Size 1): the
    # scene's forms, regions and light above it, the painting's texture below it. 0 fuses every band, the
    # capture's fine texture too (bonsai x Starry Night, preview: texture kept 0.64 at 0, 0.24 at 3).
    content_sigma: float = 3.0
    # The scene's light held: each proposal's luminance above the content sigma pulled this share of the way to the
    # content's (colour-transferred) and its colours matched to the painting again (:func:`hold_light`). 0: the
    # fusion's W / (1 + W) alone, which in flat regions (W 0.3) lets the painting repaint the scene's shading.
    light_weight: float = 0.0
    # The proposal's colours matched to the painting once more after the last pass, at full resolution (and after
    # the light is held, which always does it): a stage that ends on a coarse level then proposes the painting's
    # palette, not its upsampled blur.
    final_match: bool = False
    noise: float = 50.0 / 255.0  # matching noise of a stage's first pass, x sqrt(1 - its ladder entry)
    histogram_matching: bool = True
    search_chunk: int = 2048  # estimate patches per matrix multiply of the nearest-patch search

    def check(self) -> None:
        """Raise ConfigError for values that cannot work."""
        if self.max_levels < 1 or self.coarsest_side < 1:
            raise ConfigError("synth backend: max_levels and coarsest_side must be at least 1")
        if not self.patch_sizes or min(self.patch_sizes) < 1:
            raise ConfigError(f"synth backend: patch sizes must be at least 1, got {self.patch_sizes}")
        if not 0.0 < self.gap_ratio <= 1.0:
            raise ConfigError(f"synth backend: gap_ratio must be in (0, 1], got {self.gap_ratio}")
        if self.library_size < 2:
            raise ConfigError("synth backend: library_size must be at least 2 (a patch and its mirror image)")
        if self.pca_dims < 1 or self.pca_sample < 1 or self.search_chunk < 1:
            raise ConfigError("synth backend: pca_dims, pca_sample and search_chunk must be >= 1")
        if not 0.0 < self.robust_power <= 2.0:
            raise ConfigError(f"synth backend: robust_power must be in (0, 2], got {self.robust_power}")
        if self.irls_iterations < 1:
            raise ConfigError("synth backend: irls_iterations must be at least 1")
        if self.edge_level < 0:
            raise ConfigError(f"synth backend: edge_level must be >= 0, got {self.edge_level}")
        if not (math.isfinite(self.light_weight) and 0.0 <= self.light_weight <= 1.0):
            raise ConfigError(f"synth backend: light_weight must be in [0, 1], got {self.light_weight}")
        for name in ("content_weight", "edge_floor", "edge_gain", "noise", "content_sigma"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ConfigError(f"synth backend: {name} must be finite and >= 0, got {getattr(self, name)}")


# --- Patches on a grid ---------------------------------------------------------------------------------


def patch_grid(height: int, width: int, size: int, gap: int, offset: tuple[int, int] = (0, 0)):
    """Top-left corners (ys [a], xs [b]) of a patch grid that covers every pixel of an H x W image.

    Corners step by ``gap`` from ``offset`` (taken modulo the gap), and the first and last possible
    corners (0 and H - size) are always included, so the border is covered whatever the offset.
    """
    if size > min(height, width):
        raise ValueError(f"patch size {size} is larger than the {width}x{height} image")

    def axis(length: int, shift: int) -> torch.Tensor:
        last = length - size
        starts = torch.arange(min(shift % gap, last), last + 1, gap)
        return torch.unique(torch.cat([torch.tensor([0, last]), starts]))

    return axis(height, offset[0]), axis(width, offset[1])


def patch_index(ys: torch.Tensor, xs: torch.Tensor, size: int, width: int) -> torch.Tensor:  # -> [P, size^2]
    """Flat pixel indices of the patches with top-left corners on the grid ys x xs (row-major patches)."""
    top = (ys[:, None] * width + xs[None, :]).reshape(-1)  # [P]
    offsets = (torch.arange(size)[:, None] * width + torch.arange(size)[None, :]).reshape(-1)
    return top[:, None] + offsets[None, :]


def extract_patches(image: torch.Tensor, index: torch.Tensor) -> torch.Tensor:  # [C, H, W], [P, s^2] -> [P, C s^2]
    """The patches of ``image`` at ``index`` as rows, channel-major (all of R, then G, then B)."""
    channels = image.shape[0]
    flat = image.reshape(channels, -1)
    return flat[:, index].permute(1, 0, 2).reshape(index.shape[0], -1)


def aggregate_patches(
    patches: torch.Tensor,  # [P, C s^2]
    index: torch.Tensor,  # [P, s^2]
    weights: torch.Tensor,  # [P]
    shape: tuple[int, int, int],  # (C, H, W)
) -> tuple[torch.Tensor, torch.Tensor]:  # [C, H, W] weighted sum, [H, W] weight sum
    """sum_ij w_ij R_ij^T z_ij and sum_ij w_ij R_ij^T 1: the two sides of the weighted patch average."""
    channels, height, width = shape
    count, pixels = index.shape
    values = (patches.reshape(count, channels, pixels) * weights[:, None, None]).permute(1, 0, 2).reshape(channels, -1)
    total = torch.zeros(channels, height * width, dtype=patches.dtype)
    total.index_add_(1, index.reshape(-1), values)
    weight = torch.zeros(height * width, dtype=patches.dtype)
    weight.index_add_(0, index.reshape(-1), weights[:, None].expand(count, pixels).reshape(-1))
    return total.reshape(shape), weight.reshape(height, width)


def irls_weights(residual_norms: torch.Tensor, power: float) -> torch.Tensor:  # [P] -> [P]
    """IRLS weights ||R_ij X - z_ij||^(r - 2) of min sum ||R_ij X - z_ij||^r, floored at IRLS_EPS inside."""
    return (residual_norms.square() + IRLS_EPS).pow((power - 2.0) / 2.0)


def robust_aggregate(
    estimate: torch.Tensor,  # [C, H, W] the current X
    matches: torch.Tensor,  # [P, C s^2] z_ij
    index: torch.Tensor,  # [P, s^2]
    power: float,
    iterations: int,
) -> torch.Tensor:  # [C, H, W]
    """X~ = argmin_X sum_ij ||R_ij X - z_ij||^r by IRLS, started from the plain average (Elad and Milanfar).

    Pixels that no patch covers keep the estimate's value. r = 2 is the plain average.
    """
    shape = tuple(estimate.shape)
    weights = torch.ones(matches.shape[0], dtype=matches.dtype)
    x = estimate
    for iteration in range(iterations + 1):
        total, weight = aggregate_patches(matches, index, weights, shape)
        covered = weight > 0
        x = torch.where(covered, total / weight.clamp_min(1e-30), estimate)
        if iteration == iterations or power == 2.0:
            break
        norms = (extract_patches(x, index) - matches).norm(dim=1)
        weights = irls_weights(norms, power)
    return x


# --- Nearest style patches in a PCA subspace -----------------------------------------------------------


def pca_basis(samples: torch.Tensor, dims: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean [D] and orthonormal basis [D, d] of the top principal directions of ``samples`` [n, D].

    Randomised range finder (Halko et al.) with two power iterations on the centred samples, then an
    exact SVD in the small subspace; d = min(dims, n, D). Seeded through ``generator``.
    """
    mean = samples.mean(0)
    centred = (samples - mean).double()
    n, d_full = centred.shape
    dims = max(1, min(dims, n, d_full))
    sketch = min(d_full, dims + 8)
    probe = torch.randn(d_full, sketch, generator=generator, dtype=torch.float64)
    basis = torch.linalg.qr(centred @ probe).Q  # [n, sketch]
    for _ in range(2):
        basis = torch.linalg.qr(centred.T @ basis).Q
        basis = torch.linalg.qr(centred @ basis).Q
    _, _, vh = torch.linalg.svd(basis.T @ centred, full_matrices=False)
    return mean, vh[:dims].T.to(samples.dtype).contiguous()


def nearest_patches(queries: torch.Tensor, library: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
    """Index [P] of the nearest library row (L2) for each query row: queries [P, d], library [L, d].

    Exhaustive: ||q - l||^2 = ||l||^2 - 2 q.l + const per query, one matrix multiply per chunk of queries.
    Ties go to the lowest index.
    """
    norms = library.square().sum(1)  # [L]
    out = torch.empty(queries.shape[0], dtype=torch.long)
    for start in range(0, queries.shape[0], chunk):
        block = queries[start : start + chunk]
        out[start : start + chunk] = torch.addmm(norms[None, :], block, library.T, alpha=-2.0).argmin(1)
    return out


@dataclass
class StyleLibrary:
    """Style patches of one size at one pyramid level, kept as positions (not pixels) with their PCA projection.

    A row is a patch of the style or of its mirror image, found by its top-left pixel in ``source`` (the
    two images side by side in memory); the pixels of a row are gathered only when it is matched, so a
    library of 24k 33x33 patches costs 3 MB of projections instead of 300 MB of pixels.
    """

    size: int
    width: int  # of the style image at this level
    source: torch.Tensor  # [3, 2 H W]: the style, then its mirror image, flattened
    corners: torch.Tensor  # [L] flat index of each patch's top-left pixel in source
    mean: torch.Tensor  # [3 s^2]
    basis: torch.Tensor  # [3 s^2, d]
    projected: torch.Tensor  # [L, d]

    def __len__(self) -> int:
        return self.corners.numel()

    def patches(self, rows: torch.Tensor | None = None) -> torch.Tensor:  # [R] -> [R, 3 s^2] (all rows: None)
        corners = self.corners if rows is None else self.corners[rows]
        offsets = (torch.arange(self.size)[:, None] * self.width + torch.arange(self.size)[None, :]).reshape(-1)
        index = corners[:, None] + offsets[None, :]
        return self.source[:, index].permute(1, 0, 2).reshape(index.shape[0], -1)

    def project(self, patches: torch.Tensor) -> torch.Tensor:  # [P, 3 s^2] -> [P, d]
        return (patches - self.mean) @ self.basis


def build_library(style: torch.Tensor, size: int, settings: SynthSettings, generator: torch.Generator) -> StyleLibrary:
    """All ``size`` patches of ``style`` [3, H, W] and of its mirror image, a seeded subset above the cap."""
    _, height, width = style.shape
    columns = width - size + 1
    positions = (height - size + 1) * columns
    half = settings.library_size // 2
    chosen = torch.arange(positions)
    if positions > half:
        chosen = torch.randperm(positions, generator=generator)[:half].sort().values
    top_left = (chosen // columns) * width + chosen % columns
    corners = torch.cat([top_left, top_left + height * width])  # the second half lies in the mirror image
    source = torch.cat([style.reshape(3, -1), style.flip(-1).reshape(3, -1)], 1).contiguous()
    library = StyleLibrary(size, width, source, corners, torch.zeros(0), torch.zeros(0), torch.zeros(0))
    rows = torch.arange(len(library))
    if len(library) > settings.pca_sample:
        rows = torch.randperm(len(library), generator=generator)[: settings.pca_sample]
    library.mean, library.basis = pca_basis(library.patches(rows), settings.pca_dims, generator)
    chunk = max(1, LIBRARY_CHUNK_VALUES // library.mean.numel())
    library.projected = torch.cat(
        [
            library.project(library.patches(torch.arange(i, min(i + chunk, len(library)))))
            for i in range(0, len(library), chunk)
        ]
    ).contiguous()
    return library


# --- Scale, content and colour ---------------------------------------------------------------------------


PASS_OVERHEAD = 2.6  # a pass's cost that does not shrink with its level, in full-resolution pixels' (relative_cost)


def pyramid_levels(height: int, width: int, settings: SynthSettings) -> int:
    """How many levels (factor 2) the image has whose shorter side is at least ``coarsest_side``."""
    side = min(height, width)
    levels = 1
    while levels < settings.max_levels and side // 2**levels >= settings.coarsest_side:
        levels += 1
    return levels


def scale_ladder(levels: int, settings: SynthSettings) -> list[tuple[int, int]]:
    """(level, patch size) from coarsest to finest: every patch size at every level, as Elad and Milanfar run."""
    return [(level, size) for level in range(levels - 1, -1, -1) for size in settings.patch_sizes]


def ladder_entry(stage: Stage) -> float:
    """Where stage n of F enters the ladder, as a fraction of its length: e_n = (n - 1) / (F - 1).

    The first stage starts at the coarsest rung and the last at the finest, evenly between. A lone stage
    starts at the coarsest, or, with a single pass (the run's last), at the finest.
    """
    if stage.stages == 1:
        return 1.0 if stage.updates == 1 else 0.0
    return (stage.index - 1) / (stage.stages - 1)


def pass_scales(entry: float, passes: int, levels: int, settings: SynthSettings) -> list[tuple[int, int]]:
    """(level, patch size) of each pass of a stage that enters the ladder at ``entry`` (in [0, 1]).

    Pass j stands at x_j = e + (1 - e) j / (P - 1), from the stage's entry to the ladder's end, as a
    denoising run from the stage's noise level would; x_j picks the rung floor(x_j x len(ladder)) of
    :func:`scale_ladder` (the last at 1): coarse levels and large patches first, full resolution and
    small patches last. A stage of one pass stays at its entry.
    """
    ladder = scale_ladder(levels, settings)
    e = min(max(float(entry), 0.0), 1.0)
    out = []
    for j in range(passes):
        x_j = e + (1.0 - e) * j / (passes - 1) if passes > 1 else e
        out.append(ladder[min(len(ladder) - 1, int(x_j * len(ladder)))])
    return out


def downsample(image: torch.Tensor, level: int) -> torch.Tensor:  # [C, H, W] -> [C, H / 2^level, W / 2^level]
    if level == 0:
        return image
    height, width = image.shape[-2:]
    size = (max(1, height // 2**level), max(1, width // 2**level))
    return F.interpolate(image[None], size=size, mode="bilinear", antialias=True, align_corners=False)[0]


def upsample(image: torch.Tensor, height: int, width: int) -> torch.Tensor:  # [C, h, w] -> [C, H, W]
    if image.shape[-2:] == (height, width):
        return image
    return F.interpolate(image[None], size=(height, width), mode="bilinear", align_corners=False)[0]


def _gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:  # [C, H, W], separable, replicated border
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=image.dtype)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = kernel / kernel.sum()
    channels = image.shape[0]
    rows = F.pad(image[None], (0, 0, radius, radius), mode="replicate")
    out = F.conv2d(rows, kernel.reshape(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)
    cols = F.pad(out, (radius, radius, 0, 0), mode="replicate")
    return F.conv2d(cols, kernel.reshape(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)[0]


def fill_uncovered(image: torch.Tensor, coverage: torch.Tensor, sigma: float) -> torch.Tensor:
    """``image`` [C, H, W] with pixels of coverage [H, W] below COVERED replaced by a normalised blur of
    the covered ones (so patches on the silhouette match by what is inside it)."""
    mask = (coverage > COVERED).to(image.dtype)
    if bool(mask.all()):
        return image
    if not bool(mask.any()):
        return image
    num = _gaussian_blur(image * mask, sigma)
    den = _gaussian_blur(mask[None], sigma)[0]
    mean = (image * mask).sum((1, 2)) / mask.sum()
    smooth = torch.where(den > 1e-3, num / den.clamp_min(1e-3), mean[:, None, None])
    return torch.where(mask > 0, image, smooth)


def _gradient_magnitude(image: torch.Tensor) -> torch.Tensor:  # [H, W] -> [H, W], central differences
    gy = torch.zeros_like(image)
    gx = torch.zeros_like(image)
    gy[1:-1] = (image[2:] - image[:-2]) / 2.0
    gx[:, 1:-1] = (image[:, 2:] - image[:, :-2]) / 2.0
    return torch.sqrt(gx.square() + gy.square())


def depth_structure(depth: torch.Tensor) -> torch.Tensor:  # [H, W] -> [1, H, W]
    """The image whose edges are the scene's shape in a view's rendered ``depth`` (0: nothing, taken as 1.5 times the
    farthest depth, so a silhouette is an edge): the gradient magnitude of the inverse depth. The inverse depth is
    affine in the pixel's coordinates on a plane, so this is constant there (one-sided differences at the frame, which
    would otherwise be an edge) and its edges are the outlines and creases; none lie on a flat surface, whatever its
    slant."""
    depth = depth.float()
    far = 1.5 * float(depth.max()) if bool((depth > 0).any()) else 1.0
    inverse = 1.0 / torch.where(depth > 0, depth, torch.full_like(depth, far)).clamp_min(1e-6)
    if min(inverse.shape) < 2:  # a line of pixels has no outline across it
        return torch.zeros_like(inverse)[None]
    gy, gx = torch.gradient(inverse)
    return torch.sqrt(gx.square() + gy.square())[None]


def edge_strength(structure: torch.Tensor) -> torch.Tensor:  # [C, H, W] -> [H, W] in [0, 1]
    """The blurred gradient magnitude of the channels' mean of ``structure``, over its 99th percentile, clipped to
    [0, 1] (1 on strong edges)."""
    return _unit_edges(_gaussian_blur(_gradient_magnitude(structure.mean(0))[None], EDGE_SIGMA)[0])


def _unit_edges(magnitude: torch.Tensor) -> torch.Tensor:
    scale = torch.quantile(magnitude.reshape(-1)[:: max(1, magnitude.numel() // 65536)], 0.99)
    return (magnitude / scale.clamp_min(1e-6)).clamp(0.0, 1.0)


def fusion_edges(content: torch.Tensor, depth: torch.Tensor | None, level: int) -> torch.Tensor:  # -> [H', W']
    """The fusion's edges at pyramid ``level`` (:func:`content_weight_map`), in [0, 1]: the content's luminance
    edges; with the view's rendered ``depth`` [H, W], their geometric mean with the depth's
    (:func:`depth_structure`), renormalised. An edge then needs both: the luminance alone takes a texture painted
    on a flat surface for outlines (the demo's checkerboard came back as the proposals' regions), the depth alone
    takes a dark capture's noisy background for them and loses the outlines whose colour the painting's regions
    should follow (the bonsai after Woman with a Hat: 5 / 15 / 26% further at the three scales)."""
    luminance = edge_strength(downsample(content, level))
    if depth is None:
        return luminance
    shape = edge_strength(downsample(depth_structure(depth), level))
    return _unit_edges(torch.sqrt(luminance * shape))


def content_weight_map(edge: torch.Tensor, settings: SynthSettings) -> torch.Tensor:  # [H, W] -> [H, W]
    """W = w_c (edge_floor + edge_gain x edge), ``edge`` in [0, 1] (:func:`fusion_edges`)."""
    return settings.content_weight * (settings.edge_floor + settings.edge_gain * edge)


def _blend(image: torch.Tensor, other: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(image + weight other) / (1 + weight) per pixel: [C, H, W], [C, H, W], [H, W]."""
    return (image + weight * other) / (1.0 + weight)


def fuse_content(
    synthesis: torch.Tensor,  # [C, H, W] X~
    content_low: torch.Tensor,  # [C, H, W] blur(C', sigma)
    weight: torch.Tensor,  # [H, W] W
    sigma: float,
) -> torch.Tensor:
    """X = X~ + W / (1 + W) (blur(C') - blur(X~)): the content's bands above ``sigma`` pixels pulled in as
    Elad and Milanfar's (X~ + W C') / (1 + W) does for every band, the synthesis's finer bands left alone,
    so texture below the stroke scale is the painting's, not the capture's. sigma 0 is their fusion."""
    return synthesis + weight / (1.0 + weight) * (content_low - low_pass(synthesis, sigma))


def low_pass(image: torch.Tensor, sigma: float) -> torch.Tensor:  # [C, H, W]
    """Gaussian blur of ``sigma`` pixels; below a tenth of a pixel the image itself."""
    return image if sigma < 0.1 else _gaussian_blur(image, sigma)


def hold_light(
    image: torch.Tensor,  # [3, H, W]
    content_low: torch.Tensor,  # [3, H, W] blur(C', sigma)
    weight: float,
    sigma: float,
) -> torch.Tensor:
    """X + w (L(blur(C')) - L(blur(X))): the content's luminance above ``sigma`` pulled a share ``w`` in, the same
    shift on every channel (Rec. 709 weights sum to 1), so the hue, the saturation and every band finer than
    ``sigma`` stay the synthesis's; clamped to [0, 1].

    The fusion's W / (1 + W) is about 0.2 in flat regions, where the painting's marks then set the light as well
    as the texture: a shaded sphere came out in random bright and dark patches, and the demo's proposals were
    further from the painting at a quarter of the size than the colour transfer (patch SW 0.092 against 0.080),
    whose only advantage there is the scene's light (docs/decisions/003-scene-light.md).
    """
    shift = luminance((content_low - low_pass(image, sigma))[None])[0]  # linear: L(a) - L(b) = L(a - b)
    return (image + weight * shift).clamp(0.0, 1.0)


def to_style_colors(
    image: torch.Tensor,  # [3, H, W]
    style: torch.Tensor,  # [3, Hs, Ws]
    coverage: torch.Tensor | None,  # [H, W] or None
    histogram: bool,
    quantiles: StyleQuantiles | None = None,  # the style's, sorted once by a caller that matches many images
) -> torch.Tensor:
    """Covariance colour transfer of the covered pixels to the style, then (optionally) histogram matching
    along the style's colour principal axes; uncovered pixels are returned unchanged. Clamped to [0, 1]."""
    mask = None if coverage is None else coverage > COVERED
    if mask is not None and not bool(mask.any()):
        return image
    transform = covariance_color_transform(image, style, None if mask is None else mask)
    out = transform.apply_to_images(image)
    if histogram:
        pixels = out.permute(1, 2, 0).reshape(-1, 3)
        keep = slice(None) if mask is None else mask.reshape(-1)
        matched = pixels.clone()
        if quantiles is None:
            quantiles = StyleQuantiles.of(style.permute(1, 2, 0).reshape(-1, 3))
        matched[keep] = match_color_histograms(pixels[keep], quantiles).to(pixels.dtype)
        out = matched.reshape(image.shape[1], image.shape[2], 3).permute(2, 0, 1)
    out = out.clamp(0.0, 1.0)
    return out if mask is None else torch.where(mask, out, image)


def recolor(image: torch.Tensor, color_map: ColorMap, coverage: torch.Tensor | None) -> torch.Tensor:
    """``color_map`` applied to the covered pixels of ``image`` [3, H, W] (coverage > COVERED), clamped to [0, 1]."""
    out = color_map.apply_to_images(image).clamp(0.0, 1.0)
    return out if coverage is None else torch.where(coverage > COVERED, out, image)


@dataclass(frozen=True)
class _Matches:
    """Where a pass took its patches from: the grid (ys x xs corners at ``level``, ``kept`` of them matched) and each
    kept patch's top-left pixel in the library's source (the style at that level, its mirror image below it)."""

    level: int
    size: int
    ys: torch.Tensor  # [a]
    xs: torch.Tensor  # [b]
    kept: torch.Tensor  # [a b] bool
    corners: torch.Tensor  # [kept] flat index into the level's source, rows of ``width``
    width: int
    source: torch.Tensor  # [3, 2 h w] the level's style and its mirror image, flattened (``StyleLibrary.source``)
    synthesis: torch.Tensor  # [3, h, w] the pass's robust aggregate of the matched patches at the level


@dataclass(frozen=True)
class PaintingField:
    """Where in the painting each pixel of a proposal comes from: per pixel at the proposal size, a pixel of
    ``source`` (the painting as the backend was given it, its mirror image below it: [3, 2 Hs, Ws]); ``valid`` is
    False where no matched patch covers the pixel. Each pixel takes one of the patches that cover it, chosen by
    :func:`seam_cut`, so the field is piecewise a translation, one per patch."""

    rows: torch.Tensor  # [H, W] long, in [0, 2 Hs)
    cols: torch.Tensor  # [H, W] long, in [0, Ws)
    valid: torch.Tensor  # [H, W] bool
    source: torch.Tensor  # [3, 2 Hs, Ws]


def _nearest_centre(starts: torch.Tensor, size: int, length: int) -> torch.Tensor:  # -> [length] index into starts
    centres = starts.double() + (size - 1) / 2.0
    return torch.bucketize(torch.arange(length, dtype=torch.float64), (centres[1:] + centres[:-1]) / 2.0)


class _PatchColors:
    """The colour each kept patch of a pass puts at any pixel of the level: its translation into the level's source
    carried on past the patch's own pixels (clamped to the painting, or the mirror image, it copies from)."""

    def __init__(self, matched: _Matches):
        grid = torch.nonzero(matched.kept)[:, 0]
        iy, ix = grid // matched.xs.numel(), grid % matched.xs.numel()
        source_rows = matched.corners // matched.width
        self.source_height = matched.source.shape[1] // (2 * matched.width)
        self.half = (source_rows >= self.source_height).long() * self.source_height
        self.shift_rows = source_rows - matched.ys[iy]
        self.shift_cols = matched.corners % matched.width - matched.xs[ix]
        self.source, self.width = matched.source, matched.width

    def at(self, patch: torch.Tensor, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:  # [...] each -> [3, ...]
        top = self.half[patch]
        row = torch.minimum(torch.maximum(y + self.shift_rows[patch], top), top + self.source_height - 1)
        col = (x + self.shift_cols[patch]).clamp(0, self.width - 1)
        return self.source[:, row * self.width + col]


def _color_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # [3, ...] each -> [...]
    """Euclidean distance over the channels (``norm(dim=0)`` reduced the outer dimension 30x slower)."""
    d = a - b
    return (d[0].square() + d[1].square() + d[2].square()).sqrt()


def cheapest_paths(
    error: torch.Tensor,  # [B, L, S] the cost of the path at each place of each row
    from_left: torch.Tensor | None = None,  # [B, L, S] the cost of reaching a place from the place before it
    from_right: torch.Tensor | None = None,  # [B, L, S] ... from the place after it
) -> torch.Tensor:  # [B, L] long in [0, S)
    """For each of B cost surfaces, the path from its first row to its last, one place per row, moving at most one
    place from row to row, whose summed cost is least (dynamic programming: Efros and Freeman 2001's minimum error
    boundary cut). Infinite cost bars a place; ties keep the path straight."""
    # Row by row in numpy, each row's arrays contiguous: its small-array operations cost a tenth of torch's here.
    cost = error.double().transpose(0, 1).contiguous().numpy()  # [L, B, S]
    length, count, span = cost.shape
    moving = from_left is not None
    if moving:
        left_cost = from_left.double().transpose(0, 1).contiguous().numpy()
        right_cost = from_right.double().transpose(0, 1).contiguous().numpy()
    total = cost[0].copy()
    back = np.zeros((length, count, span), dtype=np.int8)
    left, right = np.full((count, span), np.inf), np.full((count, span), np.inf)
    for t in range(1, length):
        left[:, 1:], right[:, :-1] = total[:, :-1], total[:, 1:]
        if moving:
            left += left_cost[t]
            right += right_cost[t]
        from_l = left < total  # strictly: ties keep the path straight
        best = np.where(from_l, left, total)
        from_r = right < best
        back[t] = from_l + 2 * from_r - from_l * from_r  # 0: straight, 1: from the left, 2: from the right
        total = np.where(from_r, right, best) + cost[t]
    path = np.empty((length, count), dtype=np.int64)
    path[-1] = total.argmin(1)
    step = np.array([0, -1, 1])
    boundary = np.arange(count)
    for t in range(length - 1, 0, -1):
        path[t - 1] = path[t] + step[back[t, boundary, path[t]]]
    return torch.from_numpy(path.T.copy())


def _cut_ranges(starts: torch.Tensor, size: int, length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """For each boundary between neighbouring patches along an axis, the first and last place a cut may take (the
    pixels before it the first patch's, from it on the second's): inside both patches, and within half-way to the
    nearest centres' neighbouring cuts, so that cuts never cross. The nearest centres' own place where there is no
    room."""
    owner = _nearest_centre(starts, size, length)
    middle = torch.searchsorted(owner, torch.arange(1, starts.numel()))  # the nearest centres' cuts
    ends = torch.cat([torch.tensor([0]), middle, torch.tensor([length])])
    first = torch.maximum(starts[1:], (ends[:-2] + ends[1:-1] + 1) // 2)
    last = torch.minimum(starts[:-1] + size, (ends[1:-1] + ends[2:]) // 2)
    bad = first > last
    return torch.where(bad, middle, first), torch.where(bad, middle, last)


def _axis_cuts(
    colors: _PatchColors,
    patch_of: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],  # boundary b, row, place -> patch
    first: torch.Tensor,  # [B]
    last: torch.Tensor,  # [B]
    rows: int,
    cut_rows: tuple[int, int],  # the rows that hold matched patches, [start, stop): the others keep ``first``
    length: int,  # of each row
    transpose: bool,
) -> torch.Tensor:  # -> [B, rows]: the cut's place in each row
    """The least-cost cut of each boundary along one axis: Kwatra et al.'s seam cost (2003), how far apart the two
    patches' colours are at the two pixels of each pair of neighbours the cut separates, along the row and, where
    the cut moves, across the rows."""
    count = first.numel()
    cuts = first[:, None].expand(count, rows).clone()
    start, stop = cut_rows
    if count == 0 or stop <= start:
        return cuts
    span, height = int((last - first).max()) + 1, stop - start
    place = first[:, None] + torch.arange(span)[None]  # [B, S]
    allowed = place <= last[:, None]
    b = torch.arange(count)[:, None, None].expand(count, height, span + 1)
    r = torch.arange(start, stop)[None, :, None].expand(count, height, span + 1)
    p = (first[:, None, None] + torch.arange(-1, span)[None, None]).expand(count, height, span + 1).clamp(0, length - 1)
    a, c = patch_of(b, r, p), patch_of(b + 1, r, p)  # the patches before and after the boundary
    y, x = (p, r) if transpose else (r, p)
    present = (a >= 0) & (c >= 0)
    apart = torch.where(present, _color_distance(colors.at(a.clamp_min(0), y, x), colors.at(c.clamp_min(0), y, x)), 0)
    error = torch.where(allowed[:, None, :], apart[:, :, :-1] + apart[:, :, 1:], torch.inf)
    # A cut that moves between rows puts the pixel it passes over on the other side of a seam across the rows.
    crossed = torch.cat([torch.zeros_like(apart[:, :1]), apart[:, :-1] + apart[:, 1:]], 1)  # [B, rows, S + 1]
    cuts[:, start:stop] = first[:, None] + cheapest_paths(error, crossed[:, :, :-1], crossed[:, :, 1:])
    return cuts


def seam_cut(matched: _Matches) -> torch.Tensor:  # -> [h, w] kept patch, -1: none
    """Which of the matched patches that cover it each pixel of the pass's level takes: each boundary between
    neighbouring patches cut where the two agree, by image quilting's minimum error boundary cut (Efros and Freeman
    2001) with Kwatra et al.'s seam cost (2003). The columns' boundaries first, each a path down the image within the
    two patches' overlap, the patches of each row of the grid its nearest centres'; then the rows' boundaries, a path
    across, the patches of each column the ones the first cuts gave. The nearest centres cut every patch on a
    straight line whatever it shows there, which the views carry over the surface as hard-edged trapezoids
    (decision 021)."""
    h, w = matched.synthesis.shape[1:]
    slot = torch.full((matched.kept.numel(),), -1, dtype=torch.long)
    slot[matched.kept] = torch.arange(int(matched.kept.sum()))
    nx = matched.xs.numel()
    colors = _PatchColors(matched)
    grid = torch.nonzero(matched.kept)[:, 0]
    tops, lefts = matched.ys[grid // nx], matched.xs[grid % nx]
    if grid.numel() == 0:
        return torch.full((h, w), -1, dtype=torch.long)
    rows = (int(tops.min()), int(tops.max()) + matched.size)  # no cut matters outside the matched patches
    columns = (int(lefts.min()), int(lefts.max()) + matched.size)
    grid_row = _nearest_centre(matched.ys, matched.size, h)  # [h]
    first, last = _cut_ranges(matched.xs, matched.size, w)
    column_cuts = _axis_cuts(
        colors, lambda b, r, p: slot[grid_row[r] * nx + b], first, last, h, rows, w, transpose=False
    )
    grid_col = torch.searchsorted(column_cuts.T.contiguous(), torch.arange(w).expand(h, w).contiguous(), right=True)
    first, last = _cut_ranges(matched.ys, matched.size, h)
    row_cuts = _axis_cuts(
        colors, lambda b, r, p: slot[b * nx + grid_col[p, r]], first, last, w, columns, h, transpose=True
    )
    grid_row = torch.searchsorted(row_cuts.T.contiguous(), torch.arange(h).expand(w, h).contiguous(), right=True).T
    return slot[grid_row * nx + grid_col]


def painting_field(matched: _Matches, style: torch.Tensor, height: int, width: int) -> PaintingField:
    """The :class:`PaintingField` of a pass's matches at ``height`` x ``width`` (the full resolution); ``style`` is the
    painting at full resolution [3, Hs, Ws]. A pass at a coarser level is scaled up: its pixels' coordinates times
    2^level, plus the full-resolution pixel's place inside the level's pixel."""
    scale = 2**matched.level
    h, w = matched.synthesis.shape[1:]
    y = torch.arange(height).clamp_max(h * scale - 1) // scale
    x = torch.arange(width).clamp_max(w * scale - 1) // scale
    patch = seam_cut(matched)[y[:, None], x[None, :]]
    valid = patch >= 0
    colors = _PatchColors(matched)
    patch = patch.clamp_min(0)
    mirrored = (colors.half[patch] > 0).long()
    row = y[:, None] + colors.shift_rows[patch] - mirrored * colors.source_height
    col = x[None, :] + colors.shift_cols[patch]
    style_height, style_width = style.shape[1:]
    sub_y, sub_x = (torch.arange(height) - y * scale)[:, None], (torch.arange(width) - x * scale)[None, :]
    rows = (row * scale + sub_y).clamp(0, style_height - 1) + mirrored * style_height
    cols = (col * scale + sub_x).clamp(0, style_width - 1)
    source = torch.cat([style, style.flip(-1)], 1)
    return PaintingField(rows, cols, valid, source)


@dataclass
class _StageColors:
    """The colour maps that one stage's proposals share (``SynthBackend.prepare_stage``)."""

    style_key: bytes
    states: ColorMap  # the renders of every active view to the style
    contents: ColorMap  # the content views to the style
    content_key: bytes


# --- The backend -----------------------------------------------------------------------------------------


def _digest(*tensors: torch.Tensor) -> bytes:
    h = hashlib.sha256()
    for tensor in tensors:
        h.update(repr(tuple(tensor.shape)).encode())
        h.update(tensor.detach().float().contiguous().numpy().tobytes())
    return h.digest()


def _generator(*parts) -> torch.Generator:
    seed = int.from_bytes(hashlib.sha256(repr(parts).encode()).digest()[:8], "little") & (2**63 - 1)
    return torch.Generator().manual_seed(seed)


class SynthBackend(ProposalBackend):
    """Example-based synthesis proposals (module docstring); no weights, runs on a CPU.

    ``SynthBackend(seed=1, noise=0.1)`` overrides fields of ``SynthSettings``; unknown names raise.
    """

    name = "synth"
    takes_guides = True
    takes_depth = True

    def __init__(self, settings: SynthSettings | None = None, **overrides):
        known = {f.name for f in fields(SynthSettings)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ConfigError(f"unknown synth backend settings: {', '.join(unknown)}")
        self.settings = replace(settings or SynthSettings(), **overrides)
        self.settings.check()
        self._libraries: OrderedDict = OrderedDict()
        self._contents: OrderedDict = OrderedDict()
        self._stage: _StageColors | None = None
        self._matched: _Matches | None = None
        self._field_of: tuple[torch.Tensor, int, int] | None = None  # the last proposal's (style, height, width)
        self._levels: int | None = None  # the pyramid of the last prepared stage's views
        self._quantiles: tuple[bytes, StyleQuantiles] | None = None  # the last style's, by its digest

    @property
    def last_field(self) -> PaintingField | None:
        """Where the last proposal's pixels come from in the painting (built when asked: only runs that carry the
        marks need it)."""
        if self._matched is None or self._field_of is None:
            return None
        return painting_field(self._matched, *self._field_of)

    @staticmethod
    def _check_image(image: torch.Tensor, what: str) -> torch.Tensor:
        if image.dim() != 3 or image.shape[0] != 3:
            raise ValueError(f"the synth backend expects a [3, H, W] {what}, got {list(image.shape)}")
        image = image.detach().float()
        if not torch.isfinite(image).all():
            raise NumericalError(f"the synth backend got a {what} with non-finite values")
        return image.clamp(0.0, 1.0)

    def encode(self, image: torch.Tensor) -> torch.Tensor:  # [3, H, W] -> [3, H, W]
        """The state is the image itself (clamped to [0, 1])."""
        return self._check_image(image, "image").clone()

    def decode(self, state: torch.Tensor) -> torch.Tensor:  # [3, H, W] -> [3, H, W]
        return self._check_image(state, "state")

    def _library(self, style: torch.Tensor, style_key: bytes, level: int, size: int) -> StyleLibrary:
        key = (style_key, level, size)
        library = self._libraries.get(key)
        if library is None:
            generator = _generator(self.settings.seed, "library", style_key, level, size)
            library = build_library(downsample(style, level), size, self.settings, generator)
            self._libraries[key] = library
            while len(self._libraries) > LIBRARY_CACHE_SIZE:
                self._libraries.popitem(last=False)
        else:
            self._libraries.move_to_end(key)
        return library

    def _style_colors(self, image: torch.Tensor, style: torch.Tensor, coverage, style_key: bytes) -> torch.Tensor:
        """:func:`to_style_colors` with the style's quantiles sorted once per style, not at every match (each pass
        and each proposal's end: sorting the painting was half a 2.2M-splat run's proposal time)."""
        quantiles = None
        if self.settings.histogram_matching:
            if self._quantiles is None or self._quantiles[0] != style_key:
                self._quantiles = (style_key, StyleQuantiles.of(style.permute(1, 2, 0).reshape(-1, 3)))
            quantiles = self._quantiles[1]
        return to_style_colors(image, style, coverage, self.settings.histogram_matching, quantiles)

    def prepare_stage(self, states, style_image, contents, coverages) -> None:
        """Fit the colour maps this stage's proposals share: the renders of all views pooled to the style, and
        the content views pooled (cached), so every view recolours a surface the same way."""
        s = self.settings
        style = self._check_image(style_image, "style image")
        renders = [self._check_image(x, "state") for x in states]
        covers = [
            None if c is None else c.detach().float().reshape(r.shape[1:]).clamp(0.0, 1.0)
            for r, c in zip(renders, coverages)
        ]
        content_images = [r if c is None else self._check_image(c, "content image") for r, c in zip(renders, contents)]
        self._levels = min(pyramid_levels(*renders[0].shape[1:], s), pyramid_levels(*style.shape[1:], s))
        style_key = _digest(style)
        content_key = _digest(*content_images, *[c for c in covers if c is not None])
        if self._stage is not None and (self._stage.style_key, self._stage.content_key) == (style_key, content_key):
            content_map = self._stage.contents
        else:
            content_map = fit_color_map(content_images, style, covers, s.histogram_matching)
        self._stage = _StageColors(
            style_key, fit_color_map(renders, style, covers, s.histogram_matching), content_map, content_key
        )

    def _content(self, content, style, coverage, keys: tuple[bytes, bytes], level: int, depth=None):
        """(blur(C'), W) at ``level``: the content colour-transferred to the style and low-passed at the content
        sigma (in the level's pixels), and the fusion weight map (:func:`fusion_edges`, with the depth when given)."""
        stage = self._stage if self._stage is not None and self._stage.style_key == keys[0] else None
        key = (*keys, level, stage is not None)
        cached = self._contents.get(key)
        if cached is None:
            if stage is not None:
                transferred = downsample(recolor(content, stage.contents, coverage), level)
            else:
                transferred = downsample(self._style_colors(content, style, coverage, keys[0]), level)
            # Edges at a structural scale (object outlines and shading, not the photo's texture).
            edge_level = max(level, min(self.settings.edge_level, self.settings.max_levels - 1))
            weight = content_weight_map(fusion_edges(content, depth, edge_level), self.settings)
            weight = upsample(weight[None], *transferred.shape[1:])[0]
            cached = (low_pass(transferred, self._sigma(level)), weight)
            self._contents[key] = cached
            while len(self._contents) > 2 * LIBRARY_CACHE_SIZE:
                self._contents.popitem(last=False)
        return cached

    def _sigma(self, level: int) -> float:
        """The content sigma in pixels of ``level``."""
        return self.settings.content_sigma / 2**level

    def full_detail(self, stage: Stage) -> bool:
        """True once the stage's last pass runs at full resolution, on the pyramid of the prepared stage's views
        (before any, the largest, which reaches full resolution last).

        With ``standard``'s 12 one-pass stages that is stage 9 on; stopped before it (as the early stop did
        after 3-7 stages), the scene held only the coarse levels' blurred bands: no marks.
        """
        levels = self._levels or self.settings.max_levels
        return pass_scales(ladder_entry(stage), stage.updates, levels, self.settings)[-1][0] == 0

    def relative_cost(self, stage: Stage, height: int, width: int) -> float:
        """A pass costs PASS_OVERHEAD plus its level's share of the full-resolution pixels, in units of the latter:
        on bonsai x Starry Night (quiet) a stage's proposals took 2.5 s at the coarsest level and 3.7 s at full
        resolution with preview's 8 views, 5.0 s and 6.4 s with standard's 16: 2.6 + 4^-level gives their middle."""
        levels = pyramid_levels(height, width, self.settings)
        plan = pass_scales(ladder_entry(stage), stage.updates, levels, self.settings)
        return sum(PASS_OVERHEAD + 4.0**-level for level, _ in plan)

    def propose(
        self,
        state: torch.Tensor,  # [3, H, W]
        stage: Stage,
        style_image: torch.Tensor,  # [3, Hs, Ws]
        content_image: torch.Tensor | None,  # [3, H, W]
        coverage: torch.Tensor | None = None,  # [H, W] render alpha
        guide: tuple[torch.Tensor, torch.Tensor] | None = None,  # ([3, H, W] image, [H, W] weight)
        depth: torch.Tensor | None = None,  # [H, W] the view's rendered depth (0: nothing): its outlines
    ) -> tuple[torch.Tensor, list[float]]:
        """``stage.updates`` synthesis passes (Algorithm 1, lines 3-5); returns the proposal and the pass energies.

        The proposal is the synthesis on covered pixels, blending into the render as coverage falls
        (``color_transfer.coverage_weight``): the background and faint floaters keep their colour.
        """
        s = self.settings
        render = self._check_image(state, "state")
        style = self._check_image(style_image, "style image")
        height, width = render.shape[1:]
        content = render if content_image is None else self._check_image(content_image, "content image")
        if content.shape != render.shape:
            raise ValueError(f"content image {list(content.shape)} and state {list(render.shape)} differ in size")
        if coverage is not None:
            coverage = coverage.detach().float().reshape(height, width)
            if not torch.isfinite(coverage).all():
                raise NumericalError("the synth backend got a coverage map with non-finite values")
            coverage = coverage.clamp(0.0, 1.0)
        if guide is not None:
            guide = (
                self._check_image(guide[0], "guide"),
                guide[1].detach().float().reshape(height, width).clamp_min(0.0),
            )
        if depth is not None:
            depth = depth.detach().float().reshape(height, width)
            if not torch.isfinite(depth).all():
                raise NumericalError("the synth backend got a depth map with non-finite values")
        levels = min(pyramid_levels(height, width, s), pyramid_levels(*style.shape[1:], s))
        entry = ladder_entry(stage)
        plan = pass_scales(entry, stage.updates, levels, s)
        references = (
            content,
            coverage if coverage is not None else torch.zeros(0),
            *(() if depth is None else (depth,)),
        )
        keys = (_digest(style), _digest(*references))
        # Colours first (Elad and Milanfar: colour transfer before synthesis), then the passes, coarse to fine;
        # going to a finer level upsamples the estimate, whose detail the finer patches then synthesize.
        level = plan[0][0]
        colors = self._stage if self._stage is not None and self._stage.style_key == keys[0] else None
        if colors is not None:
            start = recolor(render, colors.states, coverage)
        else:
            start = self._style_colors(render, style, coverage, keys[0])
        if guide is not None:
            start = _blend(start, guide[0], guide[1])
        x = downsample(start, level)
        energies, self._matched = [], None
        for j, (pass_level, size) in enumerate(plan):
            if pass_level != level:
                level = pass_level
                x = upsample(x, height // 2**level, width // 2**level)
            generator = _generator(s.seed, "pass", stage.index, stage.stages, j, keys[1])
            noise = s.noise * math.sqrt(1.0 - entry) if j == 0 else 0.0
            x, energy = self._pass(x, style, content, coverage, keys, level, size, noise, generator, guide, depth)
            energies.append(energy)
        self._field_of = (style, height, width)
        # A stage that ends at a coarse level proposes its coarse bands only: none of the render's finer texture
        # (the capture's) goes back on; the finer stages paint it from the painting.
        x = upsample(x, height, width)
        if s.light_weight > 0.0:
            content_low, _ = self._content(content, style, coverage, keys, 0, depth)
            x = hold_light(x, content_low, s.light_weight, self._sigma(0))
        if s.light_weight > 0.0 or s.final_match:
            x = self._style_colors(x, style, coverage, keys[0])
        keep = 1.0 if coverage is None else coverage_weight(coverage)[None]
        return (render + keep * (x - render)).clamp(0.0, 1.0), energies

    def _pass(self, estimate, style, content, coverage, keys, level, size, noise, generator, guide=None, depth=None):
        """One EM pass on ``estimate`` (at ``level``) with ``size`` patches: (new estimate, energy before it)."""
        s = self.settings
        h, w = estimate.shape[1:]
        size = min(size, h, w, *downsample(style, level).shape[1:])
        gap = max(1, round(s.gap_ratio * size))
        cover = None if coverage is None else downsample(coverage[None], level)[0]
        library = self._library(style, keys[0], level, size)
        filled = estimate if cover is None else fill_uncovered(estimate, cover, sigma=max(1.0, size / 2))
        probe = filled + noise * torch.randn(filled.shape, generator=generator) if noise > 0 else filled
        offset = tuple(int(v) for v in torch.randint(0, gap, (2,), generator=generator))
        ys, xs = patch_grid(h, w, size, gap, offset)
        index = patch_index(ys, xs, size, w)
        kept = torch.ones(index.shape[0], dtype=torch.bool)
        if cover is not None:  # patches with nothing covered take no part
            kept = cover.reshape(-1)[index].amax(1) > COVERED
            index = index[kept]
        if index.shape[0] == 0:
            return estimate, 0.0
        # E-step: nearest style patches; M-step: robust aggregation, content fusion, colour transfer.
        queries = library.project(extract_patches(probe, index))
        rows = nearest_patches(queries, library.projected, s.search_chunk)
        matches = library.patches(rows)
        energy = (extract_patches(filled, index) - matches).norm(dim=1).pow(s.robust_power).mean() / matches.shape[1]
        synthesis = robust_aggregate(estimate, matches, index, s.robust_power, s.irls_iterations)
        corners = library.corners[rows]
        self._matched = _Matches(level, size, ys, xs, kept, corners, library.width, library.source, synthesis)
        content_low, weight = self._content(content, style, coverage, keys, level, depth)
        fused = fuse_content(synthesis, content_low, weight, self._sigma(level))
        if guide is not None:
            # The guide's strokes hold against this view's own, in proportion to its weight (1: an even mix).
            g = downsample(guide[1][None], level)[0]
            fused = (fused * (1.0 + weight) + g * downsample(guide[0], level)) / (1.0 + weight + g)
        return self._style_colors(fused, style, cover, keys[0]), float(energy)

    def clear_cache(self) -> None:
        """Forget cached style libraries and content maps (frees memory; results do not depend on it)."""
        self._libraries.clear()
        self._contents.clear()
        self._stage = None
        self._quantiles = None
