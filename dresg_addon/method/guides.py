"""Guides that make the active views' proposals agree: what earlier views proposed, seen from this one.

A view's proposal is reprojected into another view by the rendered depth of both
(:func:`~dresg_addon.scene.warp.warp_to`: exact reprojection, a depth test against occlusion). For view
i the earlier views are tried nearest camera first, and each pixel takes the first one that sees the same
surface there, so the guide is one view's strokes, not an average of several. Its weight is
``weight`` where some earlier view sees the pixel and 0 elsewhere (surfaces new to this view, occlusions,
the background).

Ink is guided by the splats instead (:func:`painted_guide`): what the earlier views painted, rendered into this
one, where their splats make at least :data:`PAINTED_SHARE` of a pixel's coverage.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..scene.camera import Camera
from ..scene.warp import warp_to
from .color_solve import ViewsInTurn

PAINTED_SHARE = 0.5  # a pixel is guided where the painted splats make at least this share of its coverage


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
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(guide [3, h, w], weight [h, w]) for view ``target`` from the ``sources``' proposals; None without sources."""
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
    if not bool(taken.any()):
        return None
    mask = _resize(taken[None].float(), *size)[0]
    return _resize(image, *size).clamp(0.0, 1.0), weight * mask


def painted_guide(
    turn: ViewsInTurn, view: int, camera: Camera, size: tuple[int, int], weight: float
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(guide [3, h, w], weight [h, w]) at the proposal ``size`` (h, w) for ``view``: what the splats painted so far
    show there (:meth:`ViewsInTurn.painted_image`), weighing ``weight`` where they make at least
    :data:`PAINTED_SHARE` of the coverage and 0 elsewhere; None before anything is painted or ``weight`` <= 0."""
    if weight <= 0 or not bool(turn.painted.any()):
        return None
    image, share = turn.painted_image(view)
    guide = image.reshape(camera.height, camera.width, 3).permute(2, 0, 1)
    mask = (share >= PAINTED_SHARE).float().reshape(1, camera.height, camera.width)
    return _resize(guide, *size).clamp(0.0, 1.0), weight * _resize(mask, *size)[0]
