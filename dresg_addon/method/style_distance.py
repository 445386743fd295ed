"""Style distance: sliced 2-Wasserstein distances between the colours or patches of images and a style image.

The method's early stop measures its stages with :func:`sliced_wasserstein_patches` and its histogram
colour transfer takes :func:`empirical_quantiles`; :mod:`dresg_addon.evaluation.metrics` reports both
distances as style metrics. Pure functions of torch tensors, float32 or float64, never NaN.

Masks (optional, [H, W] per image): bool, or alpha where alpha > ``ALPHA_THRESHOLD`` counts as
covered; an image whose mask covers nothing is measured as if unmasked.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

ALPHA_THRESHOLD = 0.5  # pixels at least this opaque have a meaningful colour and depth


def _image_list(images, name: str) -> list[torch.Tensor]:
    """[B, 3, H, W] or a list of [3, H, W] (sizes may differ) as a list of [3, H, W]."""
    if isinstance(images, torch.Tensor):
        if images.ndim == 3:
            images = images[None]
        if images.ndim != 4:
            raise ValueError(f"{name} must be [B, 3, H, W] or a list of [3, H, W], got shape {tuple(images.shape)}")
        images = list(images.unbind(0))
    out = list(images)
    for image in out:
        if image.ndim != 3 or image.shape[0] != 3:
            raise ValueError(f"{name}: each image must be [3, H, W], got shape {tuple(image.shape)}")
    if not out:
        raise ValueError(f"{name}: no images")
    return out


def _coverage(mask, hw: tuple[int, int], name: str, device) -> torch.Tensor:  # -> [H, W] bool
    """One [H, W] mask as bool: kept as is when bool, else alpha > ``ALPHA_THRESHOLD``."""
    mask = torch.as_tensor(mask, device=device)
    if tuple(mask.shape) != hw:
        raise ValueError(f"{name}: each mask must be [H, W] = {list(hw)} like its image, got shape {tuple(mask.shape)}")
    return mask if mask.dtype == torch.bool else mask > ALPHA_THRESHOLD


def _mask_list(masks, images: list[torch.Tensor]) -> list[torch.Tensor | None]:
    """None, [B, H, W] or a list of [H, W] (None: that image unmasked) as one bool mask (or None) per image."""
    if masks is None:
        return [None] * len(images)
    if isinstance(masks, torch.Tensor):
        if masks.ndim == 2:
            masks = masks[None]
        if masks.ndim != 3:
            raise ValueError(f"masks must be [B, H, W] or a list of [H, W], got shape {tuple(masks.shape)}")
        masks = list(masks.unbind(0))
    masks = list(masks)
    if len(masks) != len(images):
        raise ValueError(f"masks: got {len(masks)} masks for {len(images)} images")
    return [
        None if mask is None else _coverage(mask, tuple(image.shape[-2:]), "masks", image.device)
        for image, mask in zip(images, masks)
    ]


def _directions(dim: int, n: int, seed: int, dtype, device) -> torch.Tensor:  # -> [dim, n]
    """``n`` unit vectors in R^dim, uniform on the sphere, fixed by ``seed``."""
    if n < 1:
        raise ValueError(f"n_projections must be at least 1, got {n}")
    generator = torch.Generator().manual_seed(seed)
    d = torch.randn(dim, n, generator=generator, dtype=torch.float64)
    return (d / d.norm(dim=0, keepdim=True)).to(dtype=dtype, device=device)


def empirical_quantiles(sorted_values: torch.Tensor, k: int) -> torch.Tensor:  # [P, n] -> [P, k]
    """The empirical quantile function at levels (i + 0.5) / k, linear between order statistics.

    For ``k == n`` it returns the sorted values themselves, so equal sample counts need no interpolation.
    """
    n = sorted_values.shape[1]
    if n == k:
        return sorted_values
    levels = (torch.arange(k, dtype=torch.float64) + 0.5) / k
    pos = (levels * n - 0.5).clamp(0.0, n - 1)
    lo = pos.floor().long()
    hi = (lo + 1).clamp_max(n - 1)
    w = (pos - lo).to(sorted_values.dtype).to(sorted_values.device)
    lo, hi = lo.to(sorted_values.device), hi.to(sorted_values.device)
    return sorted_values[:, lo] * (1.0 - w) + sorted_values[:, hi] * w


def sort_rows(values: torch.Tensor) -> torch.Tensor:  # [P, n] -> [P, n], each row increasing
    """``torch.sort(values, dim=1).values``; on the CPU without autograd numpy's sort, whose SIMD quicksort is 5-7x
    faster for floats (128 rows of 16384 float32: 19 ms against 134 ms on an Intel Xeon)."""
    if values.device.type != "cpu" or values.requires_grad or values.dtype not in (torch.float32, torch.float64):
        return torch.sort(values, dim=1).values
    return torch.from_numpy(np.sort(values.numpy(), axis=1))


def sorted_projections(samples: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:  # [n, D], [D, P] -> [P, n]
    """The samples projected on each direction, sorted: each row is a 1D empirical distribution."""
    return sort_rows((samples.to(directions.dtype) @ directions).T.contiguous())


def sliced_wasserstein_sorted(px: torch.Tensor, py: torch.Tensor, chunk: int = 32) -> torch.Tensor:
    """SW_2 from :func:`sorted_projections` of two sample sets on the same directions ([P, n], [P, m])."""
    if px.ndim != 2 or py.ndim != 2 or px.shape[0] != py.shape[0] or px.shape[1] < 1 or py.shape[1] < 1:
        raise ValueError(f"sorted projections must be [P, n] and [P, m], got {tuple(px.shape)}, {tuple(py.shape)}")
    k = max(px.shape[1], py.shape[1])
    total = torch.zeros((), dtype=torch.float64, device=px.device)
    for start in range(0, px.shape[0], chunk):  # bounds the [chunk, K] interpolated quantiles
        qx = empirical_quantiles(px[start : start + chunk], k)
        qy = empirical_quantiles(py[start : start + chunk].to(px.dtype), k)
        total = total + ((qx - qy).to(torch.float64) ** 2).sum()
    return torch.sqrt(total / (px.shape[0] * k)).to(px.dtype)


def sliced_wasserstein(
    x: torch.Tensor,  # [n, D] samples
    y: torch.Tensor,  # [m, D] samples
    n_projections: int = 128,
    seed: int = 0,
) -> torch.Tensor:
    """Sliced 2-Wasserstein distance between two point clouds (scalar tensor).

    SW_2(X, Y) = sqrt( mean_theta mean_k (Q_{theta.X}(t_k) - Q_{theta.Y}(t_k))^2 ), with theta
    ``n_projections`` unit directions fixed by ``seed``, Q the empirical quantile function and
    t_k = (k + 0.5) / K, K = max(n, m): sorted projections are matched directly when n = m and by
    quantile interpolation otherwise. A shift s of a cloud gives about |s| / sqrt(D).

    >>> x = torch.rand(500, 3, dtype=torch.float64)
    >>> float(sliced_wasserstein(x, x))
    0.0
    >>> shift = torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64)
    >>> 0.25 < float(sliced_wasserstein(x, x + shift)) < 0.33
    True
    """
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1] or x.shape[0] < 1 or y.shape[0] < 1:
        raise ValueError(
            f"sliced_wasserstein: samples must be [n, D] and [m, D], got {tuple(x.shape)}, {tuple(y.shape)}"
        )
    directions = _directions(x.shape[1], n_projections, seed, x.dtype, x.device)
    return sliced_wasserstein_sorted(sorted_projections(x, directions), sorted_projections(y, directions))


def _sliced_wasserstein_batch(images, style, samples, n_projections: int, seed: int, masks=None) -> torch.Tensor:
    """SW_2 of ``samples(image, mask)`` against ``samples(style, None)`` for each image ([B]); the style side
    is sorted once and never masked."""
    images = _image_list(images, "images")
    masks = _mask_list(masks, images)
    reference = samples(_image_list(style, "style")[0], None)
    directions = _directions(reference.shape[1], n_projections, seed, images[0].dtype, images[0].device)
    reference = sorted_projections(reference.to(images[0].device), directions)
    return torch.stack(
        [
            sliced_wasserstein_sorted(sorted_projections(samples(image, mask), directions), reference)
            for image, mask in zip(images, masks)
        ]
    )


def _subsample_index(n: int, max_samples: int | None, seed: int) -> torch.Tensor | None:
    """A fixed random subset of range(n), or None for all; it depends only on (n, max_samples, seed)."""
    if max_samples is None or n <= max_samples:
        return None
    if max_samples < 1:
        raise ValueError(f"max_samples must be at least 1, got {max_samples}")
    generator = torch.Generator().manual_seed(seed + 1)
    return torch.randperm(n, generator=generator)[:max_samples]


def _kept_subset(kept: torch.Tensor | None, n: int, max_samples: int | None, seed: int) -> torch.Tensor | None:
    """Indices into range(n): the kept ones (bool [n], None: all; none kept: all), then a fixed random subset.

    Without a mask this is :func:`_subsample_index` itself; with one, the subset is drawn the same way
    among the kept indices, so an all-true mask gives exactly the unmasked samples.
    """
    if kept is None or not bool(kept.any()):
        return _subsample_index(n, max_samples, seed)
    kept = kept.nonzero()[:, 0]
    index = _subsample_index(kept.numel(), max_samples, seed)
    return kept if index is None else kept[index.to(kept.device)]


def _colour_samples(image: torch.Tensor, max_samples: int | None, seed: int, mask=None) -> torch.Tensor:
    """[3, H, W] -> [n, 3]: all (or a fixed random subset of) the pixels, the covered ones under a mask."""
    pixels = image.reshape(3, -1).T
    index = _kept_subset(None if mask is None else mask.reshape(-1), pixels.shape[0], max_samples, seed)
    return pixels if index is None else pixels[index.to(pixels.device)]


def _patch_samples(image: torch.Tensor, patch: int, max_samples: int | None, seed: int, mask=None) -> torch.Tensor:
    """[3, H, W] -> [n, 3 patch^2]: all (or a fixed random subset of) the patch x patch windows; under a
    mask, the windows whose every pixel is covered."""
    _, h, w = image.shape
    if h < patch or w < patch:
        raise ValueError(f"image of size {w}x{h} is smaller than the {patch}x{patch} patch")
    rows, cols = h - patch + 1, w - patch + 1
    kept = None
    if mask is not None:  # a window is kept when no pixel of it is background
        background = (~mask).to(image.dtype)[None, None]
        kept = F.max_pool2d(background, patch, stride=1)[0, 0].reshape(-1) == 0  # [rows * cols]
    index = _kept_subset(kept, rows * cols, max_samples, seed)
    if index is None:
        index = torch.arange(rows * cols)
    index = index.to(image.device)
    top, left = index // cols, index % cols
    offsets = torch.arange(patch, device=image.device)
    yy = (top[:, None] + offsets[None, :])[:, :, None]  # [n, patch, 1]
    xx = (left[:, None] + offsets[None, :])[:, None, :]  # [n, 1, patch]
    flat = (yy * w + xx).reshape(-1)  # [n * patch^2]
    return (
        image.reshape(3, -1)[:, flat]
        .reshape(3, index.numel(), patch * patch)
        .permute(1, 0, 2)
        .reshape(index.numel(), -1)
    )


def sliced_wasserstein_colors(
    images,  # [B, 3, H, W] or list of [3, H, W]
    style: torch.Tensor,  # [3, Hs, Ws]
    n_projections: int = 128,
    seed: int = 0,
    max_samples: int | None = 65536,
    masks=None,  # None, [B, H, W] or a list of [H, W]: bool, or alpha
) -> torch.Tensor:  # [B]
    """Style distance of colours: SW_2 between the RGB pixels of each image and of ``style``.

    SW_2 as in :func:`sliced_wasserstein`, on the point clouds {I(p)} and {S(q)} in RGB space (units
    of the image values). Images with more than ``max_samples`` pixels (None: no limit) use a fixed
    random subset that depends only on the image size and ``seed``, so identical images still give
    exactly 0; 65536 samples estimate the distance to well under 1% of typical values, and sorting
    stays fast.

    With ``masks`` (per image, bool or alpha > ``ALPHA_THRESHOLD``) the cloud is {I(p) : p covered},
    subsampled the same way among the covered pixels (the count and ``seed`` fix the subset); an
    image with no covered pixel uses all its pixels. ``style`` is never masked.

    >>> style = torch.rand(3, 16, 16)
    >>> sliced_wasserstein_colors(torch.stack([style, style.flip(-1), 0.5 * style]), style)[:2].tolist()
    [0.0, 0.0]
    >>> on_black = torch.cat([style, torch.zeros(3, 16, 8)], -1)  # the object, then background
    >>> covered = torch.arange(24) < 16
    >>> float(sliced_wasserstein_colors(on_black, style, masks=covered.expand(16, 24))[0])
    0.0
    """
    return _sliced_wasserstein_batch(
        images, style, lambda image, mask: _colour_samples(image, max_samples, seed, mask), n_projections, seed, masks
    )


def sliced_wasserstein_patches(
    images,  # [B, 3, H, W] or list of [3, H, W]
    style: torch.Tensor,  # [3, Hs, Ws]
    patch: int = 7,
    n_projections: int = 128,
    seed: int = 0,
    max_samples: int | None = 16384,
    masks=None,  # None, [B, H, W] or a list of [H, W]: bool, or alpha
) -> torch.Tensor:  # [B]
    """Style distance of local texture: SW_2 between the patch x patch RGB windows of each image and of ``style``.

    Each window is a point in R^(3 patch^2) (raw values, colour included); SW_2 as in
    :func:`sliced_wasserstein`. ``max_samples`` windows are drawn at fixed random positions that
    depend only on the image size and ``seed`` (identical images give exactly 0).

    With ``masks`` (per image, bool or alpha > ``ALPHA_THRESHOLD``) only the windows whose every pixel
    is covered count (a window touching the background is left out), subsampled the same way among
    them; an image without a fully covered window uses all its windows. ``style`` is never masked.

    >>> style = torch.rand(3, 24, 24)
    >>> float(sliced_wasserstein_patches(style[None], style)[0])
    0.0
    >>> blurred = torch.nn.functional.avg_pool2d(style[None], 3, 1, 1)
    >>> bool(sliced_wasserstein_patches(blurred, style)[0] > 0.1)
    True
    """
    if patch < 1:
        raise ValueError(f"patch size must be at least 1, got {patch}")
    return _sliced_wasserstein_batch(
        images,
        style,
        lambda image, mask: _patch_samples(image, patch, max_samples, seed, mask),
        n_projections,
        seed,
        masks,
    )
