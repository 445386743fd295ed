"""The weight-free ``patch`` proposal backend: the attention energy of Sec. 4.1 over fixed patch features.

Needs no download and runs on a CPU. The shared energy of ``base.attention_energy`` (Eqs. 6-9) runs
on self-attention features built from image patches instead of U-Net activations, and the backend adds
a coarse-to-fine sliced-Wasserstein term over colours and 7x7 patches (the weight-free style energy of
REFERENCE.md Sec. 3) through ``extra_energy``: nearest-patch attention alone is mode-seeking (a smooth
photo region keeps matching the smoothest style patches), so in the paper's 200 sign-like Adam steps it
tints the render but neither moves its palette to the style's nor adds much texture.

State (the "latent"). ``encode`` maps an image to ``G^-1(P logit(I)) / step_gain`` and ``decode`` maps
a state back with ``sigmoid(P^T G(step_gain * state))``. P is an orthonormal opponent-colour basis
(luminance, red-green, yellow-blue) and G a fixed, invertible low-pass filter in the DCT domain, mild on
luminance and strong on the two chroma channels. A fresh Adam makes every update sign-like, +-lr on
each element: on raw pixels that is salt-and-pepper colour noise, whereas through G a step is a smooth
field whose fine detail is damped (to 0.3 in luminance, 0.05 in chroma), as the SD VAE decoder turns
+-lr latent steps into smooth image changes; texture then forms in luminance and colour stays in
regions, as in paintings. The sigmoid keeps every decode in (0, 1); the round trip is exact up to the
logit clamp (1e-4).

Features. One attention layer per token stride, 16 and 8 (560 and 2240 tokens at 448x320, the token
counts of the SD1.5 layers the paper uses). A token's query and key are fixed random orthonormal
projections (seeded, one per head) of a descriptor of the 4x4 patch of the image area-pooled by
stride / 2: its contrast-normalised shape and its mean colour. One extra coordinate makes
q.k / sqrt(d) = -|p_q - p_k|^2 / (2 temperature^2) up to a per-query constant, so attention is a soft
nearest-patch lookup. A token's value is its 8x8 block of pixels (full resolution at stride 8, half at
16), shared by the heads. Eqs. 7-8 therefore pull every render block toward the style blocks whose
coarse look matches it, copying their fine texture (image analogies), and Eq. 6 keeps the render's
coarse shapes and colours near the content's. The token grids are shifted by a seeded offset per
timestep so that block seams never stay in place.

Timestep. It seeds the grid offset and the random slicing directions, and it sets the scale of the
sliced-Wasserstein term, coarse to fine as the U-Net's features are coarse at high noise: images
area-pooled by 4 while abar < 0.1 (t >= ~620), by 2 while abar < 0.5 (t >= ~360), full size after.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from dataclasses import dataclass, fields, replace

import torch
import torch.nn.functional as F

from ..errors import ConfigError
from ..schedule import alphas_cumprod
from .base import AttentionBackend, AttentionFeatures

LOGIT_EPS = 1e-4  # clamp inside the logit, as in the paper's target construction
TOKEN_PATCH = 4  # side of a token's descriptor patch, in pooled pixels
VALUE_BLOCK = 8  # side of a token's value block, in pixels of its layer's resolution
CONTRAST_FLOOR = 0.05  # keeps flat patches from being blown up by contrast normalisation
REFERENCE_CACHE_SIZE = 8
# Orthonormal opponent colour basis (rows: luminance, red-green, yellow-blue), applied to RGB logits.
OPPONENT = torch.tensor(
    [
        [1 / math.sqrt(3), 1 / math.sqrt(3), 1 / math.sqrt(3)],
        [1 / math.sqrt(2), -1 / math.sqrt(2), 0.0],
        [1 / math.sqrt(6), 1 / math.sqrt(6), -2 / math.sqrt(6)],
    ]
)


@dataclass(frozen=True)
class PatchSettings:
    """Settings of the ``patch`` backend; the defaults were tuned on LLFF fern x Starry Night at 448x320."""

    seed: int = 0
    token_strides: tuple[int, ...] = (16, 8)  # one attention layer per stride
    heads: int = 1  # one 32-dim head matched as well as two 16-dim ones, at half the cost
    head_dim: int = 32
    temperature: float = 0.25  # of the soft nearest-patch lookup, in descriptor units
    colour_weight: float = 3.0  # weight of the mean colour against the normalised shape in Q/K
    step_gain: float = 4.0  # logit units per state unit: one +-0.05 update moves a logit by <= 0.2
    luma_cutoff: float = 0.08  # cycles per pixel where G's luminance gain is halfway to its floor
    luma_floor: float = 0.3  # G's luminance gain at the finest frequencies
    chroma_cutoff: float = 0.03
    chroma_floor: float = 0.05
    swd_weight: float = 100.0  # 0 turns the sliced-Wasserstein term off (pure attention energy)
    swd_patch: int = 7
    swd_projections: int = 64  # random directions in patch space, fresh every update
    colour_projections: int = 16  # random directions in colour space (1x1 patches), fresh every update
    swd_max_patches: int = 16384  # patches per image sorted per update (strided subsampling above)

    def check(self) -> None:
        """Raise ConfigError for values that cannot work."""
        if not self.token_strides or any(int(s) != s or s < 2 or s % 2 for s in self.token_strides):
            raise ConfigError(f"token strides must be even integers of at least 2, got {self.token_strides}")
        for name in ("heads", "head_dim", "temperature", "step_gain", "luma_cutoff", "chroma_cutoff", "swd_patch"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"patch backend setting {name} must be positive, got {getattr(self, name)}")
        for name in ("luma_floor", "chroma_floor"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ConfigError(f"patch backend setting {name} must be in (0, 1], got {getattr(self, name)}")
        for name in ("colour_weight", "swd_weight", "swd_projections", "colour_projections"):
            if getattr(self, name) < 0:
                raise ConfigError(f"patch backend setting {name} must not be negative, got {getattr(self, name)}")
        if self.swd_max_patches < 1:
            raise ConfigError(f"swd_max_patches must be at least 1, got {self.swd_max_patches}")


def spectral_gain(height: int, width: int, cutoff: float, floor: float) -> torch.Tensor:  # -> [2H, W + 1]
    """Transfer function of G on the mirror extension: g(f) = floor + (1 - floor) / (1 + |f|^2 / cutoff^2).

    f in cycles per pixel, laid out for ``rfft2`` of the [2H, 2W] extension; g(0) = 1 (flat changes pass
    unchanged) and g > floor > 0 (invertible).
    """
    fy = torch.fft.fftfreq(2 * height, dtype=torch.float64)
    fx = torch.fft.rfftfreq(2 * width, dtype=torch.float64)
    f2 = fy[:, None] ** 2 + fx[None, :] ** 2
    return (floor + (1.0 - floor) / (1.0 + f2 / cutoff**2)).float()


def symmetric_filter(x: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:  # x [..., H, W], gain [2H, W + 1]
    """Filter ``x`` with a real, even transfer function on its mirror extension (a DCT-domain filter).

    The mirrored signal stays mirrored, so this is a linear operator on [H, W] alone whose inverse is
    the same filter with gain 1 / gain.
    """
    h, w = x.shape[-2:]
    ext = torch.cat([x, x.flip(-1)], -1)
    ext = torch.cat([ext, ext.flip(-2)], -2)
    return torch.fft.irfft2(torch.fft.rfft2(ext) * gain, s=(2 * h, 2 * w))[..., :h, :w]


def stride_patches(image: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Token patches of one layer: area-pool ``image`` [B, 3, H, W] by stride/2, take 4x4 patches at step 2.

    Returns (raw, normalised), each [B, 3, 16, h, w] with h = max(1, H // stride) (w alike).
    ``normalised`` is (patch - its mean colour) / (its RMS contrast + CONTRAST_FLOOR).
    """
    b, _, height, width = image.shape
    gh, gw = max(1, height // stride), max(1, width // stride)
    pooled = F.interpolate(image, size=(2 * gh, 2 * gw), mode="area")
    pooled = F.pad(pooled, (1, 1, 1, 1), mode="replicate")
    raw = F.unfold(pooled, TOKEN_PATCH, stride=2).reshape(b, 3, TOKEN_PATCH * TOKEN_PATCH, gh, gw)
    centred = raw - raw.mean(2, keepdim=True)
    contrast = centred.pow(2).mean((1, 2), keepdim=True).add(1e-8).sqrt()
    return raw, centred / (contrast + CONTRAST_FLOOR)


def patch_feature_maps(image: torch.Tensor) -> torch.Tensor:  # image [B, 3, H, W] -> [B, 96, h, w]
    """Fixed, weight-free structure features for the fit loss when no DINO weights are given.

    The contrast-normalised 4x4 colour patches of the patch backend's stride-8 and stride-16 token grids
    (the stride-16 grid upsampled to the stride-8 one; h = max(1, H // 8), w alike), differentiable in
    ``image``. Invariant to a colour offset, so they describe local structure rather than the palette:
    a stylized render whose edges and layout stay keeps them near the base render's.

    >>> patch_feature_maps(torch.rand(2, 3, 64, 48)).shape
    torch.Size([2, 96, 8, 6])
    """
    if image.dim() != 4 or image.shape[1] != 3:
        raise ValueError(f"patch_feature_maps expects [B, 3, H, W], got {list(image.shape)}")
    _, fine = stride_patches(image, 8)
    _, coarse = stride_patches(image, 16)
    fine = fine.flatten(1, 2)
    coarse = F.interpolate(coarse.flatten(1, 2), size=fine.shape[-2:], mode="nearest")
    return torch.cat([fine, coarse], 1)


def timestep_scale(timestep: int, alpha_bar: torch.Tensor) -> int:  # alpha_bar [T]
    """Pooling factor of the sliced-Wasserstein term at ``timestep``: 4 (abar < 0.1), 2 (< 0.5) or 1."""
    abar = float(alpha_bar[min(max(int(timestep), 0), alpha_bar.numel() - 1)])
    return 4 if abar < 0.1 else 2 if abar < 0.5 else 1


def patch_projections(
    image: torch.Tensor,  # [1, 3, H, W]
    directions: torch.Tensor,  # [P, 3, k, k], unit norm
    max_patches: int,
    offset: tuple[int, int] = (0, 0),
) -> torch.Tensor:  # -> [P, N]
    """Projections of the k x k patches of ``image`` on ``directions``; images with more than
    ``max_patches`` patches are sampled on a strided grid shifted by ``offset``."""
    k = directions.shape[-1]
    count = max(1, (image.shape[-2] - k + 1) * (image.shape[-1] - k + 1))
    step = max(1, math.ceil(math.sqrt(count / max_patches)))
    dy = min(offset[0] % step, image.shape[-2] - k)
    dx = min(offset[1] % step, image.shape[-1] - k)
    return F.conv2d(image[..., dy:, dx:], directions, stride=step)[0].flatten(1)


def patch_sliced_wasserstein(
    render: torch.Tensor,  # [1, 3, H, W]
    style: torch.Tensor | None,  # [1, 3, Hs, Ws]; None when ``style_sorted`` is given
    directions: torch.Tensor,  # [P, 3, k, k], unit norm
    max_patches: int,
    offset: tuple[int, int] = (0, 0),
    style_sorted: torch.Tensor | None = None,  # [P, Ns] the style's sorted projections, if already known
) -> torch.Tensor:
    """Sliced Wasserstein-2 energy between the k x k patches of ``render`` and of ``style``.

    SW = mean_p mean_i (sort(<d_p, x_i>)_i - Q_p(i))^2 over directions d_p and the N render patches x_i,
    where Q_p is the style's sorted projections resampled to N quantiles (target detached).
    """
    projected = patch_projections(render, directions, max_patches, offset)
    with torch.no_grad():
        target = style_sorted if style_sorted is not None else patch_projections(style, directions, max_patches, offset)
        if style_sorted is None:
            target = target.sort(-1).values
        if target.shape[-1] != projected.shape[-1]:
            target = F.interpolate(target[None], size=projected.shape[-1], mode="linear", align_corners=True)[0]
    ordered, _ = projected.sort(-1)
    return (ordered - target).pow(2).mean()


def _digest(image: torch.Tensor) -> bytes:
    """A content key of an image tensor (for caches that must not trust object identity)."""
    return hashlib.blake2b(image.detach().contiguous().numpy().tobytes(), digest_size=16).digest()


def _orthonormal(generator: torch.Generator, rows: int, cols: int) -> torch.Tensor:  # -> [rows, cols]
    """A random matrix with orthonormal columns (rows when cols > rows), from a seeded generator."""
    n = max(rows, cols)
    basis, _ = torch.linalg.qr(torch.randn(n, n, generator=generator, dtype=torch.float64))
    return basis[:rows, :cols].float().contiguous()


class PatchBackend(AttentionBackend):
    """Attention guidance over fixed patch features plus a patch sliced-Wasserstein energy; no weights.

    ``PatchBackend(seed=1, heads=4)`` overrides fields of ``PatchSettings``; unknown names raise.
    """

    name = "patch"

    def __init__(self, settings: PatchSettings | None = None, **overrides):
        unknown = sorted(set(overrides) - {f.name for f in fields(PatchSettings)})
        if unknown:
            raise ConfigError(f"unknown patch backend settings: {', '.join(unknown)}")
        self.settings = replace(settings or PatchSettings(), **overrides)
        self.settings.check()
        s = self.settings
        self._alpha_bar = torch.from_numpy(alphas_cumprod()).float()
        generator = torch.Generator().manual_seed(s.seed)
        descriptor_dim = 3 * TOKEN_PATCH * TOKEN_PATCH + 3
        self._projections = [  # per layer [heads, descriptor_dim, head_dim]
            torch.stack([_orthonormal(generator, descriptor_dim, s.head_dim) for _ in range(s.heads)])
            for _ in s.token_strides
        ]
        self._gains: dict[tuple[int, int], torch.Tensor] = {}
        self._references: OrderedDict[bytes, AttentionFeatures] = OrderedDict()
        self._style_targets: OrderedDict[bytes, torch.Tensor] = OrderedDict()
        self._decoded: tuple[torch.Tensor, int, torch.Tensor] | None = None

    def _gain(self, height: int, width: int) -> torch.Tensor:  # -> [3, 2H, W + 1]
        if (height, width) not in self._gains:
            s = self.settings
            luma = spectral_gain(height, width, s.luma_cutoff, s.luma_floor)
            chroma = spectral_gain(height, width, s.chroma_cutoff, s.chroma_floor)
            self._gains[(height, width)] = torch.stack([luma, chroma, chroma])
        return self._gains[(height, width)]

    @staticmethod
    def _check_image(image: torch.Tensor, what: str = "image") -> None:
        if image.dim() != 3 or image.shape[0] != 3:
            raise ValueError(f"the patch backend expects a [3, H, W] {what}, got {list(image.shape)}")

    def encode(self, image: torch.Tensor) -> torch.Tensor:  # image [3, H, W] -> [3, H, W]
        """state = G^-1(P logit(clamp(I, 1e-4, 1 - 1e-4))) / step_gain (detached, float32)."""
        self._check_image(image)
        logit = torch.logit(image.detach().float().clamp(LOGIT_EPS, 1.0 - LOGIT_EPS))
        opponent = torch.einsum("oc,chw->ohw", OPPONENT, logit)
        return symmetric_filter(opponent, 1.0 / self._gain(*image.shape[-2:])) / self.settings.step_gain

    def decode(self, state: torch.Tensor) -> torch.Tensor:  # state [3, H, W] -> [3, H, W]
        """I = sigmoid(P^T G(step_gain * state)), in [0, 1]."""
        self._check_image(state, "state")
        opponent = symmetric_filter(self.settings.step_gain * state, self._gain(*state.shape[-2:]))
        return torch.sigmoid(torch.einsum("oc,ohw->chw", OPPONENT, opponent))

    def _decode_once(self, state: torch.Tensor, keep: bool) -> torch.Tensor:
        """``decode`` shared by ``features`` and then ``extra_energy`` of one update (same, unmodified tensor).

        ``features`` keeps the decoded image for ``extra_energy``, which takes it and drops the reference.
        """
        cached, self._decoded = self._decoded, None
        if cached is not None and cached[0] is state and cached[1] == state._version:
            image = cached[2]
        else:
            image = self.decode(state)
        if keep:
            self._decoded = (state, state._version, image)
        return image

    def _grid_offset(self, timestep: int) -> tuple[int, int]:
        """(rows, columns) by which the token grids are shifted at ``timestep`` (seeded, < the largest stride)."""
        generator = torch.Generator().manual_seed(self.settings.seed * 1_000_003 + int(timestep) + 7)
        top = max(self.settings.token_strides)
        return tuple(int(x) for x in torch.randint(0, top, (2,), generator=generator))

    def features(self, state: torch.Tensor, timestep: int) -> AttentionFeatures:
        """Self-attention over the patch tokens of ``decode(state)``, one layer per token stride."""
        self._check_image(state, "state")
        return self._image_features(self._decode_once(state, keep=True), timestep)

    def _image_features(self, image: torch.Tensor, timestep: int) -> AttentionFeatures:  # image [3, H, W]
        s = self.settings
        dy, dx = self._grid_offset(timestep)
        shifted = F.pad(image[None], (dx, 0, dy, 0), mode="replicate")  # [1, 3, H + dy, W + dx]
        scale = (s.head_dim + 1) ** 0.25 / s.temperature  # q.k / sqrt(d) = -|p_q - p_k|^2 / (2 t^2) + c(q)
        q, k, v, o = [], [], [], []
        for layer, stride in enumerate(s.token_strides):
            raw, normalised = stride_patches(shifted, stride)  # [1, 3, 16, h, w] each
            gh, gw = raw.shape[-2:]
            shape = normalised.reshape(1, -1, gh * gw).transpose(1, 2)  # [1, T, 48]
            colour = raw.mean(2).reshape(1, 3, gh * gw).transpose(1, 2)  # [1, T, 3]
            # A normalised patch has unit RMS per element, so norm sqrt(48): scale it to a colour's range.
            descriptor = torch.cat([shape / math.sqrt(shape.shape[-1] / 3), s.colour_weight * colour], -1)
            projected = torch.einsum("btc,hcd->bhtd", descriptor, self._projections[layer])  # [1, heads, T, d]
            q_l = scale * torch.cat([projected, torch.ones_like(projected[..., :1])], -1)
            k_l = scale * torch.cat([projected, -0.5 * projected.pow(2).sum(-1, keepdim=True)], -1)
            blocks = F.interpolate(shifted, size=(gh * VALUE_BLOCK, gw * VALUE_BLOCK), mode="area")
            blocks = F.pixel_unshuffle(blocks, VALUE_BLOCK).reshape(1, 3 * VALUE_BLOCK**2, gh * gw)
            v_l = (2.0 * blocks.transpose(1, 2) - 1.0)[:, None].expand(1, s.heads, gh * gw, 3 * VALUE_BLOCK**2)
            q.append(q_l)
            k.append(k_l)
            v.append(v_l)
            o.append(F.scaled_dot_product_attention(q_l, k_l, v_l))
        return AttentionFeatures(q=q, k=k, v=v, o=o)

    def reference_features(self, image: torch.Tensor, timestep: int) -> AttentionFeatures:
        """Features of a fixed image (taken as is, no encode/decode round trip), cached by content and grid."""
        self._check_image(image)
        pixels = image.detach().float().clamp(0.0, 1.0).contiguous()
        key = _digest(pixels) + repr((tuple(pixels.shape), self._grid_offset(timestep))).encode()
        if key in self._references:
            self._references.move_to_end(key)
            return self._references[key]
        with torch.no_grad():
            feats = self._image_features(pixels, timestep).detached()
        self._references[key] = feats
        if len(self._references) > REFERENCE_CACHE_SIZE:
            self._references.popitem(last=False)
        return feats

    def extra_energy(self, state: torch.Tensor, style_image: torch.Tensor, timestep: int) -> torch.Tensor | None:
        """swd_weight x sliced Wasserstein over k x k patches and colours, at ``timestep_scale``'s pooling."""
        s = self.settings
        if s.swd_weight == 0.0 or s.swd_projections + s.colour_projections == 0:
            self._decoded = None
            return None
        self._check_image(style_image, "style image")
        image = self._decode_once(state, keep=False)[None]
        style = style_image.detach().float().clamp(0.0, 1.0)[None]
        factor = timestep_scale(timestep, self._alpha_bar)
        if factor > 1:
            image = F.avg_pool2d(image, factor, ceil_mode=True)
            style = F.avg_pool2d(style, factor, ceil_mode=True)
        k = min(s.swd_patch, *image.shape[-2:], *style.shape[-2:])
        # Fresh directions every update, the same for every view at one timestep (deterministic).
        generator = torch.Generator().manual_seed(s.seed * 1_000_003 + int(timestep))
        patch = torch.randn(s.swd_projections, 3 * k * k, generator=generator)
        colour = torch.randn(s.colour_projections, 3, generator=generator)
        directions = torch.zeros(s.swd_projections + s.colour_projections, 3, k, k)
        directions[: s.swd_projections] = (patch / patch.norm(dim=1, keepdim=True)).reshape(-1, 3, k, k)
        directions[s.swd_projections :, :, k // 2, k // 2] = colour / colour.norm(dim=1, keepdim=True)
        offset = tuple(int(x) for x in torch.randint(0, 64, (2,), generator=generator))
        # Every view at this timestep meets the same style target: sort the style's projections once.
        key = _digest(style) + repr((timestep, factor, k, s.swd_max_patches)).encode()
        if key not in self._style_targets:
            with torch.no_grad():
                projected = patch_projections(style, directions, s.swd_max_patches, offset)
                self._style_targets[key] = projected.sort(-1).values
            if len(self._style_targets) > REFERENCE_CACHE_SIZE:
                self._style_targets.popitem(last=False)
        target = self._style_targets[key]
        return s.swd_weight * patch_sliced_wasserstein(
            image, None, directions, s.swd_max_patches, offset, style_sorted=target
        )
