"""Stable Diffusion 1.5 component configs, written down so a single-file checkpoint loads without the Hub.

These are the public architecture facts of SD1.5 (the ``unet/``, ``vae/`` and ``text_encoder/``
``config.json`` of a diffusers SD1.5 folder), in the keyword form of ``UNet2DConditionModel``,
``AutoencoderKL`` and ``transformers.CLIPTextConfig``. Parameter counts they give: U-Net 859,520,964;
VAE 83,653,863; CLIP ViT-L/14 text encoder 123,060,480.

``attention_head_dim=8`` is diffusers' historical name for the number of heads (8 heads per layer).
"""

from __future__ import annotations

from dataclasses import dataclass, field

SD15_UNET_CONFIG: dict = {
    "act_fn": "silu",
    "attention_head_dim": 8,
    "block_out_channels": [320, 640, 1280, 1280],
    "center_input_sample": False,
    "cross_attention_dim": 768,
    "down_block_types": ["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"],
    "downsample_padding": 1,
    "flip_sin_to_cos": True,
    "freq_shift": 0,
    "in_channels": 4,
    "layers_per_block": 2,
    "mid_block_scale_factor": 1,
    "norm_eps": 1e-05,
    "norm_num_groups": 32,
    "out_channels": 4,
    "sample_size": 64,
    "up_block_types": ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"],
}

SD15_VAE_CONFIG: dict = {
    "act_fn": "silu",
    "block_out_channels": [128, 256, 512, 512],
    "down_block_types": ["DownEncoderBlock2D"] * 4,
    "in_channels": 3,
    "latent_channels": 4,
    "layers_per_block": 2,
    "norm_num_groups": 32,
    "out_channels": 3,
    "sample_size": 512,
    "scaling_factor": 0.18215,
    "up_block_types": ["UpDecoderBlock2D"] * 4,
}

# CLIP ViT-L/14 text tower. Token ids are the real ones of the CLIP BPE vocabulary (the config shipped
# with SD1.5 says 0/2/1, which only matters for the pooled output that SD does not use).
SD15_TEXT_ENCODER_CONFIG: dict = {
    "attention_dropout": 0.0,
    "bos_token_id": 49406,
    "dropout": 0.0,
    "eos_token_id": 49407,
    "hidden_act": "quick_gelu",
    "hidden_size": 768,
    "initializer_factor": 1.0,
    "initializer_range": 0.02,
    "intermediate_size": 3072,
    "layer_norm_eps": 1e-05,
    "max_position_embeddings": 77,
    "num_attention_heads": 12,
    "num_hidden_layers": 12,
    "pad_token_id": 49407,
    "projection_dim": 768,
    "vocab_size": 49408,
}

# The empty prompt as SD1.x's tokenizer encodes it: BOS, then EOS repeated as padding to 77 tokens.
EMPTY_PROMPT_IDS: tuple[int, ...] = (49406,) + (49407,) * 76


@dataclass(frozen=True)
class SD15Configs:
    """The three component configs a single-file checkpoint is read with (SD1.5's by default).

    Only an SD1.x-architecture checkpoint fits; other values serve smaller stand-ins in tests.
    """

    unet: dict = field(default_factory=lambda: dict(SD15_UNET_CONFIG))
    vae: dict = field(default_factory=lambda: dict(SD15_VAE_CONFIG))
    text_encoder: dict = field(default_factory=lambda: dict(SD15_TEXT_ENCODER_CONFIG))
