"""DINO patch features for the fit loss, on tiny random transformers models saved to a temporary folder.

The folders go through the real loading code (``save_pretrained`` then ``load_dino``); nothing is
downloaded.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")

from transformers import (  # noqa: E402
    Dinov2Config,
    Dinov2Model,
    Dinov2WithRegistersConfig,
    Dinov2WithRegistersModel,
    ViTConfig,
    ViTModel,
)

from dresg_addon.method.config import preset_run  # noqa: E402
from dresg_addon.method.dino import FEATURE_SIZE, DinoFeatures  # noqa: E402
from dresg_addon.method.loop import stylize  # noqa: E402
from dresg_addon.scene.camera import Camera, look_at  # noqa: E402
from dresg_addon.scene.gaussians import SH_C0, GaussianScene  # noqa: E402
from dresg_addon.util.errors import ModelError  # noqa: E402
from dresg_addon.util.feature_models import preprocess  # noqa: E402

TINY = {"hidden_size": 16, "num_hidden_layers": 1, "num_attention_heads": 2}


def _save(model: torch.nn.Module, folder):
    model.eval().save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def dinov2(tmp_path_factory):
    torch.manual_seed(0)
    config = Dinov2Config(**TINY, mlp_ratio=2, patch_size=14, image_size=28)
    return _save(Dinov2Model(config), tmp_path_factory.mktemp("dino") / "dinov2")


def _images(batch: int = 2, height: int = 32, width: int = 48) -> torch.Tensor:
    gen = torch.Generator().manual_seed(3)
    coarse = torch.rand(batch, 3, height // 8, width // 8, generator=gen)
    return torch.nn.functional.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)


def _tokens(features: DinoFeatures, images: torch.Tensor) -> torch.Tensor:  # -> [B, T, C]
    with torch.no_grad():
        return features.model.model(pixel_values=preprocess(features.model, images)).last_hidden_state


def test_dinov2_features_are_the_patch_tokens_on_a_grid(dinov2):
    features = DinoFeatures(dinov2)
    images = _images()
    maps = features(images)
    side = FEATURE_SIZE // 14
    assert maps.shape == (2, 16, side, side) and maps.dtype == torch.float32
    tokens = _tokens(features, images)
    assert tokens.shape[1] == 1 + side * side  # CLS + patches
    # Position (r, c) of the map is patch token r * side + c; the CLS token is left out.
    for r, c in ((0, 0), (0, side - 1), (5, 3), (side - 1, side - 1)):
        torch.testing.assert_close(maps[:, :, r, c], tokens[:, 1 + r * side + c])


def test_features_are_differentiable_in_the_image_and_the_model_is_frozen(dinov2):
    features = DinoFeatures(dinov2)
    assert not any(p.requires_grad for p in features.model.model.parameters())
    images = _images(1).requires_grad_(True)
    features(images).pow(2).mean().backward()
    assert images.grad is not None and torch.isfinite(images.grad).all() and images.grad.abs().sum() > 0


def test_register_tokens_are_left_out(tmp_path):
    torch.manual_seed(0)
    config = Dinov2WithRegistersConfig(**TINY, mlp_ratio=2, patch_size=14, image_size=28, num_register_tokens=4)
    features = DinoFeatures(_save(Dinov2WithRegistersModel(config), tmp_path / "reg"))
    images = _images(1)
    maps = features(images)
    side = FEATURE_SIZE // 14
    tokens = _tokens(features, images)
    assert tokens.shape[1] == 1 + 4 + side * side
    torch.testing.assert_close(maps.flatten(2).transpose(1, 2), tokens[:, 5:])


def test_dino_v1_vit_keeps_its_own_input_size(tmp_path):
    torch.manual_seed(0)
    config = ViTConfig(**TINY, intermediate_size=32, image_size=32, patch_size=8)
    features = DinoFeatures(_save(ViTModel(config, add_pooling_layer=False), tmp_path / "vit"))
    maps = features(_images(2))
    assert maps.shape == (2, 16, 4, 4)


def test_missing_or_wrong_folders_raise_model_error(tmp_path):
    with pytest.raises(ModelError, match="no such folder"):
        DinoFeatures(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ModelError, match="config.json"):
        DinoFeatures(tmp_path / "empty")


def _tiny_scene(n: int = 150) -> GaussianScene:
    rng = np.random.default_rng(0)
    means = rng.normal(size=(n, 3))
    means = 0.5 * means / np.linalg.norm(means, axis=1, keepdims=True)
    quats = np.tile(np.float32([1, 0, 0, 0]), (n, 1))
    colors = rng.uniform(0.4, 0.9, (n, 3))
    return GaussianScene(
        means.astype(np.float32),
        np.full((n, 3), math.log(0.08), np.float32),
        quats,
        np.full(n, 2.0, np.float32),
        ((colors - 0.5) / SH_C0).astype(np.float32),
    )


@pytest.mark.slow
def test_stylize_uses_dino_features_when_given_local_weights(dinov2):
    scene = _tiny_scene()
    cameras = [
        Camera(48, 32, 40.0, 40.0, 24.0, 16.0, look_at([2 * math.sin(a), -0.5, -2 * math.cos(a)], [0, 0, 0]), f"c{i}")
        for i, a in enumerate((0.0, 2.0))
    ]
    style = np.broadcast_to(np.float32([0.1, 0.2, 0.9]), (24, 32, 3))
    # Geometry offsets: the feature term shapes the Adam fit; a solved colour fit has none.
    config, plan = preset_run(
        "paper", stages=1, updates_per_stage=2, fit_steps=2, post_steps=0, proposal_width=32, proposal_height=24
    )
    messages = []
    with_dino = stylize(scene, cameras, style, config, plan=plan, dino_path=str(dinov2), messages=messages.append)
    assert any(m.startswith("feature loss: DINO") for m in messages), messages
    assert np.isfinite(with_dino.scene.sh_dc).all()
    messages = []
    with_patches = stylize(scene, cameras, style, config, plan=plan, messages=messages.append)
    assert any("weight-free patch features" in m for m in messages), messages
    assert not np.array_equal(with_dino.scene.sh_dc, with_patches.scene.sh_dc)
