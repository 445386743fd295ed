"""The weight-free ``patch`` proposal backend: state round trip, features, energy, stylization, extremes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from dresg_addon.errors import ConfigError
from dresg_addon.proposal import EnergyTerms, make_backend, optimize_proposal
from dresg_addon.proposal.base import ProposalBackend
from dresg_addon.proposal.patch import (
    OPPONENT,
    PatchBackend,
    PatchSettings,
    patch_feature_maps,
    patch_sliced_wasserstein,
    spectral_gain,
    symmetric_filter,
    timestep_scale,
)
from dresg_addon.schedule import alphas_cumprod, stage_timesteps

H, W = 48, 64


def content_image() -> torch.Tensor:  # [3, H, W]
    """A small synthetic 'photo': smooth greenish shading, a bright disc and a dark bar (clear edges)."""
    y, x = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    image = torch.stack([0.25 + 0.3 * x, 0.45 + 0.2 * y, 0.2 + 0.1 * x * y])
    disc = ((x - 0.35) ** 2 + (y - 0.45) ** 2 < 0.04).float()
    bar = ((x > 0.6) & (x < 0.75) & (y > 0.15)).float()
    image = image * (1 - disc) + disc * torch.tensor([0.9, 0.85, 0.6])[:, None, None]
    return image * (1 - bar) + bar * torch.tensor([0.08, 0.1, 0.12])[:, None, None]


def style_image() -> torch.Tensor:  # [3, H, W]
    """A 'painting': blue and yellow diagonal strokes, a palette far from the content's."""
    y, x = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    stripes = (torch.sin((x + 0.7 * y) * 0.9) > 0).float()
    blue = torch.tensor([0.1, 0.2, 0.7])[:, None, None]
    yellow = torch.tensor([0.95, 0.85, 0.2])[:, None, None]
    return blue * (1 - stripes) + yellow * stripes


def ssim(a: torch.Tensor, b: torch.Tensor) -> float:  # [3, H, W] each
    """Mean SSIM over 7x7 uniform windows of the luminance (Wang et al. 2004 constants)."""
    weights = torch.tensor([0.299, 0.587, 0.114])[:, None, None]
    a, b = (a * weights).sum(0)[None, None], (b * weights).sum(0)[None, None]
    mu_a, mu_b = F.avg_pool2d(a, 7, 1), F.avg_pool2d(b, 7, 1)
    var_a = F.avg_pool2d(a * a, 7, 1) - mu_a**2
    var_b = F.avg_pool2d(b * b, 7, 1) - mu_b**2
    cov = F.avg_pool2d(a * b, 7, 1) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return float(value.mean())


def run_stages(backend: PatchBackend, content, style, stages: int = 20):
    """The proposal side of Algorithm 1: re-encode the last proposal each stage, 10 updates, decode."""
    proposal, energies = content, []
    for stage in stage_timesteps(num_stages=stages):
        state, stage_energies = optimize_proposal(
            backend, backend.encode(proposal), stage.timesteps, style, content, EnergyTerms()
        )
        proposal = backend.decode(state).detach()
        energies.append(stage_energies)
    return proposal, energies


def test_make_backend_builds_patch_with_overrides():
    backend = make_backend("patch", seed=3, heads=2)
    assert isinstance(backend, PatchBackend) and backend.name == "patch"
    assert backend.settings.seed == 3 and backend.settings.heads == 2


@pytest.mark.parametrize(
    "overrides",
    [
        {"colour": 1},
        {"token_strides": (3,)},
        {"token_strides": ()},
        {"temperature": 0.0},
        {"heads": 0},
        {"luma_floor": 0.0},
        {"chroma_floor": 1.5},
        {"swd_weight": -1.0},
        {"swd_max_patches": 0},
    ],
)
def test_bad_settings_raise_config_error(overrides):
    with pytest.raises(ConfigError):
        PatchBackend(**overrides)


def test_symmetric_filter_is_inverted_by_the_reciprocal_gain_and_keeps_flat_images():
    x = torch.rand(3, 13, 17, generator=torch.Generator().manual_seed(0))
    gain = spectral_gain(13, 17, cutoff=0.06, floor=0.2)
    assert float(gain.max()) == pytest.approx(1.0) and float(gain.min()) > 0.2
    assert torch.allclose(symmetric_filter(symmetric_filter(x, gain), 1.0 / gain), x, atol=1e-5)
    flat = torch.full((3, 13, 17), 0.3)
    assert torch.allclose(symmetric_filter(flat, gain), flat, atol=1e-6)
    # Low-pass: a checkerboard (the finest frequency) is damped towards the floor.
    checker = ((torch.arange(13)[:, None] + torch.arange(17)[None, :]) % 2).float()[None] - 0.5
    assert float(symmetric_filter(checker, gain).abs().max()) < 0.5 * 0.5


def test_encode_decode_round_trip_and_range():
    backend = PatchBackend()
    image = content_image()
    state = backend.encode(image)
    assert state.shape == image.shape and state.dtype == torch.float32 and not state.requires_grad
    assert float((backend.decode(state) - image).abs().max()) < 1e-4
    # Extreme states decode to finite images in [0, 1]; black and white survive the round trip.
    wild = torch.randn(3, H, W, generator=torch.Generator().manual_seed(1)) * 1e4
    decoded = backend.decode(wild)
    assert torch.isfinite(decoded).all() and float(decoded.min()) >= 0.0 and float(decoded.max()) <= 1.0
    for value in (0.0, 1.0):
        flat = torch.full((3, H, W), value)
        assert float((backend.decode(backend.encode(flat)) - flat).abs().max()) < 2e-4


def test_one_update_is_smooth_not_salt_and_pepper():
    """A +-lr sign step on the state is damped at fine scales, chroma (colour noise) much more than luminance."""
    backend = PatchBackend()
    state = backend.encode(torch.full((3, H, W), 0.5))
    signs = torch.sign(torch.randn(3, H, W, generator=torch.Generator().manual_seed(2)))
    logits = torch.logit(backend.decode(state + backend.learning_rate * signs).double())
    opponent = torch.einsum("oc,chw->ohw", OPPONENT.double(), logits)  # per channel: G(step_gain * lr * signs)
    raw_step = backend.settings.step_gain * backend.learning_rate  # the step without G
    rms = opponent.pow(2).mean((1, 2)).sqrt()
    assert float(rms[0]) < 0.6 * raw_step  # luminance: fine detail passes at about the floor
    assert float(rms[1:].max()) < 0.25 * raw_step  # chroma: heavily smoothed
    # A flat step (all +1) passes unchanged: coarse colour changes are not slowed down.
    flat = torch.logit(backend.decode(state + backend.learning_rate).double())
    assert torch.allclose(
        torch.einsum("oc,chw->ohw", OPPONENT.double(), flat), torch.tensor(raw_step).double(), atol=1e-4
    )


def test_features_shapes_and_gradients():
    backend = PatchBackend(heads=3, head_dim=8)
    state = backend.encode(content_image()).requires_grad_(True)
    feats = backend.features(state, 500)
    dy, dx = backend._grid_offset(500)
    assert 0 <= dy < 16 and 0 <= dx < 16
    assert len(feats.q) == len(feats.k) == len(feats.v) == len(feats.o) == 2
    for layer, stride in enumerate((16, 8)):
        tokens = ((H + dy) // stride) * ((W + dx) // stride)
        assert feats.q[layer].shape == (1, 3, tokens, 9)  # head_dim + the distance coordinate
        assert feats.k[layer].shape == (1, 3, tokens, 9)
        assert feats.v[layer].shape == (1, 3, tokens, 3 * 8 * 8)  # the token's 8x8 block of pixels
        assert feats.o[layer].shape == (1, 3, tokens, 3 * 8 * 8)
    sum(o.sum() for o in feats.o).backward()
    assert torch.isfinite(state.grad).all() and float(state.grad.abs().sum()) > 0


def test_attention_is_a_soft_nearest_patch_lookup():
    """Eq. 7 on the render itself returns (nearly) its own values: each token's nearest patch is itself."""
    backend = PatchBackend(temperature=0.05)
    feats = backend.features(backend.encode(content_image()), 500)
    for v, o in zip(feats.v, feats.o):
        assert float((o - v).abs().mean()) < 0.1 * float(v.abs().mean())


def test_reference_features_match_features_and_are_cached_per_grid():
    backend = PatchBackend()
    image = style_image()
    first = backend.reference_features(image, 951)
    direct = backend.features(backend.encode(image), 951)
    assert all(torch.allclose(x, y, atol=1e-3) for x, y in zip(first.q + first.v, direct.q + direct.v))
    assert backend.reference_features(image.clone(), 951) is first  # cached by content, not identity
    assert not torch.equal(backend.reference_features(image * 0.5, 951).v[0], first.v[0])
    # Another timestep shifts the token grid (seams move), so its features are recomputed.
    assert backend._grid_offset(951) != backend._grid_offset(946)
    assert backend.reference_features(image, 946) is not first


def test_timestep_scale_is_coarse_to_fine():
    abar = torch.from_numpy(alphas_cumprod()).float()
    scales = [timestep_scale(s.state, abar) for s in stage_timesteps()]
    assert scales[0] == 4 and scales[-1] == 1 and sorted(scales, reverse=True) == scales
    assert set(scales) == {1, 2, 4}


def test_sliced_wasserstein_is_zero_on_identical_images_and_positive_otherwise():
    directions = torch.randn(16, 3, 5, 5, generator=torch.Generator().manual_seed(0))
    directions = directions / directions.flatten(1).norm(dim=1)[:, None, None, None]
    content, style = content_image()[None], style_image()[None]
    assert float(patch_sliced_wasserstein(content, content, directions, max_patches=10**6)) == 0.0
    assert float(patch_sliced_wasserstein(content, style, directions, max_patches=10**6)) > 1e-3
    # Subsampled and of a different size: still finite, still positive.
    small = F.interpolate(style, scale_factor=0.5, mode="area")
    value = patch_sliced_wasserstein(content, small, directions, max_patches=100, offset=(3, 1))
    assert math.isfinite(float(value)) and float(value) > 0


def test_energy_decreases_over_updates():
    """Repeating one timestep keeps the SW directions fixed: the summed energy must go down."""
    backend = PatchBackend()
    content, style = content_image(), style_image()
    _, energies = optimize_proposal(backend, backend.encode(content), [500] * 15, style, content, EnergyTerms())
    assert energies[-1] < 0.8 * energies[0]
    assert all(math.isfinite(e) for e in energies)


def test_attention_energy_alone_decreases():
    backend = PatchBackend(swd_weight=0.0)
    content, style = content_image(), style_image()
    assert backend.extra_energy(backend.encode(content), style, 500) is None
    _, energies = optimize_proposal(backend, backend.encode(content), [500] * 15, style, content, EnergyTerms())
    assert energies[-1] < 0.9 * energies[0]


def test_base_backend_has_no_extra_energy():
    """The hook is a no-op for other backends (the SD1.5 path is unchanged)."""
    assert ProposalBackend.extra_energy(PatchBackend(), torch.zeros(3, H, W), style_image(), 500) is None


def test_proposal_moves_colours_to_the_style_and_keeps_structure():
    backend = PatchBackend()
    content, style = content_image(), style_image()
    proposal, energies = run_stages(backend, content, style, stages=8)
    assert torch.isfinite(proposal).all() and float(proposal.min()) >= 0 and float(proposal.max()) <= 1
    style_mean = style.mean((1, 2))
    before = float((content.mean((1, 2)) - style_mean).norm())
    after = float((proposal.mean((1, 2)) - style_mean).norm())
    assert after < 0.6 * before
    # The per-channel spread moves towards the style's too (blue/yellow strokes are high-contrast).
    spread_before = float((content.std((1, 2)) - style.std((1, 2))).abs().sum())
    spread_after = float((proposal.std((1, 2)) - style.std((1, 2))).abs().sum())
    assert spread_after < spread_before
    # Structure stays: the added strokes lower SSIM on this flat synthetic image, but far less than a
    # replacement by the style (SSIM ~0) would.
    assert ssim(proposal, content) > 0.25
    assert ssim(proposal, content) > ssim(style, content) + 0.2


def test_deterministic_for_a_seed():
    content, style = content_image(), style_image()
    a, _ = run_stages(PatchBackend(seed=7), content, style, stages=2)
    b, _ = run_stages(PatchBackend(seed=7), content, style, stages=2)
    c, _ = run_stages(PatchBackend(seed=8), content, style, stages=2)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


@pytest.mark.parametrize(("render_value", "style_value"), [(0.0, 0.5), (1.0, 0.5), (0.0, 1.0), (1.0, 0.0), (0.5, 0.5)])
def test_extreme_inputs_stay_finite(render_value, style_value):
    backend = PatchBackend()
    render = torch.full((3, H, W), render_value)
    style = torch.full((3, H, W), style_value)
    state, energies = optimize_proposal(backend, backend.encode(render), [951, 501, 1], style, render, EnergyTerms())
    proposal = backend.decode(state)
    assert all(math.isfinite(e) for e in energies)
    assert torch.isfinite(proposal).all() and float(proposal.min()) >= 0 and float(proposal.max()) <= 1


def test_tiny_and_odd_sized_images_work():
    backend = PatchBackend()
    for h, w in ((5, 7), (17, 9)):
        image = torch.rand(3, h, w, generator=torch.Generator().manual_seed(h))
        state, energies = optimize_proposal(
            backend, backend.encode(image), [951, 1], image.flip(-1), image, EnergyTerms()
        )
        assert state.shape == (3, h, w) and all(math.isfinite(e) for e in energies)


def test_bad_image_shapes_raise():
    backend = PatchBackend()
    with pytest.raises(ValueError, match=r"\[3, H, W\]"):
        backend.encode(torch.zeros(1, 3, 8, 8))
    with pytest.raises(ValueError, match=r"\[B, 3, H, W\]"):
        patch_feature_maps(torch.zeros(3, 8, 8))


def test_patch_feature_maps_describe_structure_not_palette():
    image = content_image()[None] * 0.8
    feats = patch_feature_maps(image)
    assert feats.shape == (1, 96, H // 8, W // 8)
    shifted = patch_feature_maps(image + torch.tensor([0.1, -0.05, 0.15])[None, :, None, None])
    assert torch.allclose(feats, shifted, atol=1e-4)  # a colour offset leaves structure unchanged
    assert float((patch_feature_maps(image.flip(-1)) - feats).abs().mean()) > 0.1
    batch = torch.cat([image, style_image()[None]]).requires_grad_(True)
    out = patch_feature_maps(batch)
    assert out.shape[0] == 2 and torch.allclose(out[:1], feats, atol=1e-6)
    out.abs().sum().backward()
    assert torch.isfinite(batch.grad).all() and float(batch.grad.abs().sum()) > 0


def test_settings_defaults_are_the_documented_ones():
    s = PatchSettings()
    assert s.token_strides == (16, 8) and s.swd_patch == 7
    assert PatchBackend().learning_rate == 0.05  # the paper's latent lr, fresh Adam per update


def test_real_photo_and_painting_stylize(shared_data):
    oiio = pytest.importorskip("OpenImageIO")

    def read(path, width=112, height=80):
        pixels = oiio.ImageBuf(str(path)).get_pixels(oiio.FLOAT)[..., :3]
        image = torch.from_numpy(np.ascontiguousarray(pixels)).permute(2, 0, 1)[None]
        return F.interpolate(image, size=(height, width), mode="area")[0].clamp(0, 1)

    content = read(shared_data("llff_fern/images_8/image000.png"))
    style = read(shared_data("styles/starry_night.jpg"))
    proposal, _ = run_stages(PatchBackend(), content, style, stages=6)
    style_mean = style.mean((1, 2))
    assert float((proposal.mean((1, 2)) - style_mean).norm()) < 0.7 * float((content.mean((1, 2)) - style_mean).norm())
    assert ssim(proposal, content) > 0.4
