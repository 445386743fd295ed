"""Evaluation metrics on known cases, extreme inputs, and the CLIP / DINO loading path with tiny random models."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from messages import names

from dresg_addon.evaluation import metrics
from dresg_addon.method.style_distance import sort_rows
from dresg_addon.raster import render_scene
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.demo import demo_cameras, demo_scene
from dresg_addon.util.errors import ConfigError, ModelError

F64 = torch.float64


def smooth_image(h=32, w=40, seed=0, dtype=torch.float32) -> torch.Tensor:  # [3, H, W] with edges and texture
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(1, 3, h // 4, w // 4, generator=g, dtype=F64)
    image = torch.nn.functional.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)[0]
    image = image + 0.1 * torch.rand(3, h, w, generator=g, dtype=F64)
    return image.clamp(0, 1).to(dtype)


# ----------------------------------------------------------------------------------------------------
# Sliced Wasserstein


def test_sliced_wasserstein_1d_shift_is_exact():
    x = torch.linspace(0, 1, 101, dtype=F64)[:, None]
    assert float(metrics.sliced_wasserstein(x, x + 0.3)) == pytest.approx(0.3, abs=1e-12)


def test_sliced_wasserstein_unequal_counts_matches_quantiles():
    # The same uniform distribution sampled at 100 and 1000 points: quantile matching makes it ~0.
    x = ((torch.arange(100, dtype=F64) + 0.5) / 100)[:, None]
    y = ((torch.arange(1000, dtype=F64) + 0.5) / 1000)[:, None]
    assert float(metrics.sliced_wasserstein(x, y)) < 2e-3
    assert float(metrics.sliced_wasserstein(x, y + 0.2)) == pytest.approx(0.2, abs=2e-3)


@pytest.mark.parametrize("dtype", [torch.float32, F64, torch.bfloat16])
def test_rows_sorted_as_torch_sorts_them_infinities_and_nan_included(dtype):
    values = torch.randn(5, 301, generator=torch.Generator().manual_seed(0), dtype=dtype)
    values[0, :3] = torch.tensor([math.inf, -math.inf, math.nan], dtype=dtype)
    values[1] = 0.25  # all ties
    expected = torch.sort(values, dim=1).values
    assert torch.equal(sort_rows(values).nan_to_num(7.0), expected.nan_to_num(7.0))
    assert sort_rows(values).dtype == dtype


def test_sliced_wasserstein_rejects_bad_shapes():
    with pytest.raises(ValueError, match="samples"):
        metrics.sliced_wasserstein(torch.zeros(5, 3), torch.zeros(5, 2))
    with pytest.raises(ValueError, match="n_projections"):
        metrics.sliced_wasserstein(torch.zeros(5, 3), torch.zeros(5, 3), n_projections=0)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_sw_colors_identical_zero_and_shift_grows(dtype):
    style = smooth_image(dtype=dtype)
    shifted = [(style + d).clamp(0, 1) for d in (0.0, 0.1, 0.3)]
    values = metrics.sliced_wasserstein_colors(torch.stack(shifted), style)
    assert values.dtype == dtype and values.shape == (3,)
    assert float(values[0]) == 0.0
    assert 0.0 < float(values[1]) < float(values[2])
    # A permutation of the pixels has the same colour distribution.
    permuted = style.reshape(3, -1)[:, torch.randperm(style[0].numel())].reshape(style.shape)
    assert float(metrics.sliced_wasserstein_colors(permuted, style)[0]) == 0.0


def test_sw_colors_list_of_sizes_and_subsampling():
    style = smooth_image(32, 40)
    big = torch.nn.functional.interpolate(style[None], scale_factor=2, mode="nearest")[0]  # same distribution
    values = metrics.sliced_wasserstein_colors([style, big, style.flip(0)], style)
    assert float(values[0]) == 0.0
    assert float(values[1]) < 0.01 < float(values[2])
    sub = metrics.sliced_wasserstein_colors(style, style, max_samples=300)
    assert float(sub[0]) == 0.0  # same image size and seed: the same subset on both sides


def test_sw_colors_deterministic_and_seeded():
    style, image = smooth_image(seed=0), smooth_image(seed=1)
    a = metrics.sliced_wasserstein_colors(image, style, seed=3)
    assert torch.equal(a, metrics.sliced_wasserstein_colors(image, style, seed=3))
    assert float(a[0]) == pytest.approx(float(metrics.sliced_wasserstein_colors(image, style, seed=4)[0]), rel=0.2)


def test_sw_patches_known_cases():
    style = smooth_image(40, 48)
    blurred = torch.nn.functional.avg_pool2d(style[None], 5, 1, 2, count_include_pad=False)[0]
    values = metrics.sliced_wasserstein_patches([style, blurred, (style + 0.3).clamp(0, 1)], style, max_samples=2000)
    assert float(values[0]) == 0.0
    assert float(values[1]) > 0.0
    assert float(values[2]) > float(values[1])
    # The patch version sees texture that colours alone miss: a pixel shuffle keeps colours, not patches.
    shuffled = style.reshape(3, -1)[:, torch.randperm(style[0].numel())].reshape(style.shape)
    assert float(metrics.sliced_wasserstein_colors(shuffled, style)[0]) == 0.0
    assert float(metrics.sliced_wasserstein_patches(shuffled, style)[0]) > 0.025  # about a +0.05 brightness shift


def test_sw_patches_rejects_too_small_images():
    with pytest.raises(ValueError, match="smaller than the 7x7 patch"):
        metrics.sliced_wasserstein_patches(torch.rand(3, 5, 20), torch.rand(3, 20, 20))
    with pytest.raises(ValueError, match=r"\[3, H, W\]"):
        metrics.sliced_wasserstein_patches(torch.rand(4, 20, 20), torch.rand(3, 20, 20))


@pytest.mark.parametrize("fill", [0.0, 0.5, 1.0])
def test_sw_flat_images_are_finite(fill):
    flat = torch.full((3, 16, 16), fill)
    style = smooth_image()
    for fn in (metrics.sliced_wasserstein_colors, metrics.sliced_wasserstein_patches):
        assert float(fn(flat, flat)[0]) == 0.0
        value = fn(flat, style)
        assert torch.isfinite(value).all() and float(value[0]) > 0.0
        assert torch.isfinite(fn(style, flat)).all()


# ----------------------------------------------------------------------------------------------------
# Content


def test_ssim_per_image():
    a = smooth_image()
    values = metrics.ssim_per_image(torch.stack([a, a]), torch.stack([a, (a + 0.2 * torch.rand_like(a)).clamp(0, 1)]))
    assert values.shape == (2,)
    assert float(values[0]) == pytest.approx(1.0, abs=1e-6)
    assert float(values[1]) < 0.95
    assert float(metrics.ssim_per_image(torch.zeros(3, 8, 8), torch.zeros(3, 8, 8))) == pytest.approx(1.0)


def test_gradient_structure_identical_contrast_and_polarity():
    a = smooth_image(dtype=F64)
    assert float(metrics.gradient_structure_similarity(a, a)) == pytest.approx(1.0, abs=1e-12)
    # Global contrast and brightness change, and inverted colours: the same structure.
    assert float(metrics.gradient_structure_similarity(a, 0.3 + 0.4 * a)) == pytest.approx(1.0, abs=1e-3)
    assert float(metrics.gradient_structure_similarity(a, 1.0 - a)) == pytest.approx(1.0, abs=1e-6)


def test_gradient_structure_drops_when_structure_changes():
    a = smooth_image(dtype=F64)
    moved = torch.roll(a, shifts=(3, 5), dims=(1, 2))
    other = smooth_image(seed=7, dtype=F64)
    gs_moved = float(metrics.gradient_structure_similarity(a, moved))
    gs_other = float(metrics.gradient_structure_similarity(a, other))
    assert gs_moved < 0.8 and gs_other < 0.8
    # Blur keeps the edges' directions: more similar than different content.
    blurred = torch.nn.functional.avg_pool2d(a[None], 3, 1, 1, count_include_pad=False)[0]
    assert float(metrics.gradient_structure_similarity(a, blurred)) > max(gs_moved, gs_other)


def test_gradient_structure_flat_and_black_are_defined():
    black, grey = torch.zeros(3, 16, 16), torch.full((3, 16, 16), 0.5)
    assert float(metrics.gradient_structure_similarity(black, black)) == pytest.approx(1.0)
    assert float(metrics.gradient_structure_similarity(black, grey)) == pytest.approx(1.0)  # neither has edges
    textured = smooth_image(16, 16)
    value = float(metrics.gradient_structure_similarity(grey, textured))
    assert 0.0 <= value < 0.05


def test_gradient_structure_bounded_on_random_pairs():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(6, 3, 12, 12, generator=g), torch.rand(6, 3, 12, 12, generator=g)
    values = metrics.gradient_structure_similarity(a, b)
    assert values.shape == (6,) and bool(((values >= 0) & (values <= 1)).all())


def test_sobel_ramp_has_its_slope():
    ramp = (torch.arange(10, dtype=F64) * 0.05).expand(3, 8, 10)
    grad = metrics.sobel_gradients(ramp[None])[0]
    assert torch.allclose(grad[0, :, 1:-1], torch.full((8, 8), 0.05, dtype=F64))
    assert torch.allclose(grad[1], torch.zeros(8, 10, dtype=F64))


# ----------------------------------------------------------------------------------------------------
# Texture kept and shapes


def textured_base(h=48, w=64, seed=0) -> torch.Tensor:  # [3, H, W] float64: a smooth gradient plus fine noise
    y, x = torch.meshgrid(torch.linspace(0, 1, h, dtype=F64), torch.linspace(0, 1, w, dtype=F64), indexing="ij")
    smooth = 0.2 + 0.4 * x + 0.2 * y + 0.1 * torch.sin(6 * x) * torch.cos(4 * y)
    texture = 0.1 * (torch.rand(h, w, generator=torch.Generator().manual_seed(seed), dtype=F64) - 0.5)
    colour = torch.tensor([1.0, 0.9, 0.8], dtype=F64)[:, None, None]
    return (colour * (smooth + texture)).clamp(0, 1)


def blur(image: torch.Tensor, sigma: float) -> torch.Tensor:  # [C, H, W]
    return metrics.gaussian_blur(image[None], sigma)[0]


def test_gaussian_blur_keeps_constants_and_the_mean_of_a_periodic_image():
    flat = torch.full((2, 3, 9, 11), 0.3, dtype=F64)
    assert torch.allclose(metrics.gaussian_blur(flat, 2.0), flat, atol=1e-12)  # replicated border: no darkening
    checker = ((torch.arange(24)[:, None] + torch.arange(24)[None]) % 2).to(F64)[None, None]
    assert torch.allclose(metrics.gaussian_blur(checker, 2.0)[..., 8:-8, 8:-8], torch.full((8, 8), 0.5, dtype=F64))
    with pytest.raises(ValueError, match="sigma"):
        metrics.gaussian_blur(flat, 0.0)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_texture_kept_and_shapes_of_an_image_against_itself_are_1(dtype):
    images = torch.stack([textured_base(seed=s) for s in (0, 1)]).to(dtype)
    mask = blob_mask(48, 64)
    for kwargs in ({}, {"mask": mask}, {"mask": mask.to(dtype)}):
        for fn in (metrics.texture_kept, metrics.shape_similarity):
            values = fn(images, images, **kwargs)
            assert values.shape == (2,) and values.dtype == dtype
            assert torch.allclose(values, torch.ones(2, dtype=dtype), atol=1e-5)
            assert float(fn(images[0], images[0], **kwargs)) == pytest.approx(1.0, abs=1e-5)
    # A contrast change keeps the texture (a correlation) and a batch is its images one by one.
    assert float(metrics.texture_kept(0.2 + 0.5 * images[0], images[0])) == pytest.approx(1.0, abs=1e-5)
    assert float(metrics.texture_kept(0.5 * images[0], images[0], mask=mask)) == pytest.approx(1.0, abs=1e-5)
    other = images.flip(0)
    for fn in (metrics.texture_kept, metrics.shape_similarity):
        single = torch.stack([fn(a, b, mask=mask) for a, b in zip(images, other)])
        assert torch.allclose(fn(images, other, mask=mask), single, atol=1e-6)


@pytest.mark.parametrize("masked", [False, True])
def test_texture_replaced_by_noise_is_not_kept_but_the_shapes_are(masked):
    base = textured_base()
    noise = 0.1 * (torch.rand(base.shape[1:], generator=torch.Generator().manual_seed(7), dtype=F64) - 0.5)
    image = (blur(base, 2.0) + noise).clamp(0, 1)  # the capture's texture gone, other marks of the same size
    mask = blob_mask(48, 64) if masked else None
    texture = float(metrics.texture_kept(image, base, mask=mask))
    assert abs(texture) < 0.1
    shapes = float(metrics.shape_similarity(image, base, mask=mask))
    assert shapes > 0.9
    # The texture half kept: in between.
    half = float(metrics.texture_kept((blur(base, 2.0) + base) / 2 + noise / 2, base, mask=mask))
    assert 0.4 < half < 0.9
    # Other forms (the scene moved), the same kind of texture: the shapes drop (less with the shared silhouette).
    moved = torch.roll(base, shifts=(9, 17), dims=(1, 2))
    assert float(metrics.shape_similarity(moved, base, mask=mask)) < shapes - 0.1


def test_texture_kept_and_shapes_of_flat_images_are_defined():
    grey, black, base = torch.full((3, 48, 64), 0.5, dtype=F64), torch.zeros(3, 48, 64, dtype=F64), textured_base()
    for a, b in ((grey, base), (base, grey), (grey, grey), (black, black), (grey, black)):
        texture = metrics.texture_kept(a, b)
        shapes = metrics.shape_similarity(a, b)
        assert torch.isfinite(texture) and torch.isfinite(shapes)
        assert float(texture) == 0.0  # no texture in one of them: nothing kept (documented: 0.0, never NaN)
        assert 0.0 <= float(shapes) <= 1.0
    assert float(metrics.shape_similarity(grey, grey)) == pytest.approx(1.0)
    # A mask with nothing left after the erosion (5 px wide, erode 4 needs 9): 0.0 as well.
    thin = torch.zeros(48, 64, dtype=torch.bool)
    thin[10:40, 20:25] = True
    assert float(metrics.texture_kept(base, base, mask=thin)) == 0.0
    assert float(metrics.texture_kept(base, base, mask=thin, erode=2)) == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError, match="erode"):
        metrics.texture_kept(base, base, erode=-1)


def test_texture_kept_leaves_out_a_band_along_the_silhouette():
    """Texture both images share only in a band of the mask's edge, less than ``erode`` px wide, does not count."""
    g = torch.Generator().manual_seed(3)
    checker = 0.1 * ((torch.arange(48)[:, None] + torch.arange(48)[None]) % 2).to(F64)
    noise = 0.1 * torch.rand(48, 48, generator=g, dtype=F64)
    mask = torch.zeros(48, 48, dtype=torch.bool)
    mask[8:40, 8:40] = True
    inner = torch.zeros(48, 48, dtype=torch.bool)
    inner[12:36, 12:36] = True  # the pixels 4 px or more inside the mask's edge
    base = (0.5 + checker).expand(3, 48, 48)
    image = (0.5 + torch.where(inner, noise, checker)).expand(3, 48, 48)  # the same texture only in the band
    assert abs(float(metrics.texture_kept(image, base, mask=mask))) < 0.1
    assert float(metrics.texture_kept(image, base, mask=mask, erode=0)) > 0.4  # counted: the band and the edge
    # The band counts where the mask is wider than the image: pixels off the image are not uncovered.
    assert float(metrics.texture_kept(image, base, mask=torch.ones(48, 48, dtype=torch.bool))) > 0.4


# ----------------------------------------------------------------------------------------------------
# Mark contrast and forms


def painting_image(h=48, w=64, seed=5) -> torch.Tensor:  # [3, H, W] float64: colour marks at every scale
    g = torch.Generator().manual_seed(seed)
    layers = [
        torch.nn.functional.interpolate(torch.rand(1, 3, h // k, w // k, generator=g, dtype=F64), size=(h, w))[0]
        for k in (8, 4, 2, 1)  # blocks of 8, 4, 2 and 1 px: edges and flats, like strokes
    ]
    return sum(layers) / len(layers)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_mark_contrast_is_1_for_the_painting_and_0_for_the_base_itself(dtype):
    painting, base = painting_image().to(dtype), textured_base().to(dtype)
    flat = torch.full_like(painting, 0.5)
    values = metrics.mark_contrast(painting, flat, painting)  # by construction: the painting's own bands
    assert values.shape == (3,) and values.dtype == dtype
    assert values.tolist() == pytest.approx([1.0, 1.0, 1.0], abs=1e-5)
    # A view of the painting at Stroke Size 1.5: a crop of it, measured against the whole.
    large = torch.nn.functional.interpolate(painting_image(24, 32)[None], size=(72, 96))[0].to(dtype)
    crop = large[:, 12:60, 16:80]
    assert metrics.mark_contrast(crop, flat, large).tolist() == pytest.approx([1.0, 1.0, 1.0], abs=0.2)
    # A blurred copy: the marks gone, most of all the fine ones.
    blurred = metrics.mark_contrast(blur(painting, 8.0), flat, painting)
    assert float(blurred[0]) < 0.02 and float(blurred.max()) < 0.15
    # The base itself, or its texture at another brightness and contrast: none of the painting's marks.
    assert metrics.mark_contrast(base, base, painting).tolist() == [0.0, 0.0, 0.0]
    assert metrics.mark_contrast(0.2 + 0.5 * base, base, painting).abs().max() < 1e-5


@pytest.mark.parametrize("masked", [False, True])
def test_mark_contrast_leaves_the_capture_s_texture_out(masked):
    painting, base = painting_image(), textured_base()
    mask = blob_mask(48, 64) if masked else None
    marks = painting - painting.mean()
    for stylized in (base + marks, 0.5 * base + marks):  # the capture's texture left in, at any contrast
        assert metrics.mark_contrast(stylized, base, painting, mask=mask).tolist() == pytest.approx([1, 1, 1], abs=0.1)
    assert metrics.mark_contrast(base, base, painting, mask=mask).tolist() == [0.0, 0.0, 0.0]
    half = metrics.mark_contrast(base + 0.5 * marks, base, painting, mask=mask)
    assert half.tolist() == pytest.approx([0.5, 0.5, 0.5], abs=0.05)  # a linear measure: half the marks, half


def test_mark_contrast_on_a_black_background_counts_the_covered_pixels_alone():
    painting, base, mask = painting_image(), textured_base(), blob_mask(48, 64)
    stylized = torch.where(mask, painting, 0.0)  # the painting inside the silhouette, black around it
    values = metrics.mark_contrast(stylized, torch.where(mask, base, 0.0), painting, mask=mask)
    assert values.tolist() == pytest.approx([1.0, 1.0, 1.0], abs=0.1)  # the silhouette's edge makes no marks
    # A mask of alpha values thresholds at one half; a batch is its views one by one.
    assert torch.allclose(metrics.mark_contrast(stylized, base, painting, mask=0.8 * mask), values, atol=1e-6)
    both = metrics.mark_contrast(torch.stack([stylized, base]), torch.stack([base, base]), painting, mask=mask)
    assert both.shape == (2, 3) and torch.allclose(both[0], values, atol=1e-6) and both[1].abs().max() == 0.0


def test_mark_contrast_extremes_are_defined():
    painting, base = painting_image(), textured_base()
    grey, black = torch.full_like(base, 0.5), torch.zeros_like(base)
    cases = [(grey, grey, painting), (black, black, painting), (painting, base, grey), (grey, base, painting)]
    for image, reference, style in cases:
        values = metrics.mark_contrast(image, reference, style)
        assert bool(values.isfinite().all()) and float(values.min()) >= 0.0
    assert metrics.mark_contrast(painting, grey, grey).tolist() == [0.0, 0.0, 0.0]  # a flat painting has no marks
    assert metrics.mark_contrast(grey, grey, painting).tolist() == [0.0, 0.0, 0.0]  # a flat render none either
    # An empty mask covers every pixel; a mask with nothing left after the erosion gives 0.
    empty = torch.zeros(48, 64, dtype=torch.bool)
    assert torch.equal(
        metrics.mark_contrast(painting, grey, painting, mask=empty), metrics.mark_contrast(painting, grey, painting)
    )
    thin = torch.zeros(48, 64, dtype=torch.bool)
    thin[10:40, 20:25] = True
    assert metrics.mark_contrast(painting, grey, painting, mask=thin).tolist() == [0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="erode"):
        metrics.mark_contrast(painting, grey, painting, erode=-1)
    with pytest.raises(ValueError, match="painting"):
        metrics.mark_contrast(painting, grey, painting[0])


def forms_image(h=48, w=64) -> torch.Tensor:  # [3, H, W] float64: forms of ~10 px with strong edges, and texture
    y, x = torch.meshgrid(torch.arange(h, dtype=F64), torch.arange(w, dtype=F64), indexing="ij")
    forms = 0.5 + 0.3 * torch.sin(2 * math.pi * x / 20) * torch.cos(2 * math.pi * y / 24)
    return (forms + textured_base(h, w) - 0.4).clamp(0, 1)


@pytest.mark.parametrize("masked", [False, True])
def test_forms_keep_a_brightness_or_contrast_change_and_drop_for_other_forms(masked):
    base = forms_image()
    mask = blob_mask(48, 64) if masked else None
    for image in (base, 0.1 + 0.6 * base, 1.5 * base - 0.3):
        assert float(metrics.forms_similarity(image, base, mask=mask)) == pytest.approx(1.0, abs=1e-6)
    assert float(metrics.forms_similarity(base.float(), base.float(), mask=mask)) == pytest.approx(1.0, abs=1e-5)
    # The palette's brightness lowers shapes (full SSIM), not forms.
    dark = 0.3 * base
    assert float(metrics.shape_similarity(dark, base, mask=mask)) < 0.9
    # Other forms: the scene moved, or its light inverted.
    moved = torch.roll(base, shifts=(9, 17), dims=(1, 2))
    assert float(metrics.forms_similarity(moved, base, mask=mask)) < 0.8
    assert float(metrics.forms_similarity(1.0 - base, base, mask=mask)) < 0.0
    # Fine marks over the forms cost little; a batch is its pairs one by one.
    marked = base + 0.1 * (painting_image(8, 8) - 0.5).repeat(1, 6, 8)
    assert float(metrics.forms_similarity(marked, base, mask=mask)) > 0.8
    pairs = torch.stack([marked, moved]), torch.stack([base, base])
    single = torch.stack([metrics.forms_similarity(a, b, mask=mask) for a, b in zip(*pairs)])
    assert torch.allclose(metrics.forms_similarity(*pairs, mask=mask), single, atol=1e-6)


def test_forms_of_flat_images_and_empty_masks_are_defined():
    base = forms_image()
    grey, black = torch.full_like(base, 0.5), torch.zeros_like(base)
    for a, b in ((grey, base), (base, grey), (grey, grey), (black, black), (grey, black)):
        value = float(metrics.forms_similarity(a, b))
        assert math.isfinite(value) and -1.0 <= value <= 1.0
    assert float(metrics.forms_similarity(grey, black)) == pytest.approx(1.0)  # no form in either
    empty = torch.zeros(48, 64, dtype=torch.bool)
    moved = torch.roll(base, shifts=(9, 17), dims=(1, 2))
    assert float(metrics.forms_similarity(moved, base, mask=empty)) == float(metrics.forms_similarity(moved, base))


# ----------------------------------------------------------------------------------------------------
# Coverage masks (objects on a black background)


def blob_mask(h=32, w=40) -> torch.Tensor:  # [H, W] bool: an off-centre ellipse, like an object's silhouette
    y, x = torch.meshgrid(torch.arange(h, dtype=F64) + 0.5, torch.arange(w, dtype=F64) + 0.5, indexing="ij")
    return ((y - 0.45 * h) / (0.4 * h)) ** 2 + ((x - 0.55 * w) / (0.4 * w)) ** 2 <= 1.0


def test_sw_colors_masked_is_the_sw_of_the_covered_pixels():
    style = smooth_image(32, 40)
    on_black = torch.cat([style, torch.zeros(3, 32, 24)], -1)  # the style itself, then black background
    covered = (torch.arange(64) < 40).expand(32, 64)
    assert float(metrics.sliced_wasserstein_colors(on_black, style, masks=covered)[0]) == 0.0
    assert float(metrics.sliced_wasserstein_colors(on_black, style)[0]) > 0.1
    # An irregular mask: the same value as an image made of the covered pixels alone, subsampled or not.
    image, mask = smooth_image(32, 40, seed=2), blob_mask()
    alone = image[:, mask][:, None, :]  # [3, 1, n]
    assert alone.shape[-1] > 300
    for max_samples in (None, 65536, 300):
        masked = metrics.sliced_wasserstein_colors(image, style, max_samples=max_samples, masks=mask)
        assert torch.equal(masked, metrics.sliced_wasserstein_colors(alone, style, max_samples=max_samples))
    # An all-true mask keeps every pixel: exactly the unmasked value (subset included).
    full = torch.ones(32, 40, dtype=torch.bool)
    for max_samples in (None, 300):
        assert torch.equal(
            metrics.sliced_wasserstein_colors(image, style, max_samples=max_samples, masks=full),
            metrics.sliced_wasserstein_colors(image, style, max_samples=max_samples),
        )


def test_sw_patches_masked_ignores_windows_touching_the_background():
    style = smooth_image(32, 40, dtype=F64)
    noise = torch.rand(3, 32, 24, generator=torch.Generator().manual_seed(5), dtype=F64)
    image = torch.cat([style, noise], -1)
    covered = (torch.arange(64) < 40).expand(32, 64)
    # The fully covered windows are exactly the style's windows; every window reaching the noise is left out.
    assert float(metrics.sliced_wasserstein_patches(image, style, masks=covered)[0]) == 0.0
    assert float(metrics.sliced_wasserstein_patches(image, style)[0]) > 0.05
    # Irregular mask: the same as SW_2 of the windows lying wholly inside it, enumerated by hand.
    image, mask = smooth_image(32, 40, seed=2, dtype=F64), blob_mask()
    windows = [
        image[:, top : top + 7, left : left + 7].reshape(-1)
        for top in range(26)
        for left in range(34)
        if bool(mask[top : top + 7, left : left + 7].all())
    ]
    style_windows = [style[:, t : t + 7, l : l + 7].reshape(-1) for t in range(26) for l in range(34)]
    assert 50 < len(windows) < 26 * 34
    expected = metrics.sliced_wasserstein(torch.stack(windows), torch.stack(style_windows))
    masked = metrics.sliced_wasserstein_patches(image, style, masks=mask)
    assert float(masked[0]) == pytest.approx(float(expected), rel=1e-12)
    # The background does not matter, up to the pixels next to the silhouette.
    repainted = torch.where(mask, image, torch.rand(3, 32, 40, dtype=F64))
    assert torch.equal(masked, metrics.sliced_wasserstein_patches(repainted, style, masks=mask))
    # Subsampling among the kept windows is deterministic.
    a = metrics.sliced_wasserstein_patches(image, style, max_samples=40, masks=mask)
    assert torch.equal(a, metrics.sliced_wasserstein_patches(image, style, max_samples=40, masks=mask))


def test_masks_that_cover_nothing_fall_back_to_all_pixels():
    style, image = smooth_image(seed=0), smooth_image(seed=1)
    empty = torch.zeros(32, 40, dtype=torch.bool)
    for fn in (metrics.sliced_wasserstein_colors, metrics.sliced_wasserstein_patches):
        value = fn(image, style, masks=empty)
        assert torch.isfinite(value).all()
        assert torch.equal(value, fn(image, style))
    # A mask thinner than the patch has no fully covered window: all windows, per image.
    line = torch.zeros(32, 40, dtype=torch.bool)
    line[10] = True
    both = metrics.sliced_wasserstein_patches(
        torch.stack([image, image]), style, masks=torch.stack([line, blob_mask()])
    )
    assert float(both[0]) == float(metrics.sliced_wasserstein_patches(image, style)[0])
    assert float(both[1]) != float(both[0])
    a, b = smooth_image(dtype=F64), smooth_image(seed=3, dtype=F64)
    for fn in (metrics.ssim_per_image, metrics.gradient_structure_similarity):
        value = fn(a, b, mask=empty)
        assert math.isfinite(float(value))
        assert float(value) == pytest.approx(float(fn(a, b)), abs=1e-12)


def test_float_alpha_masks_threshold_at_half():
    style, image = smooth_image(seed=0), smooth_image(seed=1)
    mask = blob_mask()
    alpha = torch.where(mask, 0.51, 0.49) + 0.4 * torch.where(mask, 1.0, -1.0) * torch.rand(32, 40)  # clear of 0.5
    assert torch.equal(alpha > metrics.ALPHA_THRESHOLD, mask)
    for fn in (metrics.sliced_wasserstein_colors, metrics.sliced_wasserstein_patches):
        assert torch.equal(fn(image, style, masks=alpha), fn(image, style, masks=mask))
    for fn in (metrics.ssim_per_image, metrics.gradient_structure_similarity):
        assert torch.equal(fn(image, style, mask=alpha), fn(image, style, mask=mask))
    # Exactly the threshold is not covered (as in warp_to).
    half = torch.where(mask, 1.0, 0.5)
    assert torch.equal(
        metrics.sliced_wasserstein_colors(image, style, masks=half),
        metrics.sliced_wasserstein_colors(image, style, masks=mask),
    )


def test_ssim_masked_ignores_the_background():
    a, mask = smooth_image(dtype=F64), blob_mask()
    noise = torch.rand(3, 32, 40, generator=torch.Generator().manual_seed(1), dtype=F64)
    b = torch.where(mask, a, noise)  # identical where covered, different background
    assert float(metrics.ssim_per_image(a, b, mask=mask)) == pytest.approx(1.0, abs=1e-6)
    assert float(metrics.ssim_per_image(a, b)) < 0.9
    # A change on the object only: the background no longer dilutes it.
    changed = torch.where(mask, (a + 0.2 * noise).clamp(0, 1), a)
    masked = float(metrics.ssim_per_image(a, changed, mask=mask))
    assert masked < float(metrics.ssim_per_image(a, changed)) and masked < 0.95


def test_gradient_structure_masked_ignores_the_background():
    a, mask = smooth_image(dtype=F64), blob_mask()
    other = smooth_image(seed=7, dtype=F64)
    b = torch.where(mask, a, other)
    assert float(metrics.gradient_structure_similarity(a, b, mask=mask)) == pytest.approx(1.0, abs=1e-9)
    assert float(metrics.gradient_structure_similarity(a, b)) < 0.9
    # Other content on the object, the same background: lower (the shared silhouette keeps it well above 0).
    assert float(metrics.gradient_structure_similarity(a, torch.where(mask, other, a), mask=mask)) < 0.85


@pytest.mark.slow
def test_masks_list_and_batch_agree():
    style = smooth_image(seed=0)
    images = torch.stack([smooth_image(seed=s) for s in (1, 2, 3)])
    masks = torch.stack([blob_mask(), blob_mask().flip(0), torch.ones(32, 40, dtype=torch.bool)])
    for fn in (metrics.sliced_wasserstein_colors, metrics.sliced_wasserstein_patches):
        batched = fn(images, style, masks=masks)
        assert torch.equal(batched, fn(list(images), style, masks=list(masks)))
        assert torch.equal(batched, torch.cat([fn(i, style, masks=m) for i, m in zip(images, masks)]))
        # None in a list: that image unmasked.
        assert torch.equal(fn(images, style, masks=[masks[0], None, masks[2]])[1], fn(images[1], style)[0])
    others = torch.stack([smooth_image(seed=s) for s in (4, 5, 6)])
    for fn in (metrics.ssim_per_image, metrics.gradient_structure_similarity):
        batched = fn(images, others, mask=masks)
        single = torch.stack([fn(i, o, mask=m) for i, o, m in zip(images, others, masks)])
        assert torch.allclose(batched, single, atol=1e-6)
        assert torch.equal(fn(images, others, mask=masks[0]), fn(images, others, mask=masks[0].expand(3, 32, 40)))


def test_masks_bad_shapes_raise():
    style, images = smooth_image(seed=0), torch.stack([smooth_image(seed=1)] * 2)
    for fn in (metrics.sliced_wasserstein_colors, metrics.sliced_wasserstein_patches):
        with pytest.raises(ValueError, match=r"got shape \(32, 41\)"):
            fn(images, style, masks=torch.ones(2, 32, 41, dtype=torch.bool))
        with pytest.raises(ValueError, match=r"got shape \(2, 1, 32, 40\)"):
            fn(images, style, masks=torch.ones(2, 1, 32, 40, dtype=torch.bool))
        with pytest.raises(ValueError, match="got 3 masks for 2 images"):
            fn(images, style, masks=[torch.ones(32, 40, dtype=torch.bool)] * 3)
    for fn in (metrics.ssim_per_image, metrics.gradient_structure_similarity):
        with pytest.raises(ValueError, match=r"got shape \(3, 32, 40\)"):
            fn(images, images, mask=torch.ones(3, 32, 40, dtype=torch.bool))
        with pytest.raises(ValueError, match=r"got shape \(40, 32\)"):
            fn(images[0], images[0], mask=torch.ones(40, 32, dtype=torch.bool))


# ----------------------------------------------------------------------------------------------------
# Consistency: the warp


def plane_depth(cam: Camera, plane_z: float) -> torch.Tensor:  # camera z of the world plane z = plane_z
    v, u = np.meshgrid(np.arange(cam.height) + 0.5, np.arange(cam.width) + 0.5, indexing="ij")
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)  # camera z = 1
    c2w = cam.camera_to_world
    world_dirs = rays @ c2w[:3, :3].T
    t = (plane_z - cam.center[2]) / world_dirs[..., 2]
    return torch.tensor(np.where(t > 0, t, 0.0))


def test_warp_matches_analytic_reprojection_on_a_plane():
    # Source: identity camera looking at the plane z = 2, with an image linear in (u, v) (bilinear is exact).
    src = Camera(40, 30, 30.0, 30.0, 20.0, 15.0, np.eye(4))
    dst = Camera(36, 28, 28.0, 29.0, 17.0, 14.5, look_at((0.3, -0.2, -0.1), (0.05, 0.0, 2.0)))
    v, u = torch.meshgrid(torch.arange(30, dtype=F64) + 0.5, torch.arange(40, dtype=F64) + 0.5, indexing="ij")
    src_rgb = torch.stack([u / 40, v / 30, 0.25 + 0.01 * u], -1)
    src_depth = torch.full((30, 40), 2.0, dtype=F64)
    dst_depth = plane_depth(dst, 2.0)
    warped, valid = metrics.warp_to(src_rgb, src_depth, src, dst, dst_depth)
    assert valid.float().mean() > 0.5
    # Expected: the world point of each destination pixel projected into the source by hand.
    vd, ud = np.meshgrid(np.arange(28) + 0.5, np.arange(36) + 0.5, indexing="ij")
    z = dst_depth.numpy()
    cam_pts = np.stack([(ud - dst.cx) / dst.fx * z, (vd - dst.cy) / dst.fy * z, z, np.ones_like(z)], -1)
    world = cam_pts @ dst.camera_to_world.T
    us, vs = 30.0 * world[..., 0] / world[..., 2] + 20.0, 30.0 * world[..., 1] / world[..., 2] + 15.0
    expected = np.stack([us / 40, vs / 30, 0.25 + 0.01 * us], -1)
    inside = (us >= 0.5) & (us <= 39.5) & (vs >= 0.5) & (vs <= 29.5)
    assert np.array_equal(valid.numpy(), inside)
    np.testing.assert_allclose(warped.numpy()[inside], expected[inside], atol=1e-9)
    assert float(warped[~valid].abs().max()) == 0.0


def test_warp_occlusion_and_alpha_masks():
    cam = Camera(20, 16, 20.0, 20.0, 10.0, 8.0, np.eye(4))
    shifted = Camera(20, 16, 20.0, 20.0, 10.0, 8.0, look_at((0.1, 0, 0), (0.1, 0, 1)))
    rgb = torch.rand(16, 20, 3)
    depth = torch.full((16, 20), 2.0)
    src_depth = depth.clone()
    src_depth[:, :8] = 1.0  # an occluder in front of the plane over the source's left part
    _, free = metrics.warp_to(rgb, depth, cam, shifted, depth)
    _, occluded = metrics.warp_to(rgb, src_depth, cam, shifted, depth)
    assert int(occluded.sum()) < int(free.sum())
    alpha = torch.ones(16, 20)
    alpha[5:9] = 0.2
    _, masked = metrics.warp_to(rgb, depth, cam, shifted, depth, dst_alpha=alpha)
    assert not masked[5:9].any() and masked.sum() > 0
    with pytest.raises(ValueError, match="src_depth has shape"):
        metrics.warp_to(rgb, depth[:-1], cam, shifted, depth)


def test_warp_behind_camera_and_far_off_screen_are_invalid():
    cam = Camera(10, 8, 10.0, 10.0, 5.0, 4.0, np.eye(4))
    turned = Camera(10, 8, 10.0, 10.0, 5.0, 4.0, look_at((0, 0, 0), (0, 0, -1), up=(0, -1, 0)))  # looks back
    depth = torch.full((8, 10), 3.0)
    warped, valid = metrics.warp_to(torch.rand(8, 10, 3), depth, cam, turned, depth)
    assert not valid.any() and torch.isfinite(warped).all()


@pytest.fixture(scope="module")
def demo_views():
    """The Lambertian demo scene (no SH rest) from two cameras 5 degrees apart, 96 x 72."""
    scene = demo_scene()
    cameras = demo_cameras(n=72, width=96, height=72)[:2]
    return scene, cameras, [render_scene(scene, c) for c in cameras]


def test_warp_of_a_render_matches_the_other_views_render(demo_views):
    _, cameras, (a, b) = demo_views
    assert bool((a.depth[a.alpha > 0.5] > 0).all())
    warped, valid = metrics.warp_to(a.rgb, a.depth, cameras[0], cameras[1], b.depth, a.alpha, b.alpha)
    coverage = float(valid.float().mean())
    rmse = metrics.masked_rmse(warped, b.rgb, valid)
    unwarped = float((a.rgb - b.rgb).pow(2).mean().sqrt())
    assert coverage > 0.4
    assert rmse < 0.03 and rmse < 0.25 * unwarped


def test_consistency_rmse_detects_per_view_colour_change(demo_views):
    scene, cameras, (a, b) = demo_views
    changed = scene.copy()
    changed.sh_dc = changed.sh_dc + np.float32(0.15 / 0.28209479)  # +0.15 on every colour, view b only
    b2 = render_scene(changed, cameras[1])
    consistent = metrics.consistency_rmse([a.rgb, b.rgb], [a.depth, b.depth], [a.alpha, b.alpha], cameras, gap=1)
    flicker = metrics.consistency_rmse(
        [a.rgb, b2.rgb.clamp(0, 1)], [a.depth, b2.depth], [a.alpha, b2.alpha], cameras, gap=1
    )
    assert len(consistent.pairs) == 1 and consistent.coverage > 0.4
    assert flicker.rmse > 3 * consistent.rmse and flicker.rmse > 0.1
    assert flicker.coverage == pytest.approx(consistent.coverage)


def test_consistency_rmse_empty_views_and_no_pairs():
    cam = Camera(12, 10, 12.0, 12.0, 6.0, 5.0, np.eye(4))
    black, zero = torch.zeros(10, 12, 3), torch.zeros(10, 12)
    result = metrics.consistency_rmse([black] * 3, [zero] * 3, [zero] * 3, [cam] * 3, gap=1)
    assert result.rmse is None and result.coverage == 0.0 and len(result.pairs) == 2
    assert all(p.rmse is None and p.coverage == 0.0 for p in result.pairs)
    none = metrics.consistency_rmse([black], [zero], [zero], [cam], gap=1)
    assert none.rmse is None and none.coverage == 0.0 and none.pairs == []
    # The JSON form has no NaN.
    json.dumps(result.as_dict(), allow_nan=False)
    with pytest.raises(ValueError, match="gap"):
        metrics.consistency_rmse([black], [zero], [zero], [cam], gap=0)
    with pytest.raises(ValueError, match="cameras"):
        metrics.consistency_rmse([black] * 2, [zero], [zero], [cam] * 2, gap=1)


def test_consistency_gap_pairs():
    cam = Camera(8, 6, 8.0, 8.0, 4.0, 3.0, np.eye(4))
    rgb, depth = torch.rand(6, 8, 3), torch.full((6, 8), 1.0)
    result = metrics.consistency_rmse([rgb] * 6, [depth] * 6, None, [cam] * 6, gap=3)
    assert [(p.source, p.target) for p in result.pairs] == [(0, 3), (1, 4), (2, 5)]
    assert result.rmse == 0.0 and result.coverage == 1.0


# ----------------------------------------------------------------------------------------------------
# Efficiency


def test_read_stylize_log(tmp_path):
    path = tmp_path / "log.jsonl"
    lines = [
        {"stage": "proposal", "seconds": 1.5, "peak_rss_mb": 800.0},
        {"stage": 0, "seconds": 4.0, "peak_rss_mb": 1200.5, "peak_cuda_mb": 300},
        {"stage": 1, "note": "no time here"},
        {"stage": 1, "seconds": float("nan")},  # written as NaN by json.dumps: ignored
        [1, 2],
    ]
    text = "\n".join(json.dumps(line) for line in lines) + '\n{"stage": 2, "seconds": 9'  # cut short
    path.write_text(text)
    summary = metrics.read_stylize_log(path)
    assert summary.optimisation_seconds == 4.0
    assert summary.peaks == {"peak_rss_mb": 1200.5, "peak_cuda_mb": 300.0}
    assert summary.stages == ["proposal", 0, 1]
    assert summary.records == 4 and summary.skipped == 2
    out = summary.as_dict()
    assert out["optimisation_seconds"] == 4.0 and out["peak_rss_mb"] == 1200.5
    json.dumps(out, allow_nan=False)


def test_read_stylize_log_resumed_run(tmp_path):
    # A resumed run rewrites the finished stages, then its own clock starts again from 0.
    seconds = [10.0, 20.0, 3.0, 8.0]
    path = tmp_path / "log.jsonl"
    path.write_text("".join(json.dumps({"stage": i, "seconds": s}) + "\n" for i, s in enumerate(seconds)))
    assert metrics.read_stylize_log(path).optimisation_seconds == 28.0


def test_read_stylize_log_empty_and_missing(tmp_path):
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    summary = metrics.read_stylize_log(empty)
    assert summary.optimisation_seconds is None and summary.peaks == {} and summary.records == 0
    with pytest.raises(ConfigError) as error:
        metrics.read_stylize_log(tmp_path / "nope.jsonl")
    names(error, "nope.jsonl")


def test_measure_render(demo_views):
    scene, cameras, _ = demo_views
    small = [c.resized(32, 24) for c in cameras]
    bench = metrics.measure_render(scene, small, repeats=2)
    assert bench.frames == 4 and bench.seconds > 0 and math.isfinite(bench.fps) and bench.fps > 0
    assert bench.fps == pytest.approx(bench.frames / bench.seconds)
    assert bench.peak_rss_mb > 0 and bench.peak_cuda_mb is None
    with pytest.raises(ValueError, match="repeats"):
        metrics.measure_render(scene, small, repeats=0)


# ----------------------------------------------------------------------------------------------------
# CLIP-S and DINO-C with tiny random models


@pytest.fixture(scope="module")
def tiny_models(tmp_path_factory):
    transformers = pytest.importorskip("transformers")
    root = tmp_path_factory.mktemp("models")
    torch.manual_seed(0)
    small = {"hidden_size": 16, "intermediate_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2}
    clip = transformers.CLIPConfig(
        text_config={**small, "vocab_size": 64, "max_position_embeddings": 8, "bos_token_id": 0, "eos_token_id": 1},
        vision_config={**small, "image_size": 32, "patch_size": 8},
        projection_dim=8,
    )
    transformers.CLIPModel(clip).save_pretrained(root / "clip")
    vit = transformers.ViTConfig(**small, image_size=32, patch_size=8)
    transformers.ViTModel(vit, add_pooling_layer=False).save_pretrained(root / "vit")
    transformers.Dinov2Model(transformers.Dinov2Config(**small, image_size=32, patch_size=8)).save_pretrained(
        root / "dinov2"
    )
    # A ViT config with two layers beside one-layer weights: transformers would fill layer 2 at random.
    (root / "vit_partial").mkdir()
    (root / "vit_partial" / "model.safetensors").write_bytes((root / "vit" / "model.safetensors").read_bytes())
    config = json.loads((root / "vit" / "config.json").read_text())
    (root / "vit_partial" / "config.json").write_text(json.dumps({**config, "num_hidden_layers": 2}))
    (root / "config_only").mkdir()
    (root / "config_only" / "config.json").write_text((root / "vit" / "config.json").read_text())
    return root


def test_clip_style_score(tiny_models):
    from dresg_addon.evaluation import clip_dino

    model = clip_dino.load_clip(tiny_models / "clip")
    assert model.image_size == 32 and model.mean == clip_dino.CLIP_MEAN
    style = smooth_image(40, 48)
    renders = torch.stack([style, style.flip(-1), torch.zeros_like(style), torch.ones_like(style)])
    scores = clip_dino.clip_style_score(model, renders, style)
    assert scores.shape == (4,) and torch.isfinite(scores).all()
    assert float(scores[0]) == pytest.approx(1.0, abs=1e-5)
    assert bool((scores.abs() <= 1 + 1e-6).all())
    # Another image size gives the same embedding after the resize to the model's input.
    assert float(clip_dino.clip_style_score(model, [style], smooth_image(40, 48))[0]) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("name", ["vit", "dinov2"])
def test_dino_content_score(tiny_models, name):
    from dresg_addon.evaluation import clip_dino

    model = clip_dino.load_dino(tiny_models / name)
    assert model.image_size == (32 if name == "vit" else 224)
    contents = torch.stack([smooth_image(seed=s) for s in range(3)])
    same = clip_dino.dino_content_score(model, contents, contents)
    assert torch.allclose(same, torch.ones(3), atol=1e-5)
    other = clip_dino.dino_content_score(model, contents, contents.roll(1, 0))
    assert torch.isfinite(other).all() and bool((other <= 1 + 1e-6).all())
    black = clip_dino.dino_content_score(model, torch.zeros(1, 3, 20, 20), torch.zeros(1, 3, 20, 20))
    assert float(black[0]) == pytest.approx(1.0, abs=1e-5)
    with pytest.raises(ValueError, match="content images"):
        clip_dino.dino_content_score(model, contents, contents[:2])


def test_model_errors(tiny_models, tmp_path):
    from dresg_addon.evaluation import clip_dino

    with pytest.raises(ModelError, match="no such folder"):
        clip_dino.load_clip(tmp_path / "missing")
    with pytest.raises(ModelError, match="no config.json"):
        clip_dino.load_dino(tmp_path)
    with pytest.raises(ModelError, match="'clip' is not a DINO model"):
        clip_dino.load_dino(tiny_models / "clip")
    with pytest.raises(ModelError, match="'vit' is not a CLIP model"):
        clip_dino.check_model_folder(tiny_models / "vit", "clip")
    with pytest.raises(ModelError, match="lack .* parameters"):
        clip_dino.load_dino(tiny_models / "vit_partial")
    with pytest.raises(ModelError, match="cannot load the DINO weights") as info:
        clip_dino.load_dino(tiny_models / "config_only")
    assert "\n" not in str(info.value)


def test_mark_length_follows_strokes_round_and_is_short_for_dabs_noise_and_flats():
    """Strokes 30 px long run far along their direction and about a pixel across it, whichever way they curve; the same
    strokes cut into 6 px pieces run short; blobs (a blur) run further but as far across, so their elongation is low;
    noise runs nowhere; a flat image 0."""
    g = torch.Generator().manual_seed(0)
    h, w = 96, 128
    y, x = torch.meshgrid(torch.arange(h, dtype=F64), torch.arange(w, dtype=F64), indexing="ij")
    angle = 0.6 * torch.sin(x / 40.0)  # the strokes' direction turns across the image
    along = x * torch.cos(angle) + y * torch.sin(angle)
    across = y * torch.cos(angle) - x * torch.sin(angle)
    lane = torch.floor(across / 5.0).long() % 64
    shade = torch.rand(64, 64, generator=g, dtype=F64)
    strokes = shade[lane, torch.floor(along / 30.0).long() % 64].expand(3, h, w)
    length, width = metrics.mark_length(strokes)
    assert length / width > 5.0  # 5.5 / 0.73
    cut = shade[lane, torch.floor(along / 6.0).long() % 64].expand(3, h, w)
    assert metrics.mark_length(cut)[0] < 0.5 * length  # 1.9
    blobs = metrics.gaussian_blur(torch.rand(1, 3, h, w, generator=g, dtype=F64), 3.0)[0]
    noise = torch.rand(3, h, w, generator=g, dtype=F64)
    for image in (blobs, noise):  # 4.2 / 2.1 and 0.67 / 0.54
        other_length, other_width = metrics.mark_length(image)
        assert other_length / other_width < 0.5 * length / width
    assert metrics.mark_length(torch.full((3, h, w), 0.4, dtype=F64)) == (0.0, 0.0)
    # Masked: the strokes inside a silhouette on black measure as the strokes do.
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[8:-8, 8:-8] = True
    inside = metrics.mark_length(torch.where(mask, strokes, 0.0), mask)
    assert inside[0] == pytest.approx(length, rel=0.25) and inside[1] < 1.0
