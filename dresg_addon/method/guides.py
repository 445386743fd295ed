"""Guides that make the active views' proposals agree: what earlier views proposed, seen from this one.

A view's proposal is reprojected into another view by the rendered depth of both
(:func:`~dresg_addon.scene.warp.warp_to`: exact reprojection, a depth test against occlusion). For view
i the earlier views are tried nearest camera first, and each pixel takes the first one that sees the same
surface there, so the guide is one view's strokes, not an average of several. Its weight is
``weight`` where some earlier view sees the pixel and 0 elsewhere (surfaces new to this view, occlusions,
the background).

Where no earlier view sees the same surface by depth (thin or slatted objects, whose blended depth lies
between the object and what is behind it, and surfaces seen at grazing angles), :class:`SplatGuides`
fills in: every earlier proposal is painted onto the splats that drew it (each splat takes the
blending-weighted mean of the pixels it drew) and rendered from this view. That guide is what the fit
would make of the earlier proposals, as sharp as the splats, and it needs no depth.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..raster.rasterizer import SparseColorMap
from ..scene.camera import Camera
from ..scene.warp import warp_to


def _resize(image: torch.Tensor, height: int, width: int) -> torch.Tensor:  # [C, H, W]
    if image.shape[-2:] == (height, width):
        return image
    return F.interpolate(image[None], size=(height, width), mode="bilinear", align_corners=False)[0]


def view_guide(
    target: int,
    sources: Sequence[int],  # earlier views whose proposals are known
    proposals: Sequence[torch.Tensor | None],  # per view: [3, h, w] at the proposal size (None: not yet)
    depths: Sequence[torch.Tensor],  # per view: [H, W] rendered depth at the camera's size
    alphas: Sequence[torch.Tensor],  # per view: [H, W] coverage at the camera's size
    cameras: Sequence[Camera],
    weight: float,
    fill: tuple[torch.Tensor, torch.Tensor] | None = None,  # ([3, H, W], [H, W] in [0, 1]) where no warp lands
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(guide [3, h, w], weight [h, w]) for view ``target`` from the ``sources``' proposals; None without sources.

    ``fill`` (at the camera's size, e.g. :meth:`SplatGuides.guide`) is the guide where no source's warp is
    valid, its second part scaling the weight there."""
    if not sources or weight <= 0:
        return None
    camera = cameras[target]
    size = tuple(proposals[sources[0]].shape[-2:])
    centre = np.asarray(camera.center, dtype=np.float64)
    order = sorted(sources, key=lambda j: float(np.linalg.norm(np.asarray(cameras[j].center) - centre)))
    image = torch.zeros(3, camera.height, camera.width)
    taken = torch.zeros(camera.height, camera.width, dtype=torch.bool)
    for j in order:
        source = _resize(proposals[j].float(), cameras[j].height, cameras[j].width)
        warped, valid = warp_to(
            source.permute(1, 2, 0), depths[j], cameras[j], camera, depths[target], alphas[j], alphas[target]
        )
        new = valid & ~taken
        image[:, new] = warped.permute(2, 0, 1)[:, new].float()
        taken |= new
    mask = taken.float()
    if fill is not None:
        image = torch.where(taken, image, fill[0].float())
        mask = torch.where(taken, mask, fill[1].float())
    if not bool((mask > 0).any()):
        return None
    return _resize(image, *size).clamp(0.0, 1.0), weight * _resize(mask[None], *size)[0]


class SplatGuides:
    """The proposals so far painted onto the splats, and rendered from any active view (colour-only path).

    ``add(v, proposal)`` accumulates each splat's blending-weighted sum of the proposal's pixels it drew,
    sum_p w_pi P_p, and its weight, sum_p w_pi; a splat's guide colour is their ratio. ``guide(v)`` renders
    those colours from view v: the image, and per pixel the share of it (its coverage at most) drawn by splats
    the earlier views drew (a splat they drew with at least half the weight this view draws it with counts fully).
    """

    def __init__(self, maps: Sequence[SparseColorMap]):
        self.maps = maps
        count = maps[0].shape[1]
        self.sums = torch.zeros(count, 3)
        self.weights = torch.zeros(count)

    def _pixels(self, v: int) -> int:
        return self.maps[v].shape[0]

    def add(self, v: int, proposal: torch.Tensor) -> None:  # [3, H, W] at the view's camera size
        pixels = proposal.float().reshape(3, -1).T
        if pixels.shape[0] != self._pixels(v):
            raise ValueError(f"SplatGuides.add: the proposal has {pixels.shape[0]} pixels, view {v} {self._pixels(v)}")
        self.sums += self.maps[v].rmatvec(pixels)
        self.weights += self.maps[v].rmatvec(torch.ones(pixels.shape[0], 1))[:, 0]

    def guide(self, v: int, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:  # [3, H, W], [H, W]
        own = self.maps[v].rmatvec(torch.ones(self._pixels(v), 1))[:, 0]
        confidence = torch.where(own > 0, (2.0 * self.weights / own.clamp_min(1e-12)).clamp(0.0, 1.0), 0.0)
        colors = self.sums / self.weights.clamp_min(1e-12)[:, None]
        painted = self.maps[v].matvec(torch.cat([colors * confidence[:, None], confidence[:, None]], 1))
        image = painted[:, :3] / painted[:, 3:].clamp_min(1e-12)
        weight = painted[:, 3].clamp(0.0, 1.0)
        return image.T.reshape(3, height, width).clamp(0.0, 1.0), weight.reshape(height, width)
