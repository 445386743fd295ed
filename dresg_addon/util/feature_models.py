"""Image encoders from local weights: CLIP and DINO folders loaded with transformers, never downloaded.

``load_clip`` takes a local transformers ``CLIPModel`` (or ``CLIPVisionModelWithProjection``) folder,
``load_dino`` a local ``ViTModel`` (DINO v1), ``Dinov2Model`` or DINOv3 ViT folder. Images are resized
to the model's input size (224 x 224 for the paper's models; DINOv2/v3 take 224 x 224 too) and
normalised with the folder's ``preprocessor_config.json`` mean and std, or the model family's standard
ones. transformers is imported only here, on first use. The method's DINO feature loss
(:mod:`dresg_addon.method.dino`) and the evaluation's CLIP-S / DINO-C
(:mod:`dresg_addon.evaluation.clip_dino`) both load through this module.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass
from pathlib import Path

import torch

from .errors import ModelError, with_path
from .imageio import resize_image

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CLIP_TYPES = ("clip", "clip_vision_model")
DINO_TYPES = ("vit", "dinov2", "dinov2_with_registers", "dinov3_vit")
INTERPOLATING_TYPES = ("dinov2", "dinov2_with_registers", "dinov3_vit")  # any input size works
PAPER_SIZE = 224


@dataclass
class FeatureModel:
    """A loaded image encoder and its preprocessing."""

    kind: str  # "clip" or "dino"
    model: torch.nn.Module
    model_type: str  # transformers config.model_type
    image_size: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    device: torch.device
    path: Path


@contextlib.contextmanager
def _quiet_transformers():
    """Silence transformers' load-time chatter (reports, progress bars); errors still raise."""
    from transformers.utils import logging

    level, bars = logging.get_verbosity(), logging.is_progress_bar_enabled()
    logging.set_verbosity_error()
    logging.disable_progress_bar()
    try:
        yield
    finally:
        logging.set_verbosity(level)
        if bars:
            logging.enable_progress_bar()


def _normalisation(path: Path, default_mean, default_std) -> tuple[tuple, tuple]:
    config = path / "preprocessor_config.json"
    if not config.is_file():
        return tuple(default_mean), tuple(default_std)
    try:
        data = json.loads(config.read_text(encoding="utf-8"))
        mean, std = tuple(float(v) for v in data["image_mean"]), tuple(float(v) for v in data["image_std"])
    except (OSError, ValueError, KeyError, TypeError):
        raise ModelError(with_path(config, "unreadable image_mean / image_std")) from None
    if len(mean) != 3 or len(std) != 3 or min(std) <= 0:
        raise ModelError(with_path(config, f"image_mean {mean} / image_std {std} must be 3 values, std > 0"))
    return mean, std


def _config(path, what: str, allowed: tuple[str, ...]):
    try:
        import transformers
    except ImportError:
        raise ModelError(f"{what} metrics need the transformers package, which is not installed") from None
    path = Path(path)
    if not path.is_dir():
        raise ModelError(with_path(path, f"no such folder (expected a local transformers {what} model folder)"))
    if not (path / "config.json").is_file():
        raise ModelError(with_path(path, f"no config.json: not a transformers {what} model folder"))
    try:
        with _quiet_transformers():
            config = transformers.AutoConfig.from_pretrained(path, local_files_only=True)
    except (OSError, ValueError, KeyError) as error:
        raise ModelError(with_path(path, f"cannot read config.json ({_one_line(error)})")) from None
    if config.model_type not in allowed:
        raise ModelError(
            with_path(path, f"model type {config.model_type!r} is not a {what} model (expected {', '.join(allowed)})")
        )
    return transformers, path, config


def _one_line(error: Exception) -> str:
    text = " ".join(str(error).split())
    return text[:200] + ("..." if len(text) > 200 else "") if text else error.__class__.__name__


def _load(cls, path: Path, what: str, device, **kwargs) -> torch.nn.Module:
    try:
        with _quiet_transformers():
            model, info = cls.from_pretrained(path, local_files_only=True, output_loading_info=True, **kwargs)
    except (OSError, ValueError, KeyError, RuntimeError) as error:
        raise ModelError(with_path(path, f"cannot load the {what} weights ({_one_line(error)})")) from None
    # transformers fills missing weights with random ones and only warns: the scores would be noise.
    missing = sorted(info.get("missing_keys", ()))
    if missing:
        raise ModelError(with_path(path, f"the {what} weights lack {len(missing)} parameters (e.g. {missing[0]})"))
    return model.to(device).eval().float()


def check_model_folder(path, kind: str) -> None:
    """Raise ModelError unless ``path`` is a local transformers folder of the right family ("clip" or "dino").

    Reads only config.json, so that a command fails before its renders, and loads the weights later.
    """
    if kind not in ("clip", "dino"):
        raise ValueError(f"check_model_folder: kind must be 'clip' or 'dino', not {kind!r}")
    _config(path, kind.upper(), CLIP_TYPES if kind == "clip" else DINO_TYPES)


def load_clip(path, device="cpu") -> FeatureModel:
    """A local CLIP model folder (``CLIPModel`` or ``CLIPVisionModelWithProjection``) for CLIP-S."""
    transformers, path, config = _config(path, "CLIP", CLIP_TYPES)
    if config.model_type == "clip":
        cls, image_size = transformers.CLIPModel, config.vision_config.image_size
    else:
        cls, image_size = transformers.CLIPVisionModelWithProjection, config.image_size
    model = _load(cls, path, "CLIP", device)
    mean, std = _normalisation(path, CLIP_MEAN, CLIP_STD)
    return FeatureModel("clip", model, config.model_type, int(image_size), mean, std, torch.device(device), path)


def load_dino(path, device="cpu") -> FeatureModel:
    """A local DINO model folder (``ViTModel`` for DINO v1, ``Dinov2Model``, DINOv3 ViT) for DINO-C."""
    transformers, path, config = _config(path, "DINO", DINO_TYPES)
    # DINO checkpoints have no pooler; the CLS token is the feature.
    kwargs = {"add_pooling_layer": False} if config.model_type == "vit" else {}
    model = _load(transformers.AutoModel, path, "DINO", device, **kwargs)
    size = PAPER_SIZE if config.model_type in INTERPOLATING_TYPES else int(config.image_size)
    mean, std = _normalisation(path, IMAGENET_MEAN, IMAGENET_STD)
    return FeatureModel("dino", model, config.model_type, size, mean, std, torch.device(device), path)


def preprocess(model: FeatureModel, images: torch.Tensor) -> torch.Tensor:  # [B, 3, H, W] in [0, 1]
    x = resize_image(images.float().clamp(0.0, 1.0), model.image_size, model.image_size)
    mean = torch.tensor(model.mean).view(1, 3, 1, 1)
    std = torch.tensor(model.std).view(1, 3, 1, 1)
    return ((x - mean) / std).to(model.device)


def image_embeddings(model: FeatureModel, images, batch_size: int = 16) -> torch.Tensor:
    """[B, D] float32 embeddings of images ([B, 3, H, W] or a list of [3, H, W], values in [0, 1]).

    CLIP: the projected image embedding. DINO: the CLS token of the last hidden state.
    """
    if isinstance(images, torch.Tensor):
        images = list(images[None] if images.ndim == 3 else images)
    features = []
    with torch.no_grad():
        for start in range(0, len(images), batch_size):
            chunk = images[start : start + batch_size]
            for image in chunk:
                if image.ndim != 3 or image.shape[0] != 3:
                    raise ValueError(f"image_embeddings: images must be [3, H, W], got shape {tuple(image.shape)}")
            pixels = torch.cat([preprocess(model, image[None]) for image in chunk])
            if model.kind == "clip" and model.model_type == "clip":
                pooled = model.model.vision_model(pixel_values=pixels).pooler_output
                out = model.model.visual_projection(pooled)
            elif model.kind == "clip":
                out = model.model(pixel_values=pixels).image_embeds
            else:
                out = model.model(pixel_values=pixels).last_hidden_state[:, 0]
            features.append(out.float().cpu())
    return torch.cat(features)
