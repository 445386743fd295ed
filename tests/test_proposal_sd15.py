"""The sd15 proposal backend on tiny random models with SD1.5's block layout, loaded through the real code.

The real SD1.5 architecture is checked on the meta device (no weights allocated).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from messages import names

pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from diffusers import AutoencoderKL, UNet2DConditionModel  # noqa: E402
from safetensors.torch import load_file, save_file  # noqa: E402
from transformers import CLIPTextConfig, CLIPTextModel  # noqa: E402

from dresg_addon.method.backends import BACKENDS  # noqa: E402
from dresg_addon.method.config import StylizeConfig  # noqa: E402
from dresg_addon.method.proposal import EnergyTerms, attention_energy, optimize_proposal  # noqa: E402
from dresg_addon.method.proposal.sd15 import (  # noqa: E402
    DEFAULT_LAYERS,
    SD15Backend,
    _Capture,
    self_attention_names,
)
from dresg_addon.method.proposal.sd15_configs import (  # noqa: E402
    SD15_TEXT_ENCODER_CONFIG,
    SD15_UNET_CONFIG,
    SD15_VAE_CONFIG,
    SD15Configs,
)
from dresg_addon.util.errors import ConfigError, ModelError  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

TINY_UNET = {
    **SD15_UNET_CONFIG,
    "block_out_channels": [8, 16, 32, 32],
    "norm_num_groups": 8,
    "attention_head_dim": 2,
    "cross_attention_dim": 16,
    "sample_size": 8,
}
TINY_VAE = {**SD15_VAE_CONFIG, "block_out_channels": [8, 16, 16, 16], "norm_num_groups": 8, "layers_per_block": 1}
TINY_TEXT = {
    **SD15_TEXT_ENCODER_CONFIG,
    "hidden_size": 16,
    "intermediate_size": 32,
    "num_hidden_layers": 2,
    "num_attention_heads": 2,
    "projection_dim": 16,
}
TINY_CONFIGS = SD15Configs(unet=TINY_UNET, vae=TINY_VAE, text_encoder=TINY_TEXT)
UP_LAYERS = [f"up_blocks.{b}.attentions.{a}.transformer_blocks.0.attn1" for b in (2, 3) for a in range(3)]


def _tiny_models():
    torch.manual_seed(0)
    unet = UNet2DConditionModel.from_config(TINY_UNET)
    vae = AutoencoderKL.from_config(TINY_VAE)
    text_encoder = CLIPTextModel(CLIPTextConfig(**TINY_TEXT))
    return {"unet": unet.eval(), "vae": vae.eval(), "text_encoder": text_encoder.eval()}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny models and the diffusers folder they were saved to."""
    models = _tiny_models()
    folder = tmp_path_factory.mktemp("sd15") / "tiny-sd15"
    for name, model in models.items():
        model.save_pretrained(folder / name)
    return models, folder


@pytest.fixture(scope="module")
def backend(tiny):
    return SD15Backend(tiny[1], device="cpu", dtype=torch.float32)


def _image(height=64, width=128, seed=1):
    gen = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, height // 16, width // 16, generator=gen)
    return torch.nn.functional.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)[0]


# --- layer order -----------------------------------------------------------------------------------


def _execution_order(unet, latent, context):
    order, handles = [], []
    for name, module in unet.named_modules():
        if name.endswith("attn1"):
            handles.append(module.register_forward_pre_hook(lambda m, a, n=name: order.append(n)))
    try:
        unet(latent, torch.tensor(500, device=latent.device), encoder_hidden_states=context)
    finally:
        for handle in handles:
            handle.remove()
    return order


def test_tiny_unet_has_16_self_attention_layers_in_execution_order(backend):
    names = self_attention_names(backend.unet)
    run = _execution_order(backend.unet, torch.randn(1, 4, 8, 16), backend.empty_prompt)
    assert names == run
    assert len(names) == 16
    assert names[6].startswith("mid_block.")
    assert [names[i] for i in DEFAULT_LAYERS] == UP_LAYERS
    assert backend.layer_names == UP_LAYERS
    # The trap: module registration order puts the mid block last.
    registered = [name for name, _ in backend.unet.named_modules() if name.endswith("attn1")]
    assert registered[-1].startswith("mid_block.") and registered[10:16] != UP_LAYERS


def test_real_sd15_architecture_on_meta_device():
    with torch.device("meta"):
        unet = UNet2DConditionModel.from_config(SD15_UNET_CONFIG)
        vae = AutoencoderKL.from_config(SD15_VAE_CONFIG)
        text_encoder = CLIPTextModel(CLIPTextConfig(**SD15_TEXT_ENCODER_CONFIG))
    assert sum(p.numel() for p in unet.parameters()) == 859_520_964
    assert sum(p.numel() for p in vae.parameters()) == 83_653_863
    assert sum(p.numel() for p in text_encoder.parameters()) == 123_060_480

    latent = torch.empty(1, 4, 40, 56, device="meta")  # 448x320 proposals
    context = torch.empty(1, 77, 768, device="meta")
    names = self_attention_names(unet)
    assert names == _execution_order(unet, latent, context)
    assert len(names) == 16 and [names[i] for i in DEFAULT_LAYERS] == UP_LAYERS

    capture = _Capture(unet, UP_LAYERS)
    with capture.running(stop_at=None) as store:
        unet(latent, torch.tensor(500, device="meta"), encoder_hidden_states=context)
    for slot in range(6):
        tokens, dim = (560, 80) if slot < 3 else (2240, 40)
        for kind in "qkvo":
            assert tuple(store[(kind, slot)].shape) == (1, 8, tokens, dim)


# --- features --------------------------------------------------------------------------------------


def test_features_shapes_and_output_is_attention_of_qkv(backend):
    state = backend.encode(_image())
    assert state.shape == (4, 8, 16) and state.dtype == torch.float32
    feats = backend.features(state, 500)
    assert all(len(getattr(feats, kind)) == 6 for kind in "qkvo")
    for slot in range(6):
        tokens, dim = (32, 8) if slot < 3 else (128, 4)  # up_blocks.2: 16 channels, up_blocks.3: 8; 2 heads
        for kind in "qkvo":
            assert getattr(feats, kind)[slot].shape == (1, 2, tokens, dim)
        recomputed = torch.nn.functional.scaled_dot_product_attention(feats.q[slot], feats.k[slot], feats.v[slot])
        torch.testing.assert_close(feats.o[slot], recomputed, rtol=1e-5, atol=1e-6)


def test_forward_stops_after_last_layer_and_matches_a_full_forward(backend):
    state = backend.encode(_image(seed=2))
    calls = []
    handle = backend.unet.conv_out.register_forward_hook(lambda *args: calls.append(1))
    try:
        feats = backend.features(state, 300)
        assert calls == []  # stopped before the output convolution
        full = {}
        hooks = [
            backend.unet.get_submodule(name).to_q.register_forward_hook(
                lambda m, a, out, n=name: full.__setitem__(n, out)
            )
            for name in backend.layer_names
        ]
        backend.unet(state[None], torch.tensor(300), encoder_hidden_states=backend.empty_prompt)
        for hook in hooks:
            hook.remove()
        assert calls == [1]
    finally:
        handle.remove()
    for slot, name in enumerate(backend.layer_names):
        torch.testing.assert_close(feats.q[slot], full[name].unflatten(-1, (2, -1)).transpose(1, 2))


def test_gradients_reach_the_latent(backend):
    style = backend.reference_features(_image(seed=3), 700)
    state = backend.encode(_image(seed=4)).requires_grad_(True)
    energy = attention_energy(backend.features(state, 700), style, None, EnergyTerms())
    energy.backward()
    assert torch.isfinite(state.grad).all() and state.grad.abs().sum() > 0


def test_optimize_proposal_lowers_the_energy_and_moves_the_latent(backend):
    style_image, content_image, render = _image(seed=5), _image(seed=6), _image(seed=7)
    start = backend.encode(render)
    terms = EnergyTerms(content_weight=0.15)
    timesteps = list(range(951, 901, -5))  # one stage of the paper's DDIM schedule
    updated, energies = optimize_proposal(backend, start, timesteps, style_image, content_image, terms)
    assert len(energies) == 10 and all(torch.isfinite(torch.tensor(energies)))
    assert energies[-1] < energies[0]
    style = backend.reference_features(style_image, timesteps[-1])
    content = backend.reference_features(content_image, timesteps[-1])
    with torch.no_grad():
        before = attention_energy(backend.features(start, timesteps[-1]), style, content, terms)
        after = attention_energy(backend.features(updated, timesteps[-1]), style, content, terms)
    assert after < before
    step = (updated - start).abs()
    assert step.max() > 0.05 and step.max() <= 10 * 0.05 * 1.01  # fresh Adam: ~lr per step and element


def test_reference_features_are_cached_by_content_and_timestep(backend):
    unet_calls, vae_calls = [], []
    hooks = [
        backend.unet.conv_in.register_forward_pre_hook(lambda *args: unet_calls.append(1)),
        backend.vae.encoder.register_forward_pre_hook(lambda *args: vae_calls.append(1)),
    ]
    try:
        backend.clear_cache()
        image = _image(seed=7)
        first = backend.reference_features(image, 451)
        again = backend.reference_features(image.clone(), 451)  # same pixels, another tensor
        assert (len(unet_calls), len(vae_calls)) == (1, 1)
        for kind in "qkvo":
            for a, b in zip(getattr(first, kind), getattr(again, kind)):
                assert torch.equal(a, b) and not b.requires_grad
        backend.reference_features(image, 401)  # new timestep: a U-Net pass, the latent is reused
        assert (len(unet_calls), len(vae_calls)) == (2, 1)
        backend.reference_features(_image(seed=8), 451)  # other pixels
        assert (len(unet_calls), len(vae_calls)) == (3, 2)
    finally:
        for hook in hooks:
            hook.remove()


def test_decode_is_an_image_in_unit_range(backend):
    image = backend.decode(backend.encode(_image(seed=9)))
    assert image.shape == (3, 64, 128) and torch.isfinite(image).all()
    assert image.min() >= 0 and image.max() <= 1
    extreme = backend.decode(torch.full((4, 8, 16), 50.0))
    assert torch.isfinite(extreme).all() and extreme.min() >= 0 and extreme.max() <= 1


def test_bad_shapes_and_timesteps_are_refused(backend):
    with pytest.raises(ValueError, match=r"\[3, 60, 128\]"):
        backend.encode(torch.rand(3, 60, 128))
    with pytest.raises(ValueError, match="latent"):
        backend.features(torch.zeros(3, 8, 16), 10)
    with pytest.raises(ValueError, match="timestep"):
        backend.features(torch.zeros(4, 8, 16), 1000)


# --- loading ---------------------------------------------------------------------------------------


def test_a_run_builds_sd15_from_a_folder_with_its_settings_in_the_constructor(tiny):
    models, folder = tiny
    config = StylizeConfig().with_(proposal="sd15", model_path=str(folder), scene_weight=0.8)
    built = BACKENDS["sd15"].make(config, config.plan().with_(use_style_values=False), device="cpu")
    assert built.name == "sd15" and built.dtype == torch.float32 and built.device == torch.device("cpu")
    assert built.learning_rate == 0.05  # the paper's latent lr
    assert built.terms == EnergyTerms(0.3 * 0.8, use_content_query=True, use_style_keys=True, use_style_values=False)
    ids = torch.tensor([[49406] + [49407] * 76])
    with torch.no_grad():
        expected = models["text_encoder"](input_ids=ids).last_hidden_state
    torch.testing.assert_close(built.empty_prompt, expected)


def _resnet_to_ldm(rest: str) -> str:
    for new, old in [
        ("norm1", "in_layers.0"),
        ("conv1", "in_layers.2"),
        ("norm2", "out_layers.0"),
        ("conv2", "out_layers.3"),
        ("time_emb_proj", "emb_layers.1"),
        ("conv_shortcut", "skip_connection"),
    ]:
        rest = rest.replace(new, old)
    return rest


def _unet_key_to_ldm(key: str) -> str:
    """diffusers U-Net key -> original SD key (SD1.x block layout, 2 layers per block)."""
    fixed = {
        "time_embedding.linear_1": "time_embed.0",
        "time_embedding.linear_2": "time_embed.2",
        "conv_in": "input_blocks.0.0",
        "conv_norm_out": "out.0",
        "conv_out": "out.2",
    }
    module, _, leaf = key.rpartition(".")
    if module in fixed:
        return f"{fixed[module]}.{leaf}"
    rules = [
        (
            r"down_blocks\.(\d)\.resnets\.(\d)\.(.*)",
            lambda i, j, r: f"input_blocks.{3 * i + j + 1}.0.{_resnet_to_ldm(r)}",
        ),
        (r"down_blocks\.(\d)\.attentions\.(\d)\.(.*)", lambda i, j, r: f"input_blocks.{3 * i + j + 1}.1.{r}"),
        (r"down_blocks\.(\d)\.downsamplers\.0\.conv\.(.*)", lambda i, r: f"input_blocks.{3 * (i + 1)}.0.op.{r}"),
        (r"up_blocks\.(\d)\.resnets\.(\d)\.(.*)", lambda i, j, r: f"output_blocks.{3 * i + j}.0.{_resnet_to_ldm(r)}"),
        (r"up_blocks\.(\d)\.attentions\.(\d)\.(.*)", lambda i, j, r: f"output_blocks.{3 * i + j}.1.{r}"),
        (r"up_blocks\.(\d)\.upsamplers\.0\.(.*)", lambda i, r: f"output_blocks.{3 * i + 2}.{1 if i == 0 else 2}.{r}"),
        (r"mid_block\.attentions\.0\.(.*)", lambda r: f"middle_block.1.{r}"),
        (r"mid_block\.resnets\.(\d)\.(.*)", lambda j, r: f"middle_block.{2 * j}.{_resnet_to_ldm(r)}"),
    ]
    for pattern, build in rules:
        match = re.fullmatch(pattern, key)
        if match:
            return build(*(int(g) if g.isdigit() else g for g in match.groups()))
    raise KeyError(key)


def _vae_key_to_ldm(key: str, value: torch.Tensor) -> tuple[str, torch.Tensor]:
    """diffusers VAE key -> original SD key; attention projections become 1x1 convolutions."""
    key = key.replace("conv_norm_out", "norm_out").replace("conv_shortcut", "nin_shortcut")
    key = re.sub(r"encoder\.down_blocks\.(\d)\.resnets\.", r"encoder.down.\1.block.", key)
    key = re.sub(r"encoder\.down_blocks\.(\d)\.downsamplers\.0\.", r"encoder.down.\1.downsample.", key)
    key = re.sub(r"decoder\.up_blocks\.(\d)\.resnets\.", lambda m: f"decoder.up.{3 - int(m[1])}.block.", key)
    key = re.sub(r"decoder\.up_blocks\.(\d)\.upsamplers\.0\.", lambda m: f"decoder.up.{3 - int(m[1])}.upsample.", key)
    key = re.sub(r"mid_block\.resnets\.(\d)\.", lambda m: f"mid.block_{int(m[1]) + 1}.", key)
    if "mid_block.attentions.0." in key:
        key = key.replace("mid_block.attentions.0.", "mid.attn_1.")
        for new, old in [("group_norm", "norm"), ("to_q", "q"), ("to_k", "k"), ("to_v", "v"), ("to_out.0", "proj_out")]:
            key = key.replace(f".{new}.", f".{old}.")
        if value.dim() == 2:
            value = value[:, :, None, None]
    return key, value


def _original_checkpoint(models) -> dict:
    state = {f"model.diffusion_model.{_unet_key_to_ldm(k)}": v for k, v in models["unet"].state_dict().items()}
    for key, value in models["vae"].state_dict().items():
        key, value = _vae_key_to_ldm(key, value)
        state[f"first_stage_model.{key}"] = value
    for key, value in models["text_encoder"].state_dict().items():
        state[f"cond_stage_model.transformer.text_model.{key.removeprefix('text_model.')}"] = value
    return {key: value.contiguous().clone() for key, value in state.items()}


def test_single_safetensors_checkpoint_loads_with_local_configs(tiny, backend, tmp_path):
    models, _ = tiny
    path = tmp_path / "tiny-sd15.safetensors"
    save_file(_original_checkpoint(models), str(path))
    loaded = SD15Backend(path, device="cpu", configs=TINY_CONFIGS)
    for name in ("unet", "vae"):
        original = getattr(backend, name).state_dict()
        converted = getattr(loaded, name).state_dict()
        assert converted.keys() == original.keys()
        assert all(torch.equal(converted[key], original[key]) for key in original)
    torch.testing.assert_close(loaded.empty_prompt, backend.empty_prompt)
    # With the real SD1.5 configs the tiny weights must be refused, not silently padded.
    names(_refused(path), "tiny-sd15.safetensors", "shape")


def _refused(path) -> str:
    with pytest.raises(ModelError) as error:
        SD15Backend(path, device="cpu")
    return str(error.value)


def test_missing_paths_and_wrong_files_raise_model_error(tiny, tmp_path):
    models, folder = tiny
    names(_refused(tmp_path / "nowhere"), "nowhere")
    _refused("")
    text = tmp_path / "model.txt"
    text.write_text("not weights")
    names(_refused(text), "model.txt")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x00\x01garbage" * 10)
    names(_refused(junk), "junk.safetensors")
    foreign = tmp_path / "foreign.safetensors"
    save_file({"weight": torch.zeros(2)}, str(foreign))
    names(_refused(foreign), "foreign.safetensors", "model.diffusion_model.")  # the weights it looked for
    vae_only = tmp_path / "vae-only"
    models["vae"].save_pretrained(vae_only / "vae")
    names(_refused(vae_only), "vae-only", "unet/config.json")  # the folder and the file it lacks


def test_damaged_folder_weights_raise_model_error(tiny, tmp_path):
    models, _ = tiny
    for name, model in models.items():
        model.save_pretrained(tmp_path / "sd" / name)
    weights = tmp_path / "sd" / "unet" / "diffusion_pytorch_model.safetensors"
    state = load_file(str(weights))
    dropped = sorted(state)[0]
    del state[dropped]
    save_file(state, str(weights))
    names(_refused(tmp_path / "sd"), "unet", "1 missing", dropped)  # the model, how many, an example
    weights.write_bytes(b"truncated")
    names(_refused(tmp_path / "sd"), "unet")
    weights.unlink()
    names(_refused(tmp_path / "sd"), "unet")


def test_layer_and_device_settings_are_checked(tiny):
    _, folder = tiny
    with pytest.raises(ConfigError, match="at least one"):
        SD15Backend(folder, device="cpu", layers=())
    with pytest.raises(ConfigError, match="distinct"):
        SD15Backend(folder, device="cpu", layers=(10, 10))
    with pytest.raises(ModelError, match="16"):  # SD1.5 has 16 self-attention layers: 0 to 15
        SD15Backend(folder, device="cpu", layers=(3, 16))
    with pytest.raises(ConfigError, match="feature_cache_size"):
        SD15Backend(folder, device="cpu", feature_cache_size=-1)
    with pytest.raises(ConfigError, match="dtype"):
        SD15Backend(folder, device="cpu", dtype="int8")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA"):
            SD15Backend(folder, device="cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_a_proposal_on_cuda_starts_where_the_cpu_s_does_and_lowers_the_energy_in_half_precision_too(tiny, backend):
    # Compared before any Adam step: Adam's first steps are about lr x sign(g), so GPU rounding flips the small
    # gradients' steps and the two runs part ways by design; what must agree is the features and the decode.
    style_image, content_image, render = _image(seed=5), _image(seed=6), _image(seed=7)
    terms = EnergyTerms(content_weight=0.15)
    timesteps = list(range(951, 921, -5))
    gpu = SD15Backend(tiny[1], device="cuda", dtype=torch.float32)
    for chosen in (backend, gpu):
        chosen.clear_cache()
    starts = [chosen.encode(render) for chosen in (backend, gpu)]
    torch.testing.assert_close(starts[1].cpu(), starts[0].cpu(), atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(gpu.decode(starts[1]).cpu(), backend.decode(starts[0]).cpu(), atol=1e-3, rtol=1e-3)
    energies = [
        optimize_proposal(c, s, timesteps, style_image, content_image, terms)[1] for c, s in zip((backend, gpu), starts)
    ]
    assert energies[1][0] == pytest.approx(energies[0][0], rel=1e-3)
    assert energies[1][-1] < energies[1][0]
    half = SD15Backend(tiny[1], device="cuda", dtype=torch.float16)
    latent, steps = optimize_proposal(half, half.encode(render), timesteps, style_image, content_image, terms)
    image = half.decode(latent)
    assert all(torch.isfinite(torch.tensor(steps))) and steps[-1] < steps[0] and torch.isfinite(image).all()
    assert image.shape == (3, 64, 128) and float(image.min()) >= 0 and float(image.max()) <= 1


def test_importing_the_proposal_package_does_not_import_diffusers():
    code = (
        "import sys, dresg_addon.method.proposal, dresg_addon.method.proposal.sd15; "
        "heavy = [m for m in ('diffusers', 'transformers', 'bpy') if m in sys.modules]; "
        "assert not heavy, heavy"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
