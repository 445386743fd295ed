"""DINO patch features for the fit loss's feature term (Eq. 16), from local weights only.

The release uses DINOv2 patch features at 224 px; any local ViT / DINOv2 folder that
:func:`~dresg_addon.util.feature_models.load_dino` accepts works. Differentiable in the input image.
"""

from __future__ import annotations

import torch

from ..util.feature_models import load_dino, preprocess

FEATURE_SIZE = 224  # the release's DINO input size


class DinoFeatures:
    """images [B, 3, H, W] in [0, 1] -> patch-token feature maps [B, C, h, w] (CLS dropped), on the images' device
    whatever the model's."""

    def __init__(self, path, device="cpu"):
        self.model = load_dino(path, device)
        self.model.model.requires_grad_(False)
        self.model.image_size = FEATURE_SIZE if self.model.model_type != "vit" else self.model.image_size

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        pixels = preprocess(self.model, images)
        tokens = self.model.model(pixel_values=pixels).last_hidden_state  # [B, 1 (+ registers) + h*w, C]
        side = pixels.shape[-1] // self.model.model.config.patch_size
        patches = tokens[:, -side * side :]
        return patches.transpose(1, 2).reshape(tokens.shape[0], -1, side, side).float().to(images.device)
