"""Proxies (method/proxies.py): splats narrower than a pixel share a colour per pixel-sized cell during the colour fit;
the renders stay exact, wide splats keep their own colour, and every member takes its cell's colour at the end."""

from __future__ import annotations

import numpy as np
import torch
from test_marks import plane_cameras as cameras  # three views from above, 1.2 away, 60 px focal

from dresg_addon.method.config import preset_run
from dresg_addon.method.fitting import FitState, ViewRenderer, result_scene, seen_gaussians
from dresg_addon.method.loop import stylize
from dresg_addon.method.proxies import _equal_rows, proxy_columns
from dresg_addon.raster import RasterSettings
from dresg_addon.raster.rasterizer import ColorOnlyRenderer, geometry_tensors, render_scene
from dresg_addon.scene.gaussians import GaussianScene

FINE = 6000  # about 4 to a pixel-sized cell


def mixed_scene(seed: int = 0) -> GaussianScene:
    """A plane of fine splats (0.2 px in the views below) with a few wide ones (6 px) over it."""
    rng = np.random.default_rng(seed)
    fine, wide = FINE, 12
    means = np.concatenate(
        [
            np.c_[rng.uniform(-0.3, 0.3, (fine, 2)), np.zeros(fine)],
            np.c_[rng.uniform(-0.25, 0.25, (wide, 2)), np.full(wide, -0.05)],
        ]
    ).astype(np.float32)
    sigma = np.r_[np.full(fine, 0.004), np.full(wide, 0.12)]
    log_scales = np.log(np.c_[sigma, sigma, sigma * 0.1]).astype(np.float32)
    count = fine + wide
    return GaussianScene(
        means=means,
        log_scales=log_scales,
        quats=np.tile(np.float32([1, 0, 0, 0]), (count, 1)),
        opacity_logits=np.r_[np.full(fine, 2.0), np.full(wide, -1.0)].astype(np.float32),
        sh_dc=rng.normal(0, 0.8, (count, 3)).astype(np.float32),
    )


def test_a_merged_map_draws_the_same_image_as_its_members_painted_their_cells_colour():
    scene, camera = mixed_scene(), cameras()[1]
    tensors = geometry_tensors(scene)
    column = torch.from_numpy(np.random.default_rng(1).integers(0, 40, len(scene)))
    colors = torch.rand(40, 3, generator=torch.Generator().manual_seed(2))
    exact = ColorOnlyRenderer(*tensors, camera)(colors[column])
    merged = ColorOnlyRenderer(*tensors, camera).merge_columns(column, 40)
    assert merged.map.nnz < ColorOnlyRenderer(*tensors, camera).map.nnz  # a pixel's samples of one cell are summed
    assert torch.allclose(merged(colors), exact, atol=1e-6)
    pixel, gauss, _ = merged.contributions()
    assert bool((pixel[1:] >= pixel[:-1]).all()) and int(gauss.max()) < 40


def test_a_map_merged_where_only_some_columns_are_shared_sums_exactly_their_samples():
    scene, camera = mixed_scene(), cameras()[0]
    tensors = geometry_tensors(scene)
    # The fine splats two by two into one column each, the wide ones each their own: most samples stay alone.
    column = torch.arange(len(scene)) // 2
    column[FINE:] = torch.arange(FINE // 2, FINE // 2 + len(scene) - FINE)
    count = int(column.max()) + 1
    colors = torch.rand(count, 3, generator=torch.Generator().manual_seed(3))
    whole = ColorOnlyRenderer(*tensors, camera)
    pixel, gauss, weight = whole.contributions()
    pairs = torch.unique(pixel * count + column[gauss]).numel()  # distinct (pixel, column): the merged samples
    merged = ColorOnlyRenderer(*tensors, camera).merge_columns(column, count)
    assert merged.map.nnz == pairs < whole.map.nnz
    assert torch.allclose(merged(colors), whole(colors[column]), atol=1e-6)
    assert torch.equal(merged.seen, torch.zeros(count, dtype=torch.bool).index_fill_(0, column[gauss], True))
    merged_pixel, merged_column, _ = merged.contributions()
    assert bool((merged_pixel[1:] >= merged_pixel[:-1]).all())
    assert torch.unique(merged_pixel * count + merged_column).numel() == pairs  # no (pixel, column) twice


def test_fine_splats_share_cells_and_wide_ones_keep_their_own_column():
    scene, views = mixed_scene(), cameras()
    tensors = geometry_tensors(scene)
    drawn = [ColorOnlyRenderer(*tensors, c).seen for c in views]
    proxies = proxy_columns(tensors[0], tensors[2], views, drawn, sigma_px=0.5)
    fine, wide = proxies.column[:FINE], proxies.column[FINE:]
    assert proxies.grouped and proxies.count < 0.5 * len(scene)
    assert torch.bincount(proxies.column, minlength=proxies.count)[wide].eq(1).all()  # alone in their columns
    # A cell is about a pixel: members of one column lie within 1.8 px of each other in the nearest view (1.2 away).
    means = tensors[0][:FINE]
    for g in torch.unique(fine)[:50]:
        members = means[fine == g, :2]
        assert float((members.amax(0) - members.amin(0)).norm()) * 60.0 / 1.2 < 1.8
    assert proxy_columns(tensors[0], tensors[2], views, drawn, sigma_px=0.0).grouped is False
    # A scene whose splats are all wider than a pixel gets none.
    coarse = proxy_columns(tensors[0], tensors[2] + 3.0, views, drawn, sigma_px=0.5)
    assert not coarse.grouped and torch.equal(coarse.column, torch.arange(len(scene)))


def test_cells_are_grouped_as_their_rows_compare_whatever_their_range():
    g = torch.Generator().manual_seed(3)
    near = torch.randint(-40, 40, (5000, 4), generator=g) // 9
    far = near * (2**40)  # ranges too wide to ravel into one integer: compared row by row
    for key in (near, far):
        expected = torch.unique(key, dim=0, return_inverse=True)[1]
        assert torch.equal(_equal_rows(key), expected)


def test_every_member_takes_its_cells_colour_and_the_base_renders_stay_exact():
    scene, views = mixed_scene(), cameras()
    seen, fast = seen_gaussians(scene, views, RasterSettings(), geometry=False)
    exact = [f(torch.from_numpy(scene.base_colors)) for f in fast]  # before the renderer narrows and merges them
    renderer = ViewRenderer(scene, views, seen, RasterSettings(), False, fast, proxy_sigma=1.0)
    state = FitState.start(scene, seen, False, renderer.proxies)
    assert renderer.proxies is not None and state.colors.shape[0] == renderer.proxies.count
    assert state.splat_count == seen.numel()
    for image, reference in zip(renderer.base(state), exact):
        assert torch.allclose(image.permute(1, 2, 0), reference, atol=1e-5)
    with torch.no_grad():
        state.colors.copy_(torch.rand(state.colors.shape, generator=torch.Generator().manual_seed(3)))
    out = result_scene(scene, state, zero_sh_rest=True)
    index, column = state.members
    assert np.allclose(out.base_colors[index.numpy()], state.colors.detach()[column].numpy(), atol=1e-6)
    # The renders of the fit are those of the result: every member drawn in its cell's colour.
    after = seen_gaussians(out, views, RasterSettings(), geometry=False)[1]
    for v, f in enumerate(after):
        assert torch.allclose(f(torch.from_numpy(out.base_colors)), renderer(v, state).permute(1, 2, 0), atol=1e-5)


def test_a_run_with_proxies_colours_what_it_did_without_them():
    scene, views = mixed_scene(), cameras()
    style = np.random.default_rng(4).uniform(0, 1, (40, 56, 3)).astype(np.float32)
    runs = {}
    for sigma in (0.0, 1.0):
        config, plan = preset_run("preview", stages=1, proposal_width=64, proposal_height=48, proxy_sigma=sigma)
        runs[sigma] = stylize(scene, views, style, config, plan=plan, views=[0, 1, 2])
    with_, without = runs[1.0], runs[0.0]
    assert with_.log[0]["gaussians_optimised"] == without.log[0]["gaussians_optimised"]
    assert abs(with_.log[0]["base_style_distance"] - without.log[0]["base_style_distance"]) < 1e-6
    assert np.isfinite(with_.scene.sh_dc).all()
    # The views see the same picture: a fine splat's own colour is below what a pixel shows.
    for camera in views:
        a, b = render_scene(with_.scene, camera).rgb, render_scene(without.scene, camera).rgb
        assert float((a - b).abs().mean()) < 0.03, float((a - b).abs().mean())


def test_the_fit_takes_its_maps_from_the_selections_renders_and_draws_the_same():
    scene, views = mixed_scene(), cameras()
    style = np.random.default_rng(4).uniform(0, 1, (40, 56, 3)).astype(np.float32)
    config, plan = preset_run("preview", stages=1, proposal_width=64, proposal_height=48)
    chosen = stylize(scene, views, style, config, plan=plan)  # 3 cameras, up to 16 views: the selection's renders
    given = stylize(scene, views, style, config, plan=plan, views=chosen.selection.indices)  # rendered again
    assert np.array_equal(chosen.scene.sh_dc, given.scene.sh_dc)
