"""The ``sd15`` proposal backend: frozen Stable Diffusion 1.5 as the feature extractor of Sec. 4.1.

The state is the VAE latent of the image (``[4, H/8, W/8]``, float32). ``features`` runs the U-Net on
that clean latent at timestep t with the empty-prompt embedding (no noise, no guidance) and collects
Q/K/V and the attention output of the selected self-attention layers (Phi^attn, Eq. 5,
``eq:attn-features``); the energy and the Adam loop are the shared ones of ``base``.

Weights come only from local files: a diffusers folder (``unet/``, ``vae/``, ``text_encoder/``) or one
original-format ``.safetensors`` checkpoint, read with the configs of ``sd15_configs`` and diffusers'
key conversion. Nothing is downloaded. diffusers and transformers are imported inside the functions
that need them, so importing this module stays cheap.

Self-attention layers are numbered in execution order: down blocks 0-5, mid block 6, up blocks 7-15.
``unet.named_modules()`` lists the mid block last, so layers are selected by name from that order.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from functools import partial
from pathlib import Path

import torch

from ...util.errors import ConfigError, ModelError, NumericalError, with_path
from ..schedule import SD15_TRAIN_TIMESTEPS
from .base import AttentionBackend, AttentionFeatures, EnergyTerms
from .sd15_configs import EMPTY_PROMPT_IDS, SD15Configs

LATENT_SCALE = 0.18215  # SD1.x VAE latent scaling
DEFAULT_LAYERS = (10, 11, 12, 13, 14, 15)  # up_blocks.2 and up_blocks.3, the paper's layers
LATENT_CACHE_SIZE = 256  # reference latents (36 KB each at 448x320)

_COMPONENTS = (("unet", "U-Net"), ("vae", "VAE"), ("text_encoder", "CLIP text encoder"))
_STANDARD_WEIGHTS = {
    "diffusion_pytorch_model.safetensors",
    "diffusion_pytorch_model.safetensors.index.json",
    "diffusion_pytorch_model.bin",
    "model.safetensors",
    "model.safetensors.index.json",
    "pytorch_model.bin",
}
_CHECKPOINT_PREFIXES = (
    ("model.diffusion_model.", "U-Net"),
    ("first_stage_model.", "VAE"),
    ("cond_stage_model.transformer.", "CLIP text encoder"),
)


# --- layers -----------------------------------------------------------------------------------------


def self_attention_names(unet) -> list[str]:
    """Names of the U-Net's self-attention (``attn1``) modules in the order ``forward`` runs them.

    Walks down blocks, the mid block, then up blocks; inside a block, transformers run in list order.
    """
    blocks = [(f"down_blocks.{i}", block) for i, block in enumerate(unet.down_blocks)]
    if unet.mid_block is not None:
        blocks.append(("mid_block", unet.mid_block))
    blocks += [(f"up_blocks.{i}", block) for i, block in enumerate(unet.up_blocks)]
    names = []
    for prefix, block in blocks:
        for a, transformer in enumerate(getattr(block, "attentions", None) or []):
            for b, layer in enumerate(getattr(transformer, "transformer_blocks", None) or []):
                if getattr(layer, "attn1", None) is not None:
                    names.append(f"{prefix}.attentions.{a}.transformer_blocks.{b}.attn1")
    return names


def _check_layers(layers: Sequence[int]) -> tuple[int, ...]:
    layers = tuple(int(layer) for layer in layers)
    if not layers:
        raise ConfigError("sd15 backend: at least one self-attention layer is needed")
    if len(set(layers)) != len(layers) or min(layers) < 0:
        raise ConfigError(f"sd15 backend: layers must be distinct non-negative indices, got {list(layers)}")
    return layers


def _split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:  # [B, T, heads * d] -> [B, heads, T, d]
    return x.unflatten(-1, (heads, -1)).transpose(1, 2)


class _StopForward(Exception):
    """Raised by the hook of the last needed layer: the rest of the U-Net does not change the features."""


class _Capture:
    """Forward hooks on to_q / to_k / to_v and a pre-hook on to_out[0] of the selected attn1 modules.

    The hooks do nothing unless a capture is running, so the U-Net stays usable on its own.
    """

    def __init__(self, unet, names: Sequence[str]):
        self._running = False
        self._stop_at = None
        self._store: dict[tuple[str, int], torch.Tensor] = {}
        for slot, name in enumerate(names):
            attn = unet.get_submodule(name)
            for kind in ("q", "k", "v"):
                getattr(attn, f"to_{kind}").register_forward_hook(partial(self._on_projection, kind, slot, attn.heads))
            attn.to_out[0].register_forward_pre_hook(partial(self._on_output, slot, attn.heads))

    def _on_projection(self, kind, slot, heads, module, args, output):
        if self._running:
            self._store[(kind, slot)] = _split_heads(output, heads)

    def _on_output(self, slot, heads, module, args):
        if self._running:
            self._store[("o", slot)] = _split_heads(args[0], heads)
            if slot == self._stop_at:
                raise _StopForward

    @contextmanager
    def running(self, stop_at: int | None) -> Iterator[dict[tuple[str, int], torch.Tensor]]:
        """Capture into the yielded dict; ``stop_at`` (a slot) ends the forward after that layer's output."""
        self._store = {}
        self._running, self._stop_at = True, stop_at
        try:
            yield self._store
        finally:
            self._running, self._stop_at = False, None


# --- device and dtype ------------------------------------------------------------------------------

_DTYPES = {
    "float32": torch.float32,
    "fp32": torch.float32,
    "float16": torch.float16,
    "fp16": torch.float16,
    "bfloat16": torch.bfloat16,
    "bf16": torch.bfloat16,
}


def default_device() -> torch.device:
    """CUDA if available, else Apple MPS if available, else CPU."""
    if torch.cuda.is_available():
        return torch.device("cuda")
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        return torch.device("mps")
    return torch.device("cpu")


def default_dtype(device: torch.device) -> torch.dtype:
    """bf16 on CUDA (fp16 on GPUs without bf16), fp32 elsewhere (bf16 support on MPS depends on the OS)."""
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return torch.float32


def _resolve_device(device) -> torch.device:
    if device is None:
        return default_device()
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as error:
        raise ConfigError(f"sd15 backend: unknown device {device!r}") from error
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("sd15 backend: CUDA was asked for but is not available")
    if device.type == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
        raise ConfigError("sd15 backend: MPS was asked for but is not available")
    return device


def _resolve_dtype(dtype, device: torch.device) -> torch.dtype:
    if dtype is None:
        return default_dtype(device)
    if isinstance(dtype, torch.dtype):
        if dtype not in _DTYPES.values():
            raise ConfigError(f"sd15 backend: unsupported dtype {dtype}")
        return dtype
    if str(dtype).lower() not in _DTYPES:
        raise ConfigError(f"sd15 backend: unknown dtype {dtype!r} (choose {', '.join(_DTYPES)})")
    return _DTYPES[str(dtype).lower()]


# --- loading ---------------------------------------------------------------------------------------


def _summary(error: Exception) -> str:
    """One line of a loader's error: the size-mismatch line when there is one, else the first line."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    for line in lines:
        if "size mismatch" in line:
            return line[:300]
    return (lines[0] if lines else type(error).__name__)[:300]


def _key_problems(missing: Sequence[str], mismatched: Sequence[str]) -> str:
    parts = []
    if missing:
        parts.append(f"{len(missing)} missing (e.g. {sorted(missing)[0]})")
    if mismatched:
        parts.append(f"{len(mismatched)} of the wrong shape (e.g. {sorted(mismatched)[0]})")
    return ", ".join(parts)


@contextmanager
def _quiet_loaders() -> Iterator[None]:
    """Silence diffusers / transformers warnings and progress bars during a load; problems become ModelError."""
    from diffusers.utils import logging as diffusers_logging
    from transformers.utils import logging as transformers_logging

    saved = [
        (log, log.get_verbosity(), log.is_progress_bar_enabled()) for log in (diffusers_logging, transformers_logging)
    ]
    for log, _, _ in saved:
        log.set_verbosity_error()
        log.disable_progress_bar()
    try:
        yield
    finally:
        for log, verbosity, bar in saved:
            log.set_verbosity(verbosity)
            if bar:
                log.enable_progress_bar()


def _weights_variant(folder: Path) -> str | None:
    """``None`` for standard weight names, ``"fp16"`` for a folder that only has the fp16 variant."""
    names = {path.name for path in folder.iterdir()}
    if names & _STANDARD_WEIGHTS:
        return None
    if any(".fp16." in name for name in names):
        return "fp16"
    raise ModelError(with_path(folder, "no weight file (diffusion_pytorch_model.safetensors or model.safetensors)"))


def _load_folder(path: Path, dtype: torch.dtype) -> dict:
    """U-Net, VAE and text encoder of a diffusers folder, each checked for missing or misshapen weights."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextModel

    classes = {"unet": UNet2DConditionModel, "vae": AutoencoderKL, "text_encoder": CLIPTextModel}
    models = {}
    for sub, label in _COMPONENTS:
        folder = path / sub
        if not (folder / "config.json").is_file():
            raise ModelError(
                with_path(
                    path,
                    f"not a diffusers Stable Diffusion folder: {sub}/config.json is missing "
                    "(for a single checkpoint, give the .safetensors file itself)",
                )
            )
        variant = _weights_variant(folder)
        try:
            model, info = classes[sub].from_pretrained(
                str(path), subfolder=sub, local_files_only=True, dtype=dtype, variant=variant, output_loading_info=True
            )
        except Exception as error:  # the loaders raise OSError, ValueError, RuntimeError, safetensors errors...
            raise ModelError(with_path(folder, f"cannot load the {label}: {_summary(error)}")) from error
        problems = _key_problems(sorted(info.get("missing_keys", ())), sorted(info.get("mismatched_keys", ())))
        if problems:
            raise ModelError(with_path(folder, f"{label} weights do not match its config: {problems}"))
        models[sub] = model
    return models


def _assign_weights(cls, config: dict, state: dict, path: Path, label: str):
    """Build ``cls`` from ``config`` without allocating, then take the converted weights as its parameters."""
    with torch.device("meta"):
        model = cls.from_config(config)
    expected = model.state_dict()
    missing = [key for key in expected if state.get(key) is None]
    mismatched = [
        key for key in expected if state.get(key) is not None and tuple(state[key].shape) != tuple(expected[key].shape)
    ]
    problems = _key_problems(missing, mismatched)
    if problems:
        raise ModelError(with_path(path, f"{label} weights do not match SD1.5: {problems}"))
    model.load_state_dict({key: state[key] for key in expected}, strict=True, assign=True)
    return model.eval()


def _load_single_file(path: Path, dtype: torch.dtype, configs: SD15Configs) -> dict:
    """U-Net, VAE and text encoder of one original-format (CompVis / A1111) ``.safetensors`` checkpoint.

    Key conversion is diffusers' own; weights are checked key by key (``from_single_file`` would fill
    missing ones with random values without a word when ``accelerate`` is not installed).
    """
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from diffusers.loaders.single_file_utils import (
        convert_ldm_clip_checkpoint,
        convert_ldm_unet_checkpoint,
        convert_ldm_vae_checkpoint,
    )
    from safetensors.torch import load_file
    from transformers import CLIPTextConfig, CLIPTextModel

    try:
        checkpoint = load_file(str(path))
    except Exception as error:  # safetensors raises its own error type for a bad header
        raise ModelError(with_path(path, f"not a readable .safetensors file ({_summary(error)})")) from error
    for prefix, label in _CHECKPOINT_PREFIXES:
        if not any(key.startswith(prefix) for key in checkpoint):
            raise ModelError(with_path(path, f"no {label} weights ({prefix}*): not a Stable Diffusion 1.x checkpoint"))
    try:
        unet_state = convert_ldm_unet_checkpoint(checkpoint, configs.unet, extract_ema=True)
        vae_state = convert_ldm_vae_checkpoint(checkpoint, configs.vae)
        text_state = convert_ldm_clip_checkpoint(checkpoint)
    except Exception as error:  # the converters index keys they expect: a foreign layout raises anything
        raise ModelError(with_path(path, f"weights do not match SD1.5 ({_summary(error)})")) from error
    models = {
        "unet": _assign_weights(UNet2DConditionModel, configs.unet, unet_state, path, "U-Net"),
        "vae": _assign_weights(AutoencoderKL, configs.vae, vae_state, path, "VAE"),
    }
    try:
        text_encoder, info = CLIPTextModel.from_pretrained(
            None,
            config=CLIPTextConfig(**configs.text_encoder),
            state_dict=text_state,
            local_files_only=True,
            output_loading_info=True,
        )
    except Exception as error:  # a size mismatch raises RuntimeError; say which component failed
        raise ModelError(with_path(path, f"cannot load the CLIP text encoder: {_summary(error)}")) from error
    problems = _key_problems(sorted(info.get("missing_keys", ())), sorted(info.get("mismatched_keys", ())))
    if problems:
        raise ModelError(with_path(path, f"CLIP text encoder weights do not match SD1.5: {problems}"))
    models["text_encoder"] = text_encoder
    return {name: model.to(dtype) for name, model in models.items()}


def load_sd15(model_path, dtype: torch.dtype = torch.float32, configs: SD15Configs | None = None) -> dict:
    """``{"unet", "vae", "text_encoder"}`` from a local diffusers folder or ``.safetensors`` checkpoint, on CPU.

    Raises ModelError naming the file and the problem: missing path, wrong layout, weights that do not fit.
    """
    path = Path(model_path).expanduser()
    if not str(model_path) or not path.exists():
        raise ModelError(
            with_path(path, "no such file or folder (give an SD1.5 diffusers folder or .safetensors file)")
        )
    with _quiet_loaders():
        if path.is_dir():
            models = _load_folder(path, dtype)
        elif path.suffix.lower() == ".safetensors":
            models = _load_single_file(path, dtype, configs or SD15Configs())
        else:
            raise ModelError(
                with_path(path, "not a Stable Diffusion model: give a diffusers folder or a .safetensors checkpoint")
            )
    _check_architecture(path, models)
    return models


def _check_architecture(path: Path, models: dict) -> None:
    unet, vae, text_encoder = models["unet"], models["vae"], models["text_encoder"]
    if unet.config.in_channels != 4 or vae.config.latent_channels != 4:
        raise ModelError(
            with_path(
                path,
                f"U-Net takes {unet.config.in_channels} latent channels and the VAE makes "
                f"{vae.config.latent_channels}; SD1.5 uses 4 (inpainting and depth models do not fit)",
            )
        )
    width = text_encoder.config.hidden_size
    if unet.config.cross_attention_dim != width:
        raise ModelError(
            with_path(
                path,
                f"text encoder width {width} does not match the U-Net's cross-attention width "
                f"{unet.config.cross_attention_dim} (not an SD1.x model?)",
            )
        )
    config = text_encoder.config
    if config.max_position_embeddings < len(EMPTY_PROMPT_IDS) or config.vocab_size <= max(EMPTY_PROMPT_IDS):
        raise ModelError(with_path(path, "the text encoder is not CLIP's (77 positions, 49408 tokens expected)"))


# --- the backend -----------------------------------------------------------------------------------


def _image_key(image: torch.Tensor) -> tuple:
    """Content key of an image: equal pixels give equal keys, whatever tensor object holds them."""
    data = image.detach().to("cpu", torch.float32).contiguous()
    return tuple(data.shape), hashlib.blake2b(data.numpy().tobytes(), digest_size=16).hexdigest()


def _lru_put(cache: OrderedDict, key, value, capacity: int) -> None:
    if capacity <= 0:
        return
    cache[key] = value
    cache.move_to_end(key)
    while len(cache) > capacity:
        cache.popitem(last=False)


class SD15Backend(AttentionBackend):
    """Frozen SD1.5: VAE latents as the state, U-Net self-attention Q/K/V/O as the features.

    ``layers`` are zero-based self-attention indices in execution order (default 10-15). Reference
    features are cached per (image content, timestep), so the style pass at a timestep runs once for
    all views; ``feature_cache_size`` entries are kept (0 turns the cache off). Tensors come back on
    the backend's device. ``learning_rate`` and ``terms`` (the content weight and the ablation switches)
    are those of the attention energy's Adam step.
    """

    name = "sd15"

    def __init__(
        self,
        model_path,
        device=None,
        dtype=None,
        layers: Sequence[int] = DEFAULT_LAYERS,
        feature_cache_size: int = 24,
        configs: SD15Configs | None = None,
        learning_rate: float = 0.05,
        terms: EnergyTerms | None = None,  # None: the paper's (EnergyTerms())
    ):
        self.learning_rate, self.terms = learning_rate, terms or EnergyTerms()
        self.layers = _check_layers(layers)
        if int(feature_cache_size) < 0:
            raise ConfigError(f"sd15 backend: feature_cache_size must be >= 0, got {feature_cache_size}")
        self.device = _resolve_device(device)
        self.dtype = _resolve_dtype(dtype, self.device)
        self.feature_cache_size = int(feature_cache_size)
        models = load_sd15(model_path, dtype=self.dtype, configs=configs)
        names = self_attention_names(models["unet"])
        if max(self.layers) >= len(names):
            raise ModelError(
                with_path(
                    Path(model_path),
                    f"the U-Net has {len(names)} self-attention layers; layer {max(self.layers)} was asked for",
                )
            )
        self.layer_names = [names[layer] for layer in self.layers]
        self.unet = models["unet"].to(self.device).eval().requires_grad_(False)
        self.vae = models["vae"].to(self.device).eval().requires_grad_(False)
        self.empty_prompt = self._encode_empty_prompt(models["text_encoder"])  # [1, 77, C]
        self._capture = _Capture(self.unet, self.layer_names)
        self._last_slot = max(range(len(self.layers)), key=lambda slot: self.layers[slot])
        self._latents: OrderedDict = OrderedDict()
        self._features: OrderedDict = OrderedDict()

    def _encode_empty_prompt(self, text_encoder) -> torch.Tensor:
        """The empty prompt's last hidden state, computed once; the text encoder is not kept."""
        text_encoder = text_encoder.to(self.device).eval()
        ids = torch.tensor([EMPTY_PROMPT_IDS], device=self.device)
        with torch.no_grad():
            return text_encoder(input_ids=ids).last_hidden_state.to(self.dtype)

    # -- state <-> image

    def encode(self, image: torch.Tensor) -> torch.Tensor:  # image [3, H, W] in [0, 1] -> [4, H/8, W/8]
        """VAE latent ``latent_dist.mean * 0.18215`` of ``2 x - 1``; H and W must be multiples of 8."""
        if image.dim() != 3 or image.shape[0] != 3 or image.shape[1] % 8 or image.shape[2] % 8:
            raise ValueError(f"sd15 encode expects a [3, H, W] image with H, W multiples of 8, got {list(image.shape)}")
        x = image.detach().to(self.device, self.dtype)[None] * 2.0 - 1.0
        with torch.no_grad():
            latent = self.vae.encode(x).latent_dist.mean * LATENT_SCALE
        return latent[0].float()

    def decode(self, state: torch.Tensor) -> torch.Tensor:  # state [4, h, w] -> [3, 8h, 8w] in [0, 1]
        """``VAE.decode(z / 0.18215)``, mapped by ``x * 0.5 + 0.5`` and clamped to [0, 1]."""
        if state.dim() != 3 or state.shape[0] != 4:
            raise ValueError(f"sd15 decode expects a [4, h, w] latent, got {list(state.shape)}")
        with torch.no_grad():
            image = self.vae.decode(state.detach().to(self.device, self.dtype)[None] / LATENT_SCALE).sample[0]
        image = image.float()
        if not torch.isfinite(image).all():
            raise NumericalError("sd15 decode: the VAE produced non-finite values")
        return (image * 0.5 + 0.5).clamp(0.0, 1.0)

    # -- features

    def features(self, state: torch.Tensor, timestep: int) -> AttentionFeatures:  # state [4, h, w]
        """Q/K/V/O ([1, heads, tokens, dim], float32) of the selected layers for the clean latent at ``timestep``.

        Differentiable in ``state``; the U-Net forward stops right after the last selected layer.
        """
        if state.dim() != 3 or state.shape[0] != 4:
            raise ValueError(f"sd15 features expect a [4, h, w] latent, got {list(state.shape)}")
        if not 0 <= int(timestep) < SD15_TRAIN_TIMESTEPS:
            raise ValueError(f"timestep must be in [0, {SD15_TRAIN_TIMESTEPS}), got {timestep}")
        latent = state.to(self.device, self.dtype)[None]
        t = torch.tensor(int(timestep), device=self.device)
        with self._capture.running(stop_at=self._last_slot) as store, suppress(_StopForward):
            self.unet(latent, t, encoder_hidden_states=self.empty_prompt)
        return AttentionFeatures(
            *([store[(kind, slot)].float() for slot in range(len(self.layers))] for kind in ("q", "k", "v", "o"))
        )

    def reference_features(self, image: torch.Tensor, timestep: int) -> AttentionFeatures:  # image [3, H, W]
        """Features of a fixed style or content image without gradients, cached by content and timestep."""
        key = _image_key(image)
        cached = self._features.get((key, int(timestep)))
        if cached is not None:
            self._features.move_to_end((key, int(timestep)))
            return AttentionFeatures(*([t.float() for t in getattr(cached, n)] for n in ("q", "k", "v", "o")))
        latent = self._latents.get(key)
        if latent is None:
            latent = self.encode(image)
            _lru_put(self._latents, key, latent, LATENT_CACHE_SIZE)
        with torch.no_grad():
            result = self.features(latent, timestep)
        # Stored in the model dtype: the values came from it, so nothing is lost and GPU memory halves.
        stored = AttentionFeatures(*([t.to(self.dtype) for t in getattr(result, n)] for n in ("q", "k", "v", "o")))
        _lru_put(self._features, (key, int(timestep)), stored, self.feature_cache_size)
        return result

    def clear_cache(self) -> None:
        """Forget cached reference latents and features (frees memory; results do not depend on it)."""
        self._latents.clear()
        self._features.clear()
