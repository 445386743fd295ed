"""Proxies: the splats narrower than a pixel share a colour during the colour fit, a colour per pixel-sized cell.

A capture of a few million splats holds most of them below a pixel at the fit size (the bonsai split 8x: 82% of
the seen splats under half a pixel in the view that draws them largest; the bonsai itself 52%). No view can show two
such splats in one pixel apart, so during the fit they need no colour of their own: each pixel-sized cell of them gets one column
of the colour-only maps (:meth:`~dresg_addon.raster.ColorOnlyRenderer.merge_columns` sums its members' samples
pixel by pixel, so the images stay exactly those of the members each painted the cell's colour), and at the end
every member takes its cell's colour (:func:`~.fitting.result_scene`). A splat wider than half a pixel keeps its
own column, so the fit is exact for it. At 1 px the bonsai's patch distance to the painting rose 2.6% at the fit
size (bench/quality.py, standard, Starry Night); at half a pixel the dense scene keeps nearly all of the saving.

Cells are cubes of a world size that is one pixel where the splat is seen closest (its depth over the focal
length in the view nearest to it), rounded down to a power of two so that neighbours of a similar size share a
grid: their members lie within one pixel of each other (about 1.7 px along a diagonal) in that view, and within
less in the others.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..scene.camera import Camera

PROXY_CELL_PX = 1.0  # a cell's side, in pixels of the view that sees it closest


@dataclass(frozen=True)
class ProxyColumns:
    """The fit's columns over the seen splats: ``column[i]`` is seen splat i's column; ``representative[g]`` the seen
    splat that stands for column g (its first member; a splat of its own stands for itself). Columns run in space
    order (:func:`spatial_order_key`), not the scene's."""

    column: torch.Tensor  # [M] long, in [0, count)
    representative: torch.Tensor  # [count] long, indices into the seen splats

    @property
    def count(self) -> int:
        return int(self.representative.numel())

    @property
    def grouped(self) -> bool:
        """Whether any two splats share a column."""
        return self.count < self.column.numel()


def pixel_world_size(
    means: torch.Tensor,  # [M, 3] the seen splats' means
    cameras: Sequence[Camera],
    drawn: Sequence[torch.Tensor],  # V x [M] bool: the splats each view draws
) -> torch.Tensor:  # [M] float32: world length of a pixel at the splat in the view nearest it; inf if none draws it
    """The world size of one pixel at each splat, in the view that draws it closest: depth / focal length."""
    size = torch.full((means.shape[0],), math.inf)
    for camera, seen in zip(cameras, drawn):
        w2c = torch.as_tensor(camera.world_to_camera, dtype=torch.float32)
        depth = means @ w2c[2, :3] + w2c[2, 3]
        here = torch.where(seen & (depth > 0), depth / min(camera.fx, camera.fy), math.inf)
        size = torch.minimum(size, here)
    return size


def proxy_columns(
    means: torch.Tensor,  # [M, 3]
    log_scales: torch.Tensor,  # [M, 3]
    cameras: Sequence[Camera],
    drawn: Sequence[torch.Tensor],  # V x [M] bool
    sigma_px: float,  # the plan's proxy_sigma
    cell_px: float = PROXY_CELL_PX,
) -> ProxyColumns:
    """The columns of the colour fit: one per pixel-sized cell of splats narrower than ``sigma_px`` in every view
    that draws them, one per splat for the rest (module notes). ``sigma_px`` 0 gives every splat its own column."""
    m = means.shape[0]
    pixel = pixel_world_size(means.float(), cameras, drawn)
    sigma = log_scales.float().amax(1).exp() / pixel  # the largest axis, in pixels where it is seen largest
    small = (sigma < sigma_px) & torch.isfinite(pixel) & (pixel > 0)
    own = torch.arange(m)
    if not bool(small.any()):
        return ProxyColumns(own, own)
    index = torch.nonzero(small).squeeze(-1)
    level = torch.floor(torch.log2(pixel[index] * cell_px)).clamp(-126, 126)
    cell = torch.floor(means[index].double() / torch.exp2(level.double())[:, None]).long()
    group = _equal_rows(torch.cat([level.long()[:, None], cell], 1))
    # Each cell is represented by its first member; a splat of its own by itself.
    first = torch.full((int(group.max()) + 1,), m, dtype=torch.long).scatter_reduce_(0, group, index, "amin")
    representative_of = own.clone()
    representative_of[index] = first[group]
    representative = torch.unique(representative_of)  # sorted
    representative = representative[torch.argsort(spatial_order_key(means[representative]), stable=True)]
    column_of = torch.empty(m, dtype=torch.long)
    column_of[representative] = torch.arange(representative.numel())
    return ProxyColumns(column_of[representative_of], representative)


def spatial_order_key(points: torch.Tensor) -> torch.Tensor:  # [M, 3] -> [M] long
    """A Z-order (Morton) key of each point by its rank along each axis (21 bits an axis): sorted by it, points near
    in space are near in the order. The fit's columns in this order make a view's product gather neighbouring
    colours from neighbouring memory: W c 25% faster on the bonsai split 8x than in a capture's own order. Ranks,
    not coordinates, so that a few far floaters do not squeeze the scene into a handful of cells."""
    count = points.shape[0]
    key = torch.zeros(count, dtype=torch.long)
    if count == 0:
        return key
    bits = 21
    for axis in range(3):
        rank = torch.empty(count, dtype=torch.long)
        rank[torch.argsort(points[:, axis], stable=True)] = torch.arange(count)
        cell = rank * (1 << bits) // count  # in [0, 2^21)
        for bit in range(bits):
            key |= ((cell >> bit) & 1) << (3 * bit + axis)
    return key


def _equal_rows(key: torch.Tensor) -> torch.Tensor:  # [M, D] long -> [M] long: one id per distinct row
    """Group ids of the rows of ``key``: the rows ravelled into one integer where their ranges allow (a 1-D unique,
    50x faster than ``torch.unique(dim=0)`` on 1.3M cells), else compared whole."""
    low = key.amin(0)
    span = key.amax(0) - low + 1
    if math.prod(float(extent) for extent in span) >= 2.0**62:
        return torch.unique(key, dim=0, return_inverse=True)[1]
    flat = torch.zeros(key.shape[0], dtype=torch.long)
    for d in range(key.shape[1]):
        flat = flat * span[d] + (key[:, d] - low[d])
    return torch.unique(flat, return_inverse=True)[1]
