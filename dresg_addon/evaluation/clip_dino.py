"""The paper's CLIP-S and DINO-C (Sec. 5.1, "Metrics"), computed when the user has local weights.

- CLIP-S: mean cosine between the CLIP image embeddings of each render and of the style image
  (the paper uses CLIP ViT-B/32).
- DINO-C: mean cosine between the DINO CLS features of each stylized render and of the content image
  (the base render) from the same pose (the paper uses DINO ViT-S/16).

The encoders load from local folders through :mod:`dresg_addon.util.feature_models` (re-exported
here, so one import gives the loaders and the scores).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..util.feature_models import (
    CLIP_MEAN,
    FeatureModel,
    check_model_folder,
    image_embeddings,
    load_clip,
    load_dino,
)

__all__ = [
    "CLIP_MEAN",
    "FeatureModel",
    "check_model_folder",
    "clip_style_score",
    "dino_content_score",
    "image_embeddings",
    "load_clip",
    "load_dino",
]


def clip_style_score(model: FeatureModel, renders, style: torch.Tensor) -> torch.Tensor:  # -> [B]
    """CLIP-S per render: cos(E(render), E(style)) with E the CLIP image embedding; the paper averages it."""
    if model.kind != "clip":
        raise ValueError("clip_style_score needs a model from load_clip")
    ours = image_embeddings(model, renders)
    ref = image_embeddings(model, style[None] if style.ndim == 3 else style)
    return F.cosine_similarity(ours, ref.expand_as(ours), dim=1, eps=1e-8)


def dino_content_score(model: FeatureModel, renders, contents) -> torch.Tensor:  # -> [B]
    """DINO-C per render: cos(F(render_i), F(content_i)) with F the DINO CLS feature, same pose i."""
    if model.kind != "dino":
        raise ValueError("dino_content_score needs a model from load_dino")
    ours, ref = image_embeddings(model, renders), image_embeddings(model, contents)
    if ours.shape != ref.shape:
        raise ValueError(f"dino_content_score: {ours.shape[0]} renders but {ref.shape[0]} content images")
    return F.cosine_similarity(ours, ref, dim=1, eps=1e-8)
