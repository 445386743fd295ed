"""Marks carried by the splats (method/marks.py): the synthesis's painting field, each splat's vote over its pixels,
the owner of each splat's marks, and the targets' fine band taken from the splats."""

from __future__ import annotations

import numpy as np
import torch

from dresg_addon.method.config import preset_run
from dresg_addon.method.loop import Stylization, stylize
from dresg_addon.method.marks import (
    CarriedMarks,
    Surfaces,
    ViewVote,
    carried_targets,
    emphasis_gains,
    emphasized,
    fine_band,
    first_views_fields,
    paint_view,
    painting_band_deviation,
    vote_view,
)
from dresg_addon.method.proposal.synth import (
    PaintingField,
    SynthBackend,
    _Matches,
    _nearest_centre,
    _PatchColors,
    cheapest_paths,
    low_pass,
    patch_grid,
    seam_cut,
)
from dresg_addon.method.schedule import stage_timesteps
from dresg_addon.raster.rasterizer import render_scene
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.gaussians import GaussianScene
from dresg_addon.scene.warp import warp_to

COARSE, FINE = stage_timesteps(12, 1)[0], stage_timesteps(12, 1)[-1]  # standard's first stage and its last


def painting(height: int = 60, width: int = 80, seed: int = 0) -> torch.Tensor:  # [3, H, W] strokes, not noise
    g = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.arange(height).float(), torch.arange(width).float(), indexing="ij")
    image = torch.zeros(3, height, width)
    for channel in range(3):
        angle, frequency = torch.rand(2, generator=g) * torch.tensor([3.14, 0.5]) + torch.tensor([0.0, 0.2])
        image[channel] = 0.5 + 0.5 * torch.sin(frequency * (x * torch.cos(angle) + y * torch.sin(angle)))
    return image


def test_the_field_points_at_the_painting_pixels_the_proposal_shows():
    style = painting(seed=1)
    content = style[:, 2:58, 5:77].clone()  # a piece of the painting: every patch has an exact match
    backend = SynthBackend(content_weight=0.0, histogram_matching=False, noise=0.0)
    proposal, _ = backend.propose(content, FINE, style, content)  # the last rung: full resolution
    field = backend.last_field
    assert field.rows.shape == (56, 72) and bool(field.valid.all())
    assert torch.equal(field.rows[:, 0], torch.arange(2, 58)) and torch.equal(field.cols[0], torch.arange(5, 77))
    assert (field.source[:, field.rows, field.cols] - proposal).abs().mean() < 0.01


def test_a_coarse_pass_gives_a_field_at_full_resolution_and_none_where_nothing_is_covered():
    style = painting(seed=1)
    content = painting(56, 72, seed=2)
    coverage = torch.ones(56, 72)
    coverage[:, :30] = 0.0
    backend = SynthBackend(coarsest_side=24, patch_sizes=(13, 9))
    backend.propose(content, COARSE, style, content, coverage)  # the first rung: the coarsest level
    field = backend.last_field
    assert backend._matched.level > 0
    assert field.rows.shape == (56, 72) and not bool(field.valid[:, :4].any()) and bool(field.valid[:, 40:].all())
    assert int(field.rows.max()) < 2 * style.shape[1] and int(field.cols.max()) < style.shape[2]
    assert int(field.rows.min()) >= 0 and int(field.cols.min()) >= 0


def test_the_cheapest_path_follows_the_valley_moves_one_column_a_row_and_keeps_out_of_barred_columns():
    valley = [4, 4, 5, 6, 6, 5, 5, 4]
    error = torch.rand(2, 8, 9, generator=torch.Generator().manual_seed(3)) + 0.5
    for row, column in enumerate(valley):
        error[0, row, column] = 0.0
    error[1] = 1.0  # flat: straight down its first column that is allowed
    error[1, :, :3] = torch.inf
    paths = cheapest_paths(error)
    assert paths[0].tolist() == valley and paths[1].tolist() == [3] * 8
    assert cheapest_paths(torch.zeros(1, 1, 1)).tolist() == [[0]]  # one row, one place


def two_patches(agree: list[int]) -> _Matches:
    """Two 8x8 patches side by side (corners at columns 0 and 4 of a 8x12 image) copying a random painting whose two
    copies agree in each row only at columns agree[row] and agree[row] + 1 of their overlap (4-7)."""
    source = torch.rand(3, 8, 40, generator=torch.Generator().manual_seed(4))
    for row, column in enumerate(agree):  # the second patch shows source column 16 + x at its pixel x
        source[:, row, 16 + column : 18 + column] = source[:, row, column : column + 2]
    flat = torch.cat([source, source.flip(-1)], 1).reshape(3, -1)
    ys, xs = torch.tensor([0]), torch.tensor([0, 4])
    return _Matches(
        0, 8, ys, xs, torch.ones(2, dtype=torch.bool), torch.tensor([0, 20]), 40, flat, torch.zeros(3, 8, 12)
    )


def test_the_seam_between_two_patches_runs_where_their_colours_agree_not_on_a_straight_line():
    agree = [4, 4, 5, 6, 6, 5, 5, 4]
    labels = seam_cut(two_patches(agree))
    columns = torch.arange(12)[None]
    expected = (columns >= torch.tensor(agree)[:, None] + 1).long()  # the first patch up to the agreeing pair
    assert torch.equal(labels, expected)


def assert_each_pixel_takes_a_patch_covering_it(labels, kept, ys, xs, size) -> torch.Tensor:  # -> [h, w] chosen
    grid = torch.nonzero(kept)[:, 0][labels.clamp_min(0)]
    top, left = ys[grid // xs.numel()], xs[grid % xs.numel()]
    y, x = torch.meshgrid(torch.arange(labels.shape[0]), torch.arange(labels.shape[1]), indexing="ij")
    chosen = labels >= 0
    assert bool(((top <= y) & (y < top + size) & (left <= x) & (x < left + size))[chosen].all())
    return chosen


def test_the_cut_gives_every_pixel_a_kept_patch_that_covers_it_on_any_grid():
    g = torch.Generator().manual_seed(5)
    for _ in range(60):
        size = int(torch.randint(1, 12, (1,), generator=g))
        h, w = (int(v) for v in torch.randint(size, 40, (2,), generator=g))
        gap = max(1, round(0.6 * size))
        ys, xs = patch_grid(h, w, size, gap, tuple(int(v) for v in torch.randint(0, gap, (2,), generator=g)))
        kept = torch.rand(ys.numel() * xs.numel(), generator=g) > 0.2
        source_h, source_w = h + 5, w + 7
        rows = torch.randint(0, 2 * source_h - size + 1, (int(kept.sum()),), generator=g)
        corners = rows * source_w + torch.randint(0, source_w - size + 1, rows.shape, generator=g)
        source = torch.rand(3, 2 * source_h * source_w, generator=g)
        matched = _Matches(0, size, ys, xs, kept, corners, source_w, source, torch.rand(3, h, w, generator=g))
        chosen = assert_each_pixel_takes_a_patch_covering_it(seam_cut(matched), kept, ys, xs, size)
        if bool(kept.all()):
            assert bool(chosen.all())


def test_every_pixel_takes_a_kept_patch_that_covers_it_and_the_cut_seams_cost_less_than_the_nearest_centres():
    style = painting(seed=1)
    content = painting(56, 72, seed=2)
    coverage = torch.ones(56, 72)
    coverage[:, :20] = 0.0
    backend = SynthBackend(patch_sizes=(13,), noise=0.0)
    backend.propose(content, FINE, style, content, coverage)
    matched = backend._matched
    labels = seam_cut(matched)
    kept = torch.nonzero(matched.kept)[:, 0]
    chosen = assert_each_pixel_takes_a_patch_covering_it(labels, matched.kept, matched.ys, matched.xs, 13)
    assert bool(chosen[:, 24:].all()) and not bool(chosen[:, :4].any())
    y, x = torch.meshgrid(torch.arange(56), torch.arange(72), indexing="ij")

    colors = _PatchColors(matched)

    def seam_cost(choice):  # Kwatra's cost summed over the field's seams
        total = 0.0
        for dy, dx in ((0, 1), (1, 0)):
            a, b = choice[: 56 - dy, : 72 - dx], choice[dy:, dx:]
            seam = (a != b) & (a >= 0) & (b >= 0)
            a, b = a.clamp_min(0), b.clamp_min(0)
            for yy, xx in ((y[: 56 - dy, : 72 - dx], x[: 56 - dy, : 72 - dx]), (y[dy:, dx:], x[dy:, dx:])):
                total += float(((colors.at(a, yy, xx) - colors.at(b, yy, xx)).norm(dim=0) * seam).sum())
        return total

    slot = torch.full((matched.kept.numel(),), -1, dtype=torch.long)
    slot[matched.kept] = torch.arange(kept.numel())
    rows, cols = _nearest_centre(matched.ys, 13, 56), _nearest_centre(matched.xs, 13, 72)
    nearest = slot[rows[:, None] * matched.xs.numel() + cols[None]]  # what the field took before the cut
    assert seam_cost(labels) < seam_cost(nearest)


def translation_field(height: int, width: int, source: torch.Tensor, shift: tuple[int, int]) -> PaintingField:
    y, x = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    rows = (y + shift[0]).clamp(0, source.shape[1] - 1)
    cols = (x + shift[1]).clamp(0, source.shape[2] - 1)
    return PaintingField(rows, cols, torch.ones(height, width, dtype=torch.bool), source)


def test_each_splat_takes_the_translation_most_of_its_weight_votes_for_not_the_mean():
    source = torch.rand(3, 40, 40, generator=torch.Generator().manual_seed(0))
    field = translation_field(10, 10, source, (3, 5))
    field.rows[:, :4] = (field.rows[:, :4] + 9).clamp_max(39)  # the left columns copy from 9 rows lower
    # Splat 0 lies on the right (one translation); splat 1 has 0.7 of its weight on the left, 0.3 on the right.
    pixel = torch.tensor([16, 17, 27, 20, 21, 26])
    splat = torch.tensor([0, 0, 0, 1, 1, 1])
    weight = torch.tensor([0.5, 0.2, 0.3, 0.4, 0.3, 0.3])
    vote = vote_view((pixel, splat, weight), (10, 10), field, 3)
    assert torch.allclose(vote.agreed, torch.tensor([1.0, 0.7, 0.0]))
    # Each centre (the weighted mean of its pixels) moved by its mode translation: (3, 5) and (12, 5).
    centres = torch.tensor([[1.3, 6.5], [2.0, 2.1]], dtype=torch.float64)
    assert torch.allclose(
        vote.coordinates[:2].double(), centres + torch.tensor([[3.0, 5.0], [12.0, 5.0]], dtype=torch.float64)
    )


def test_a_field_at_half_the_fit_size_votes_by_the_proposal_pixel():
    source = torch.rand(3, 30, 30, generator=torch.Generator().manual_seed(1))
    field = translation_field(5, 5, source, (2, 2))  # the proposal at 5x5, the render at 10x10
    vote = vote_view((torch.tensor([99]), torch.tensor([0]), torch.tensor([1.0])), (10, 10), field, 1)
    # Fit pixel (9, 9) is proposal pixel 4.25 (centres: (9 + 0.5) / 2 - 0.5), moved by (2, 2).
    assert torch.allclose(vote.coordinates[0].double(), torch.tensor([6.25, 6.25], dtype=torch.float64))


def test_each_view_is_painted_as_the_splats_carry_the_painting_so_its_strokes_follow_the_surface():
    source = torch.rand(3, 40, 20, generator=torch.Generator().manual_seed(2))  # a painting 20x20 and its mirror
    # Four splats a pixel each, at (1, 1), (1, 2), (2, 1), (2, 2) in view A and three pixels to the right in view B.
    splat = torch.arange(4)
    in_a = torch.tensor([11, 12, 21, 22])
    marks = CarriedMarks(torch.tensor([[5.0, 5.0], [5.0, 6.0], [6.0, 5.0], [6.0, 6.0]], dtype=torch.float64), splat)
    one = torch.ones(4)
    image_a, painted_a = paint_view((in_a, splat, one), (10, 10), (10, 10), marks, source)
    image_b, painted_b = paint_view((in_a + 3, splat, one), (10, 10), (10, 10), marks, source)
    assert painted_a.sum() == 4 and torch.equal(painted_b.reshape(-1).nonzero()[:, 0], in_a + 3)
    assert torch.equal(image_a[:, 1:3, 1:3], source[:, 5:7, 5:7])
    assert torch.equal(image_b[:, 1:3, 4:6], image_a[:, 1:3, 1:3])
    # A splat drawn over several pixels paints the painting around its coordinate, not one colour.
    wide, painted = paint_view(
        (torch.tensor([0, 1, 2]), torch.zeros(3, dtype=torch.long), one[:3]),
        (1, 3),
        (1, 3),
        CarriedMarks(torch.tensor([[3.0, 8.0]], dtype=torch.float64), torch.tensor([0])),
        source,
    )
    assert torch.equal(wide[:, 0], source[:, 3, 7:10])
    # A coordinate in the mirror image (the lower half) stays in it: the pixel above the centre would be row 19.
    mirror = CarriedMarks(torch.tensor([[20.0, 5.0]], dtype=torch.float64), torch.tensor([0]))
    three = (torch.arange(3), torch.zeros(3, dtype=torch.long), one[:3])
    column, _ = paint_view(three, (3, 1), (3, 1), mirror, source)
    assert torch.equal(column[:, :, 0], source[:, [20, 20, 21], 5])


def plane_view(camera: Camera, block: int, owner: Camera):
    """A view of the z = 0 plane: its depth [H, W] and each pixel's splat, the ``block`` x ``block`` square of the
    owner's pixels its point falls in (the splats the owner sees at ``block`` pixels)."""
    c2w = camera.camera_to_world
    v, u = np.meshgrid(np.arange(camera.height) + 0.5, np.arange(camera.width) + 0.5, indexing="ij")
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1) @ c2w[:3, :3].T
    t = -c2w[2, 3] / rays[..., 2]  # camera-space z of the plane, as the ray's camera z is 1
    points = c2w[:3, 3] + t[..., None] * rays
    seen = points @ owner.world_to_camera[:3, :3].T + owner.world_to_camera[:3, 3]
    uo = owner.fx * seen[..., 0] / seen[..., 2] + owner.cx
    vo = owner.fy * seen[..., 1] / seen[..., 2] + owner.cy
    splat = (np.floor(vo / block) * (owner.width // block) + np.floor(uo / block)).astype(np.int64).ravel()
    inside = ((uo >= 0) & (uo < owner.width) & (vo >= 0) & (vo < owner.height)).ravel()  # the plane's splats
    pixel = torch.from_numpy(np.nonzero(inside)[0])
    contributions = (pixel, torch.from_numpy(splat[inside]), torch.ones(pixel.numel()))
    return torch.from_numpy(t).float(), contributions


def carried_plane(block: int = 4):
    """The plane's owner view from above (the first) and a view tilted towards it and closer; the owner's field a
    translation into a painting whose colour is its own (row, column), so an image painted from it says where each
    pixel is."""
    owner = Camera(32, 32, 32.0, 32.0, 16.0, 16.0, look_at([0, 0, 1.0], [0, 0, 0]), "owner")
    tilted = Camera(32, 32, 32.0, 32.0, 16.0, 16.0, look_at([0.35, 0.1, 0.6], [0, 0, 0]), "tilted")
    rows, cols = torch.meshgrid(torch.arange(80.0), torch.arange(40.0), indexing="ij")
    source = torch.stack([rows, cols, torch.zeros_like(rows)])  # [3, 2 x 40, 40]: the painting and its mirror
    field = translation_field(32, 32, source, (3, 4))
    depth_o, in_o = plane_view(owner, block, owner)
    depth_t, in_t = plane_view(tilted, block, owner)
    splats = (32 // block) ** 2
    vote = vote_view(in_o, (32, 32), field, splats)
    marks = CarriedMarks.from_votes([vote, ViewVote(torch.zeros(splats, 2, dtype=torch.float64), torch.zeros(splats))])
    surfaces = Surfaces([owner, tilted], [depth_o, depth_t], [field, field])
    return marks, source, surfaces, in_t


def test_a_stroke_the_owner_paints_runs_on_in_a_tilted_view_where_a_translation_per_splat_cuts_it():
    marks, source, surfaces, in_t = carried_plane()
    assert marks.owner.max() == 0
    by_splat, painted = paint_view(in_t, (32, 32), (32, 32), marks, source)
    by_depth, painted_too = paint_view(in_t, (32, 32), (32, 32), marks, source, 1, surfaces)
    assert torch.equal(painted, painted_too) and torch.isfinite(by_depth).all()
    inner = (slice(8, 24), slice(8, 24))  # well inside the plane
    # The tilted view is closer: a painting pixel spans more than one of its pixels, so along a row or a column the
    # owner's strokes advance and never step back; a translation per splat steps back at every splat's border.
    for image, axis in ((by_depth[1][inner], 1), (by_depth[0][inner], 0)):
        assert (image.diff(dim=axis) >= 0).all()
    steps_back = [int((by_splat[1 - axis][inner].diff(dim=axis) < 0).sum()) for axis in (0, 1)]
    assert sum(steps_back) >= 30, steps_back  # of 480 steps
    # Each pixel takes the owner's field at its point: the owner pixel it falls in, moved by (3, 4).
    rows, cols, found = first_views_fields(1, torch.arange(32 * 32), surfaces)
    assert found.reshape(32, 32)[inner].all()
    assert torch.equal(rows.reshape(32, 32)[inner].float(), by_depth[0][inner])
    # In the owner itself it is its own field: the painting the owner's proposal shows.
    _, in_o = plane_view(surfaces.cameras[0], 4, surfaces.cameras[0])
    own, _ = paint_view(in_o, (32, 32), (32, 32), marks, source, 0, surfaces)
    assert torch.equal(own[0], surfaces.fields[0].rows.float()) and torch.equal(own[1], surfaces.fields[0].cols.float())


def test_a_point_the_first_view_does_not_see_takes_the_next_views_field_and_else_its_splats_translation():
    marks, source, surfaces, in_t = carried_plane()
    by_splat, _ = paint_view(in_t, (32, 32), (32, 32), marks, source)
    (top, tilted), (field, _) = surfaces.cameras, surfaces.fields
    depth_o, depth_t = surfaces.depths[0].clone(), surfaces.depths[1].clone()
    depth_t[:4] = 0.0  # no depth: nothing to unproject
    depth_o[:, :10] *= 0.5  # something nearer hides the plane from the first view there
    blank = PaintingField(field.rows, field.cols, torch.zeros(32, 32, dtype=torch.bool), source)  # covered nothing
    pixels = torch.arange(32 * 32)
    cut = Surfaces([top, tilted], [depth_o, depth_t], [field, blank])
    _, _, first = first_views_fields(1, pixels, cut)
    first = first.reshape(32, 32)
    assert not first[:4].any() and first[8:16, 20:28].all() and not first[8:24, 2:6].any()
    image, _ = paint_view(in_t, (32, 32), (32, 32), marks, source, 1, cut)
    assert torch.isfinite(image).all() and torch.equal(image[:, ~first], by_splat[:, ~first])
    # With a field of its own, the tilted view paints what the first view hides from its own copy of the painting.
    own = translation_field(32, 32, source, (20, 10))
    rows, cols, found = first_views_fields(1, pixels, Surfaces([top, tilted], [depth_o, depth_t], [field, own]))
    rows, cols, found = rows.reshape(32, 32), cols.reshape(32, 32), found.reshape(32, 32)
    assert torch.equal(found, depth_t > 0)
    hidden = found & ~first
    assert torch.equal(rows[hidden], own.rows[hidden]) and torch.equal(cols[hidden], own.cols[hidden])
    # A point behind a view: a camera beyond the plane's back looking away from it sees none of it.
    away = Camera(32, 32, 32.0, 32.0, 16.0, 16.0, look_at([0, 0, -1.0], [0, 0, -2.0]), "away")
    behind = Surfaces([away, tilted], [torch.ones(32, 32), depth_t], [field, blank])
    rows, cols, found = first_views_fields(1, pixels, behind)
    assert not found.any() and rows.eq(0).all() and cols.eq(0).all()
    image, _ = paint_view(in_t, (32, 32), (32, 32), marks, source, 1, behind)
    assert torch.equal(image, by_splat)


def test_owners_take_whole_surfaces_in_turn_and_unvoted_splats_have_none():
    coordinates = [torch.full((4, 2), 10.0 * v, dtype=torch.float64) for v in range(3)]
    agreed = [torch.tensor([1.0, 0.2, 0.0, 0.0]), torch.tensor([1.5, 1.0, 0.0, 0.0]), torch.tensor([0.1, 0.4, 2.0, 0])]
    marks = CarriedMarks.from_votes([ViewVote(c, a) for c, a in zip(coordinates, agreed)], share=0.5)
    assert marks.owner.tolist() == [0, 1, 2, -1]
    assert marks.coordinates[:3, 0].tolist() == [0.0, 10.0, 20.0]
    assert marks.carried.tolist() == [True, True, True, False]


def test_targets_keep_their_coarse_bands_and_take_the_splats_fine_band_on_covered_pixels():
    g = torch.Generator().manual_seed(3)
    ramp = torch.linspace(0.3, 0.7, 40)
    target = torch.stack(
        [ramp[None, :].expand(40, 40), ramp[:, None].expand(40, 40), 1.0 - ramp[None, :].expand(40, 40)]
    )
    marks = (torch.rand(3, 40, 40, generator=g) - 0.5) * 0.2 + 0.5
    alpha = torch.ones(40, 40)
    alpha[:, :8] = 0.0  # the background keeps its target
    (out,) = carried_targets([target], [marks], [alpha], sigma=3.0)
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    assert torch.equal(out[:, :, :8], target[:, :, :8])
    inner = (slice(None), slice(10, 30), slice(18, 32))  # away from the borders, where the blurs are cut

    def correlation(a, b):
        a, b = a[inner].flatten() - a[inner].mean(), b[inner].flatten() - b[inner].mean()
        return float((a * b).sum() / (a.norm() * b.norm()))

    assert correlation(fine_band(out, alpha, 3.0), fine_band(marks, alpha, 3.0)) > 0.9
    assert correlation(out - fine_band(out, alpha, 3.0), target - fine_band(target, alpha, 3.0)) > 0.95
    same, *_ = carried_targets([target], [target], [alpha], sigma=3.0)
    assert torch.allclose(same, target, atol=1e-5)


def marks_on_grey(seed: int = 4, size: int = 40) -> torch.Tensor:  # [3, H, W]: fine marks around mid grey
    g = torch.Generator().manual_seed(seed)
    return (0.5 + 0.15 * (torch.rand(1, size, size, generator=g) - 0.5)).expand(3, size, size).clone()


def test_a_fit_that_drew_half_of_the_marks_asks_for_them_twice_as_strong_up_to_the_painting():
    target, alpha = marks_on_grey(), torch.ones(40, 40)
    half = target - 0.5 * fine_band(target, alpha, 1.5)  # the fit drew half the band
    asked = float(fine_band(target, alpha, 1.5).std())
    (gain,) = emphasis_gains([target], [half], [alpha], 1.5, asked, most=4.0)
    assert abs(gain - 1.0) < 0.1  # about half: the blur of a band is not quite nothing
    (capped,) = emphasis_gains([target], [half], [alpha], 1.5, asked, most=0.5)
    assert capped == 0.5
    # the target already twice as strong as the painting: what the fit drew (its band equal to the painting's) is enough
    (strong,) = emphasis_gains([target], [half], [alpha], 1.5, asked / 2, most=4.0)
    assert strong == 0.0
    # drawn whole, nothing more is asked; a flat target, an empty view and a flat painting ask for nothing either
    flat = torch.full((3, 40, 40), 0.5)
    assert emphasis_gains([target], [target], [alpha], 1.5, asked, most=4.0) == [0.0]
    assert emphasis_gains([flat], [flat], [alpha], 1.5, asked, most=4.0) == [0.0]
    assert emphasis_gains([target], [half], [torch.zeros(40, 40)], 1.5, asked, most=4.0) == [0.0]
    assert emphasis_gains([target], [half], [alpha], 1.5, 0.0, most=4.0) == [0.0]
    assert emphasis_gains([target], [torch.full_like(target, float("nan"))], [alpha], 1.5, asked, most=4.0) == [0.0]


def test_emphasis_strengthens_the_fine_band_on_covered_pixels_only_and_stays_in_range():
    target, alpha = marks_on_grey(), torch.ones(40, 40)
    alpha[:, :10] = 0.0
    (out,) = emphasized([target], [alpha], [1.0], 1.5)
    assert torch.equal(out[:, :, :10], target[:, :, :10])
    inner = (slice(None), slice(8, 32), slice(18, 32))
    assert float(fine_band(out, alpha, 1.5)[inner].std()) > 1.8 * float(fine_band(target, alpha, 1.5)[inner].std())
    (saturated,) = emphasized([torch.where(target > 0.5, 1.0, 0.0)], [alpha], [4.0], 1.5)
    assert saturated.min() >= 0 and saturated.max() <= 1
    (flat,) = emphasized([torch.full((3, 40, 40), 0.3)], [alpha], [2.0], 1.5)
    assert torch.allclose(flat, torch.full((3, 40, 40), 0.3), atol=1e-6)
    assert painting_band_deviation(target, 1.5) > 0 and painting_band_deviation(torch.zeros(3, 8, 8), 1.5) == 0


# --- Through the loop: a plane seen by three views --------------------------------------------------------


def plane_scene(side: int = 72, spacing: float = 1.0 / 72) -> GaussianScene:
    """A flat grey square of splats finer than the marks (about a pixel in the views below), in the z = 0 plane."""
    grid = (np.arange(side) - (side - 1) / 2) * spacing
    x, y = np.meshgrid(grid, grid)
    count = side * side
    means = np.stack([x.ravel(), y.ravel(), np.zeros(count)], 1).astype(np.float32)
    scales = np.log(np.array([spacing * 0.6, spacing * 0.6, spacing * 0.05], np.float32))
    return GaussianScene(
        means=means,
        log_scales=np.broadcast_to(scales, (count, 3)).copy(),
        quats=np.tile(np.float32([1, 0, 0, 0]), (count, 1)),
        opacity_logits=np.full(count, 3.0, np.float32),
        sh_dc=np.zeros((count, 3), np.float32),
    )


def plane_cameras(width: int = 64, height: int = 48) -> list[Camera]:
    """Three views of the plane from above, a little apart: each sees it whole, at about a splat a pixel."""
    cameras = []
    for k, offset in enumerate((-0.25, 0.0, 0.25)):
        eye = np.array([offset, 0.1 * k - 0.1, 1.2])
        cameras.append(Camera(width, height, 60.0, 60.0, width / 2, height / 2, look_at(eye, [0, 0, 0]), f"top_{k}"))
    return cameras


def stroke_painting(height: int = 48, width: int = 64) -> np.ndarray:
    """Short dark and light diagonal strokes on a mid ground: marks a blend of misplaced copies turns grey."""
    rng = np.random.default_rng(5)
    canvas = np.full((height, width, 3), 0.5, np.float32)
    for _ in range(90):
        y, x = rng.integers(0, height), rng.integers(0, width)
        colour = rng.choice([0.05, 0.95]) * np.ones(3) + rng.normal(0, 0.05, 3)
        for t in range(-4, 5):
            canvas[(y + t) % height, (x + t) % width] = colour
            canvas[(y + t) % height, (x + t + 1) % width] = colour
    return np.clip(canvas, 0, 1)


def stylized_plane(carry: bool, scene: GaussianScene | None = None, messages=None, **plan):
    """The plane stylized from its three views; each view's last images (render, proposal, marks, target) by name."""
    images = {}

    def on_stage(update):
        images.update(update.images)

    settings = {"stages": 1, "updates_per_stage": 12, "proposal_width": 64, "proposal_height": 48, "stroke_size": 1.0}
    config, plan = preset_run("preview", **{**settings, "carry_marks": carry, **plan})
    cameras = plane_cameras()
    scene = plane_scene() if scene is None else scene
    result = stylize(
        scene, cameras, stroke_painting(), config, plan=plan, views=[0, 1, 2], on_stage=on_stage, messages=messages
    )
    return result, cameras, [images[c.name] for c in cameras]


def warp_correlation(images, cameras, depths, alphas) -> float:
    """How well marks line up on the surface across views: the correlation of each view's band between 1 and 3 px
    with its neighbour's image warped into it by depth, the mean over the pairs (1: the same marks in the same
    places; the views of one scene reach about 0.7 here, the warp's resampling costs the rest)."""

    def band(image, valid):  # [H, W, 3] -> [H, W, 3], a difference of blurs over the valid pixels
        x, w = image.permute(2, 0, 1), valid.float()[None]
        blurs = [low_pass(x * w, s) / low_pass(w, s).clamp_min(1e-4) for s in (1.0, 3.0)]
        return (blurs[0] - blurs[1]).permute(1, 2, 0)

    values = []
    for i, j in ((0, 1), (1, 2)):
        warped, valid = warp_to(images[i], depths[i], cameras[i], cameras[j], depths[j], alphas[i], alphas[j])
        a, b = band(warped, valid)[valid], band(images[j], valid)[valid]
        a, b = a - a.mean(), b - b.mean()
        values.append(float((a * b).sum() / (a.norm() * b.norm())))
    return float(np.mean(values))


def test_strokes_through_the_splats_coordinates_line_up_across_views_where_per_view_strokes_do_not(monkeypatch):
    # Each view synthesized on its own: no guide from the views before it (which makes views agree another way).
    monkeypatch.setattr(Stylization, "guided", lambda self: False)
    result, cameras, images = stylized_plane(carry=True)
    renders = [render_scene(result.scene, c) for c in cameras]
    depths = [torch.as_tensor(r.depth).float() for r in renders]
    alphas = [torch.as_tensor(r.alpha).float() for r in renders]

    def agreement(kind: str) -> float:
        return warp_correlation([torch.as_tensor(v[kind]).float() for v in images], cameras, depths, alphas)

    # One stage: each view's synthesis places its strokes in its own places (nothing fed back yet to agree on); painted
    # through the splats' coordinates, the same strokes sit on the same surface in every view.
    proposals, marks = agreement("proposal"), agreement("marks")
    assert proposals < 0.2 and marks > 0.5, (proposals, marks)
    assert agreement_of_renders(renders, cameras, depths, alphas) > 0.6  # the scene's own views: the warp's ceiling


def test_on_splats_wider_than_the_marks_the_fit_asks_again_for_what_it_lost_and_draws_stronger_marks():
    wide = plane_scene(side=36, spacing=2.0 / 72)  # splats about 2 px in these views: they draw a share of the marks
    said = []
    plain, cameras, _ = stylized_plane(True, wide)
    stronger, _, _ = stylized_plane(True, wide, said.append, marks_emphasis=1.5)
    assert any(line.startswith("marks emphasised") for line in said), said
    assert np.isfinite(stronger.scene.sh_dc).all()

    def band(result) -> float:  # the renders' band finer than the children's width, over the covered pixels
        values = []
        for camera in cameras:
            out = render_scene(result.scene, camera)
            image, alpha = torch.as_tensor(out.rgb).permute(2, 0, 1).float(), torch.as_tensor(out.alpha).float()
            values.append(float(fine_band(image, alpha, 2.0)[:, alpha > 0.9].std()))
        return float(np.mean(values))

    assert band(stronger) > 1.08 * band(plain), (band(stronger), band(plain))  # 1.14 when written


def agreement_of_renders(renders, cameras, depths, alphas) -> float:
    return warp_correlation([torch.as_tensor(r.rgb).float() for r in renders], cameras, depths, alphas)


def test_a_view_worked_on_a_slice_of_samples_at_a_time_votes_and_paints_the_same(monkeypatch):
    from dresg_addon.method import marks as module

    marks, source, surfaces, in_t = carried_plane(block=2)
    field = surfaces.fields[0]
    splats = marks.owner.numel()
    whole = vote_view(in_t, (32, 32), field, splats), paint_view(in_t, (32, 32), (32, 32), marks, source, 1, surfaces)
    monkeypatch.setattr(module, "SAMPLES_AT_ONCE", 37)  # ranges of splats for the vote, slices for the rest
    sliced = vote_view(in_t, (32, 32), field, splats), paint_view(in_t, (32, 32), (32, 32), marks, source, 1, surfaces)
    assert torch.equal(whole[0].agreed, sliced[0].agreed) and whole[0].agreed.gt(0).sum() > 100
    torch.testing.assert_close(whole[0].coordinates, sliced[0].coordinates, rtol=0, atol=1e-9)
    assert torch.equal(whole[1][0], sliced[1][0]) and torch.equal(whole[1][1], sliced[1][1])


def test_only_the_last_stage_is_fitted_a_second_time():
    # Earlier stages are fitted once: their style distances decide the early stop, and a second fit's gain would read
    # as progress and run stages more.
    said = []
    wide = plane_scene(side=36, spacing=2.0 / 72)
    stylized_plane(True, wide, said.append, stages=3, marks_emphasis=1.5)
    carried = [line for line in said if line.startswith("marks carried by")]
    emphasised = [i for i, line in enumerate(said) if line.startswith("marks emphasised")]
    assert len(carried) >= 2 and len(emphasised) == 1, said
    assert emphasised[0] > max(i for i, line in enumerate(said) if line.startswith("marks carried by")), said
