"""The bounded least-squares colour fit (method/color_solve.py) against dense solutions, and its stiff cases."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from test_pipeline import away_camera, ring_cameras, sphere_scene

from dresg_addon.method.color_solve import (
    ColorSolveSettings,
    LinearViews,
    covered_rmse,
    projected_solve,
    solve_colors,
)
from dresg_addon.method.medium import Ink
from dresg_addon.raster import ColorOnlyRenderer, geometry_tensors
from dresg_addon.scene.gaussians import GaussianScene
from dresg_addon.util.errors import ConfigError, NumericalError


def concatenate(a: GaussianScene, b: GaussianScene) -> GaussianScene:
    names = ("means", "log_scales", "quats", "opacity_logits", "sh_dc")
    return GaussianScene(**{name: np.concatenate([getattr(a, name), getattr(b, name)]) for name in names})


def linear_views(scene, cameras) -> LinearViews:
    renderers = [ColorOnlyRenderer(*geometry_tensors(scene), camera) for camera in cameras]
    return LinearViews([r.linear_map() for r in renderers], [r.background for r in renderers])


def dense(views: LinearViews) -> torch.Tensor:  # [sum P, N] float64: every view's W stacked
    n = views.energy.numel()
    eye = torch.eye(n)
    return torch.cat([torch.cat([m.matvec(eye[:, k : k + 1]) for k in range(n)], 1) for m in views.maps]).double()


def objective(views: LinearViews, colors: torch.Tensor, targets) -> float:
    return sum(float((img - t).double().square().sum()) for img, t in zip(views.images(colors), targets))


def dense_box_optimum(matrix: torch.Tensor, rhs: torch.Tensor, iterations: int = 20000) -> torch.Tensor:
    """min ||A x - b||^2 over x in [0, 1] by accelerated projected gradient (FISTA) on the dense matrix."""
    lipschitz = float(torch.linalg.matrix_norm(matrix, 2)) ** 2
    x = torch.full((matrix.shape[1], rhs.shape[1]), 0.5, dtype=torch.float64)
    y, t = x.clone(), 1.0
    for _ in range(iterations):
        x_next = (y - matrix.T @ (matrix @ y - rhs) / lipschitz).clamp(0.0, 1.0)
        t_next = (1 + math.sqrt(1 + 4 * t * t)) / 2
        y = x_next + (t - 1) / t_next * (x_next - x)
        x, t = x_next, t_next
    return x


@pytest.fixture(scope="module")
def small():
    """80 splats on a sphere seen by three 24x16 cameras: small enough for dense solutions."""
    scene = sphere_scene(n=80, seed=3)
    views = linear_views(scene, ring_cameras(3, width=24, height=16))
    return scene, views


def test_targets_a_scene_can_show_are_reached_as_the_dense_least_squares_solution_does(small):
    _, views = small
    truth = torch.from_numpy(np.random.default_rng(0).uniform(0.2, 0.8, (80, 3)).astype(np.float32))
    targets = views.images(truth)  # exactly representable, inside the box
    matrix = dense(views)
    rhs = torch.cat([t - b for t, b in zip(targets, views.constants)]).double()
    exact = torch.linalg.lstsq(matrix, rhs).solution
    start = torch.full((80, 3), 0.5)
    result = solve_colors(views, targets, start, ColorSolveSettings(tolerance=1e-6, max_rounds=40, cg_iterations=20))
    reached = objective(views, result.colors, targets)
    optimum = float((matrix @ exact - rhs).square().sum())
    assert reached <= optimum + 1e-6 * objective(views, start, targets)
    # Splats the views see well get their colour back.
    seen = views.energy > 0.2 * float(views.energy.max())
    torch.testing.assert_close(result.colors[seen], truth[seen], atol=0.02, rtol=0)


def test_targets_outside_what_the_box_allows_reach_the_bounded_optimum(small):
    _, views = small
    rng = np.random.default_rng(1)
    targets = [torch.from_numpy(rng.uniform(0, 1, (t.shape[0], 3)).astype(np.float32)) for t in views.constants]
    matrix = dense(views)
    rhs = torch.cat([t - b for t, b in zip(targets, views.constants)]).double()
    reference = dense_box_optimum(matrix, rhs)
    optimum = float((matrix @ reference - rhs).square().sum())
    result = solve_colors(views, targets, torch.full((80, 3), 0.5), ColorSolveSettings(tolerance=1e-5, max_rounds=60))
    assert result.colors.min() >= 0 and result.colors.max() <= 1
    assert objective(views, result.colors, targets) <= 1.01 * optimum
    # Unbounded least squares would leave the box: the bounds are what makes this optimum.
    unbounded = torch.linalg.lstsq(matrix, rhs).solution
    assert unbounded.min() < 0 or unbounded.max() > 1


def test_the_objective_never_rises_and_the_solve_stops_at_its_tolerance(small):
    _, views = small
    rng = np.random.default_rng(2)
    targets = [torch.from_numpy(rng.uniform(0, 1, (t.shape[0], 3)).astype(np.float32)) for t in views.constants]
    settings = ColorSolveSettings(tolerance=0.01, max_rounds=50)
    result = solve_colors(views, targets, torch.full((80, 3), 0.5), settings)
    values = result.objectives
    assert all(b <= a for a, b in zip(values, values[1:]))
    assert len(values) - 1 < settings.max_rounds  # stopped by the tolerance, not the cap
    assert values[-2] - values[-1] <= settings.tolerance * values[-1]
    assert values[-1] == pytest.approx(objective(views, result.colors, targets), rel=1e-5)


def test_each_round_gets_its_colours_residuals_and_their_covered_rmse_is_the_renders(small):
    _, views = small
    rng = np.random.default_rng(4)
    targets = [torch.from_numpy(rng.uniform(0, 1, (t.shape[0], 3)).astype(np.float32)) for t in views.constants]
    covered = [coverage[:, 0] > 0.5 for coverage in views.coverages]
    seen = []

    def each_round(index, value, colors, residuals):
        images = views.images(colors)
        for image, target, residual in zip(images, targets, residuals):
            assert torch.allclose(residual, image - target, atol=1e-5)
        masked = torch.cat([(image - target)[mask] for image, target, mask in zip(images, targets, covered)])
        seen.append((covered_rmse(residuals, covered), float(masked.double().square().mean().sqrt())))

    solve_colors(views, targets, torch.full((80, 3), 0.5), ColorSolveSettings(max_rounds=3), each_round)
    assert seen and all(ours == pytest.approx(truth, rel=1e-5) for ours, truth in seen)
    assert covered_rmse(residuals=[torch.ones(4, 3)], covered=[torch.zeros(4, dtype=torch.bool)]) == 0.0


def test_more_iterations_fit_closer(small):
    _, views = small
    truth = torch.from_numpy(np.random.default_rng(4).uniform(0, 1, (80, 3)).astype(np.float32))
    targets = views.images(truth)
    reached = []
    for rounds, iterations in ((1, 1), (1, 4), (3, 4), (10, 8)):
        settings = ColorSolveSettings(tolerance=1e-9, max_rounds=rounds, cg_iterations=iterations)
        reached.append(
            objective(views, solve_colors(views, targets, torch.full((80, 3), 0.5), settings).colors, targets)
        )
    assert all(b <= a * (1 + 1e-6) for a, b in zip(reached, reached[1:])) and reached[-1] < 0.9 * reached[0]


def test_a_solve_is_deterministic(small):
    _, views = small
    targets = [torch.rand(t.shape[0], 3, generator=torch.Generator().manual_seed(5)) for t in views.constants]
    a = solve_colors(views, targets, torch.full((80, 3), 0.3))
    b = solve_colors(views, targets, torch.full((80, 3), 0.3))
    assert torch.equal(a.colors, b.colors) and a.objectives == b.objectives


def test_stiff_cases_stay_finite_in_the_box():
    scene = sphere_scene(n=60, seed=6)
    # A view that sees nothing, and a splat that one pixel barely sees (far out on the image's edge).
    cameras = [*ring_cameras(2, width=24, height=16), away_camera(24, 16)]
    views = linear_views(scene, cameras)
    assert float(views.maps[2].column_energy().sum()) == 0.0
    start = torch.rand(60, 3, generator=torch.Generator().manual_seed(7))
    for fill in (0.0, 0.5, 1.0):  # flat targets, at the bounds and between
        targets = [torch.full((t.shape[0], 3), fill) for t in views.constants]
        result = solve_colors(views, targets, start)
        assert torch.isfinite(result.colors).all() and result.colors.min() >= 0 and result.colors.max() <= 1
        assert all(math.isfinite(v) for v in result.objectives)
    # A tiny, faint splat in front of the sphere: one pixel, alpha a few percent.
    speck = replace(
        sphere_scene(n=1),
        means=np.float32([[0.0, -0.35, -1.2]]),
        log_scales=np.full((1, 3), math.log(1e-4), np.float32),
        opacity_logits=np.float32([-3.0]),
    )
    far = replace(speck, means=np.float32([[0.0, 30.0, 0.0]]))  # behind the camera: nothing sees it
    views = linear_views(concatenate(concatenate(scene, speck), far), cameras[:1])
    energy = views.energy
    assert 0 < float(energy[-2]) < 1e-3 * float(energy.max()) and float(energy[-1]) == 0
    start = torch.rand(62, 3, generator=torch.Generator().manual_seed(8))
    targets = [torch.ones(views.constants[0].shape[0], 3)]
    result = solve_colors(views, targets, start)
    assert torch.isfinite(result.colors).all() and result.colors.min() >= 0 and result.colors.max() <= 1
    untouched = views.energy == 0
    assert untouched.any() and torch.equal(result.colors[untouched], start[untouched])  # unseen: kept


def test_non_finite_targets_and_bad_settings_are_refused(small):
    _, views = small
    targets = [torch.zeros(t.shape[0], 3) for t in views.constants]
    targets[1][3, 0] = float("nan")
    with pytest.raises(NumericalError, match="non-finite"):
        solve_colors(views, targets, torch.zeros(80, 3))
    for bad in ({"tolerance": 0.0}, {"ridge": -1.0}, {"max_rounds": 0}, {"anchor": -1.0}):
        with pytest.raises(ConfigError, match="colour solver"):
            ColorSolveSettings(**bad)


@pytest.mark.slow
def test_an_anchored_solve_reaches_the_dense_proximal_optimum_and_keeps_what_the_views_barely_see(small):
    """min ||A x - b||^2 + mu e_bar ||x - x0||^2 over the box, against FISTA on the stacked dense problem."""
    _, views = small
    rng = np.random.default_rng(9)
    targets = [torch.from_numpy(rng.uniform(0, 1, (t.shape[0], 3)).astype(np.float32)) for t in views.constants]
    start = torch.from_numpy(rng.uniform(0, 1, (80, 3)).astype(np.float32))
    mu = 1.0
    weight = mu * float(views.energy.mean())
    matrix = dense(views)
    rhs = torch.cat([t - b for t, b in zip(targets, views.constants)]).double()
    stacked = torch.cat([matrix, math.sqrt(weight) * torch.eye(80, dtype=torch.float64)])
    reference = dense_box_optimum(stacked, torch.cat([rhs, math.sqrt(weight) * start.double()]))

    def anchored(colors):
        return objective(views, colors, targets) + weight * float((colors.double() - start.double()).square().sum())

    settings = ColorSolveSettings(tolerance=1e-6, max_rounds=40, anchor=mu)
    result = solve_colors(views, targets, start, settings)
    assert anchored(result.colors) <= 1.001 * anchored(reference.float())
    # A splat the views see a twentieth as much as the average one hardly moves; the best-seen ones move most.
    faint, bright = views.energy < 0.05 * views.energy.mean(), views.energy > 2 * views.energy.mean()
    assert faint.any() and bright.any()
    moved = (result.colors - start).abs().sum(1)
    assert float(moved[faint].max()) < 0.1 < float(moved[bright].mean())
    # The plain optimum fits the views closer than the anchored fit.
    plain = solve_colors(views, targets, start, replace(settings, anchor=0.0))
    assert objective(views, plain.colors, targets) <= objective(views, result.colors, targets)
    # Stiff: an anchor a million times the views' weight keeps every colour, finite.
    held = solve_colors(views, targets, start, replace(settings, anchor=1e6))
    assert torch.isfinite(held.colors).all() and float((held.colors - start).abs().max()) < 1e-3


def test_the_view_average_of_a_flat_render_is_its_colour_on_every_splat_drawn_and_the_fallback_elsewhere():
    """Targets rendered from one colour (silhouettes half covered, over a black background) give every drawn splat
    exactly that colour, whatever colours the splats had: detail the views cannot see does not survive."""
    from dresg_addon.method.color_solve import view_average_colors

    scene = sphere_scene(n=80, far=5, seed=3)
    views = linear_views(scene, ring_cameras(3, width=24, height=16))
    flat = torch.tensor([0.8, 0.3, 0.1])
    targets = views.images(flat.expand(85, 3))
    drawn = views.energy > 0
    assert bool(drawn[:80].any()) and not bool(drawn[80:].any())  # the far splats are in no view
    fallback = torch.rand(85, 3, generator=torch.Generator().manual_seed(0))
    average = view_average_colors(views, targets, fallback)
    assert torch.allclose(average[drawn], flat.expand(int(drawn.sum()), 3), atol=1e-5)
    assert torch.equal(average[~drawn], fallback[~drawn])


def test_a_solve_from_the_view_average_keeps_less_of_the_start_than_one_from_the_colours(small):
    """Two starts, one target: from the splats' own random colours the anchored solve keeps part of them where the
    views barely constrain them; from the view average, the targets' own colour."""
    from dresg_addon.method.color_solve import view_average_colors

    scene, views = small
    n = views.energy.numel()
    noisy = torch.rand(n, 3, generator=torch.Generator().manual_seed(1))
    flat = torch.full((n, 3), 0.5)
    targets = views.images(flat)
    settings = ColorSolveSettings(anchor=0.3)
    kept = solve_colors(views, targets, noisy, settings).colors
    averaged = solve_colors(views, targets, view_average_colors(views, targets, noisy), settings).colors
    drawn = views.energy > 0
    assert float((averaged - flat)[drawn].abs().max()) < 1e-4
    assert float((kept - flat)[drawn].abs().max()) > 100 * float((averaged - flat)[drawn].abs().max())


def test_the_view_average_stays_finite_on_faint_and_uncovered_pixels(small):
    from dresg_addon.method.color_solve import view_average_colors

    _, views = small
    n = views.energy.numel()
    targets = [torch.ones_like(b) for b in views.constants]  # white even where nothing is drawn
    average = view_average_colors(views, targets, torch.zeros(n, 3))
    assert torch.isfinite(average).all() and float(average.min()) >= 0.0 and float(average.max()) <= 1.0
    with pytest.raises(NumericalError):
        view_average_colors(views, [t * float("nan") for t in targets], torch.zeros(n, 3))


def _drawn(views: LinearViews) -> torch.Tensor:  # [V, N]: how much each view draws each splat
    return torch.stack([m.rmatvec(c.new_ones(c.shape))[:, 0] for m, c in zip(views.maps, views.coverages)])


def test_best_views_keep_the_joint_fit_where_the_views_agree_and_each_views_marks_where_they_do_not(small):
    from dresg_addon.method.color_solve import best_view_colors, single_view_solutions

    _, views = small
    n = views.energy.numel()
    settings = ColorSolveSettings(tolerance=1e-6, max_rounds=30, cg_iterations=16, anchor=0.3)
    start = torch.full((n, 3), 0.5)
    truth = torch.from_numpy(np.random.default_rng(8).uniform(0.2, 0.8, (n, 3)).astype(np.float32))
    agreeing = views.images(truth)  # one set of colours shows every target: the plain fit reaches it
    plain = replace(settings, anchor=0.0)
    joint = solve_colors(views, agreeing, start, plain).colors
    seen = views.energy > 0.2 * float(views.energy.max())
    torch.testing.assert_close(
        best_view_colors(views, agreeing, joint, plain, 4.0)[seen], joint[seen], atol=0.01, rtol=0
    )
    # Each view painted with its own marks: the joint fit averages them; at a stiff sharpness each splat takes
    # the colours of the one view that draws it most, exactly (finite, although (d / max d)^1e6 underflows).
    rng = np.random.default_rng(9)
    painted = [views.images(torch.from_numpy(rng.uniform(0, 1, (n, 3)).astype(np.float32)))[v] for v in range(3)]
    joint = solve_colors(views, painted, start, settings).colors
    alone = torch.stack(single_view_solutions(views, painted, joint, settings))  # [V, N, 3]
    drawn = _drawn(views)
    top = drawn.topk(2, dim=0).values
    clear = (top[0] > 0) & (top[1] < 0.9 * top[0])  # one view draws it clearly most
    assert int(clear.sum()) > n // 4
    sharpest = best_view_colors(views, painted, joint, settings, 1e6)
    assert torch.isfinite(sharpest).all()
    picked = alone[drawn.argmax(0), torch.arange(n)]
    torch.testing.assert_close(sharpest[clear], picked[clear], atol=1e-5, rtol=0)
    # Softer weights lie between the best view and the others; the solve setting applies them to its fit.
    soft = best_view_colors(views, painted, joint, settings, 4.0)
    assert float((soft - joint).abs().mean()) > 0.01
    assert float((soft - sharpest)[clear].abs().mean()) < float((joint - sharpest)[clear].abs().mean())
    via = solve_colors(views, painted, start, settings, pick=lambda v, t, j: best_view_colors(v, t, j, settings, 4.0))
    torch.testing.assert_close(via.colors, soft)


def test_best_views_leave_splats_no_view_draws_alone_and_refuse_a_sharpness_that_cannot_weigh():
    from dresg_addon.method.color_solve import best_view_colors

    scene = sphere_scene(n=80, far=5, seed=3)
    views = linear_views(scene, ring_cameras(3, width=24, height=16))
    drawn = views.energy > 0
    joint = torch.rand(85, 3, generator=torch.Generator().manual_seed(2))
    targets = views.images(torch.full((85, 3), 0.4))
    settings = ColorSolveSettings(anchor=0.3)
    best = best_view_colors(views, targets, joint, settings, 4.0)
    assert torch.equal(best[~drawn], joint[~drawn])
    assert torch.isfinite(best).all() and float(best.min()) >= 0.0 and float(best.max()) <= 1.0
    for sharpness in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="sharpness"):
            best_view_colors(views, targets, joint, settings, sharpness)


def test_best_views_blend_block_by_block_exactly_as_all_at_once(small, monkeypatch):
    from dresg_addon.method import color_solve

    _, views = small
    n = views.energy.numel()
    rng = np.random.default_rng(10)
    painted = [views.images(torch.from_numpy(rng.uniform(0, 1, (n, 3)).astype(np.float32)))[v] for v in range(3)]
    joint = torch.from_numpy(rng.uniform(0, 1, (n, 3)).astype(np.float32))
    settings = ColorSolveSettings(anchor=0.3)
    whole = color_solve.best_view_colors(views, painted, joint, settings, 4.0)
    monkeypatch.setattr(color_solve, "BLEND_BLOCK", 7)
    assert torch.equal(color_solve.best_view_colors(views, painted, joint, settings, 4.0), whole)


def test_a_map_of_only_some_columns_draws_those_splats_and_no_others(small):
    _, views = small
    m = views.maps[0]
    n = m.shape[1]
    keep = torch.from_numpy(np.random.default_rng(4).uniform(size=n) < 0.5)
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(5))
    pixels = torch.rand(m.shape[0], 3, generator=torch.Generator().manual_seed(6))
    only = m.only_columns(keep)
    torch.testing.assert_close(only.matvec(colors), m.matvec(colors * keep[:, None]))
    torch.testing.assert_close(only.rmatvec(pixels), m.rmatvec(pixels) * keep[:, None])
    torch.testing.assert_close(only.column_energy(), m.column_energy() * keep)
    # A solver's sum over views adds W^T y into its vector in place: the same as adding a new one.
    total = colors.clone()
    assert m.add_rmatvec(total, pixels) is total
    torch.testing.assert_close(total, colors + m.rmatvec(pixels))


def test_each_splats_first_view_is_the_earliest_that_draws_it_well(small):
    from dresg_addon.method.color_solve import first_views

    _, views = small
    drawn = _drawn(views)  # [V, N]
    first = first_views(views.drawn_weights, 0.5)
    enough = (drawn >= 0.5 * drawn.amax(0)) & (drawn > 0)
    for v, earlier in ((0, []), (1, [0]), (2, [0, 1])):
        expected = enough[v] & ~enough[earlier].any(0) if earlier else enough[v]
        assert int(expected.sum()) > 0, f"no splat is first drawn by view {v}: the case tests nothing"
        assert torch.equal(first == v, expected)
    assert torch.equal(first == -1, ~(drawn > 0).any(0))
    assert torch.equal(first_views(views.drawn_weights, 1.0), torch.where((drawn > 0).any(0), drawn.argmax(0), -1))


def test_views_in_turn_hold_what_earlier_views_painted_and_reach_targets_that_agree(small):
    from dresg_addon.method.color_solve import PAINT_ROUNDS, ViewsInTurn, first_view_colors, view_average_colors

    _, views = small
    n = views.energy.numel()
    settings = ColorSolveSettings(tolerance=1e-6, cg_iterations=16, anchor=0.3)
    rng = np.random.default_rng(11)
    # Targets that agree: painting in turn reaches each of them as closely as the joint fit does.
    truth = torch.from_numpy(rng.uniform(0.2, 0.8, (n, 3)).astype(np.float32))
    agreeing = views.images(truth)
    turned = first_view_colors(views, agreeing, torch.zeros(n, 3), settings, 0.5)
    for image, target, coverage in zip(views.images(turned), agreeing, views.coverages):
        covered = coverage[:, 0] > 0.5
        assert float((image - target)[covered].square().mean().sqrt()) < 0.01
    # Each view its own marks: view 0 paints alone, as its own unanchored solve; a later view's splats are solved
    # with the earlier views' held, so its pixels over them are left to what view 0 painted there.
    painted = [views.images(torch.from_numpy(rng.uniform(0, 1, (n, 3)).astype(np.float32)))[v] for v in range(3)]
    turn = ViewsInTurn(views, 0.5, settings)
    assert not bool(turn.painted.any())
    turn.paint(0, painted[0])
    one = LinearViews([views.maps[0]], [views.constants[0]])
    alone = projected_solve(
        one,
        [painted[0]],
        view_average_colors(one, [painted[0]], torch.full((n, 3), 0.5)),
        replace(settings, anchor=0.0, max_rounds=PAINT_ROUNDS),
    ).colors
    mine = turn.first == 0
    assert torch.equal(turn.painted, mine)
    torch.testing.assert_close(turn.colors[mine], alone[mine], atol=1e-6, rtol=0)
    held = turn.colors[mine].clone()
    turn.paint(1, painted[1])
    turn.paint(2, painted[2])
    torch.testing.assert_close(turn.colors[mine], held, atol=0, rtol=0)
    assert torch.equal(turn.painted, turn.first >= 0)
    # What the painted splats show: their colours' render over the pixel's coverage (not darkened by a thin one).
    image, share = turn.painted_image(1)
    render, coverage = views.maps[1].matvec(turn.colors), views.coverages[1]
    full = (share > 0.999) & (coverage[:, 0] > 0.01)
    assert int(full.sum()) > 10
    torch.testing.assert_close(image[full] * coverage[full], render[full], atol=1e-3, rtol=0)
    assert torch.isfinite(image).all() and float(share.min()) >= 0.0 and float(share.max()) <= 1.0
    # Ink's pick: each splat from its first view; a painting already made of these targets is taken as it is.
    ink = Ink(np.ones((8, 8, 3), np.float32))
    via = solve_colors(
        views, painted, torch.full((n, 3), 0.5), settings, pick=lambda v, t, j: ink.pick_colors(v, t, j, settings)
    )
    joint = solve_colors(views, painted, torch.full((n, 3), 0.5), settings).colors
    torch.testing.assert_close(via.colors, first_view_colors(views, painted, joint, settings, 0.5))
    taken = ink.pick_colors(views, painted, joint, settings, painted=turn)
    torch.testing.assert_close(taken, via.colors, atol=1e-6, rtol=0)


def test_the_first_view_leaves_splats_no_view_draws_alone_and_refuses_a_share_outside_0_1():
    from dresg_addon.method.color_solve import first_view_colors

    scene = sphere_scene(n=80, far=5, seed=3)
    views = linear_views(scene, ring_cameras(3, width=24, height=16))
    drawn = views.energy > 0
    joint = torch.rand(85, 3, generator=torch.Generator().manual_seed(2))
    targets = views.images(torch.full((85, 3), 0.4))
    first = first_view_colors(views, targets, joint, ColorSolveSettings(anchor=0.3), 0.5)
    assert torch.equal(first[~drawn], joint[~drawn])
    assert torch.isfinite(first).all() and float(first.min()) >= 0.0 and float(first.max()) <= 1.0
    for share in (0.0, -0.5, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="share"):
            first_view_colors(views, targets, joint, ColorSolveSettings(), share)


def test_views_in_turn_stay_finite_with_a_view_that_sees_nothing_and_targets_at_the_box():
    from dresg_addon.method.color_solve import ViewsInTurn

    scene = sphere_scene(n=80, seed=3)
    views = linear_views(scene, [away_camera(24, 16), *ring_cameras(2, width=24, height=16)])
    turn = ViewsInTurn(views, 0.5, ColorSolveSettings())
    assert not bool((turn.first == 0).any())  # the first view draws nothing: it owns nothing
    extremes = [torch.zeros(16 * 24, 3), torch.ones(16 * 24, 3), torch.full((16 * 24, 3), 1e-30)]
    for view, target in enumerate(extremes):
        turn.paint(view, target)
        image, share = turn.painted_image(view)
        assert torch.isfinite(image).all() and torch.isfinite(share).all()
        assert float(image.min()) >= 0.0 and float(image.max()) <= 1.0
    image, share = turn.painted_image(0)
    assert float(share.max()) == 0.0 and float(image.abs().max()) == 0.0  # nothing painted is seen: no guide there
    colors = turn.over(torch.full((len(scene), 3), 0.5))
    assert torch.isfinite(colors).all() and float(colors.min()) >= 0.0 and float(colors.max()) <= 1.0
    assert float(colors[turn.first == 1].max()) > 0.99  # the all-white view's splats: white


def test_fit_split_by_splat_width_separates_disagreeing_views_from_what_no_view_can_draw(small):
    """Agreeing targets: no band loses anything, jointly or alone. Each view with its own marks: every band's joint
    error is above the view's own. A mark finer than the splats: the view alone cannot draw it either."""
    from dresg_addon.method.color_solve import fit_split

    scene, views = small
    settings = ColorSolveSettings(tolerance=1e-6, max_rounds=30, cg_iterations=16)
    widths = [torch.linspace(0.5, 12.0, m.shape[0]) for m in views.maps]  # every band has pixels
    truth = torch.from_numpy(np.random.default_rng(8).uniform(0.2, 0.8, (80, 3)).astype(np.float32))
    rows = fit_split(views, views.images(truth), widths, [0, 2], (3.0, 8.0), settings)
    assert {row.band for row in rows} == {"< 3 px", "3-8 px", ">= 8 px"} and {row.view for row in rows} == {0, 2}
    for v in (0, 2):
        assert sum(row.share for row in rows if row.view == v) == pytest.approx(1.0)
    assert max(max(row.joint_rmse, row.single_rmse) for row in rows) < 0.02
    rng = np.random.default_rng(9)
    painted = [views.images(torch.from_numpy(rng.uniform(0, 1, (80, 3)).astype(np.float32)))[v] for v in range(3)]
    rows = fit_split(views, painted, widths, [1], (3.0, 8.0), settings)
    assert all(row.joint_rmse > 2.0 * row.single_rmse and row.single_rmse < 0.02 for row in rows)
    checker = [views.images(truth)[v].clone() for v in range(3)]
    for image in checker:
        image[::2] = 1.0 - image[::2]  # every other pixel inverted: finer than a splat
    alone = fit_split(views, checker, widths, [0], (), settings)
    assert [row.band for row in alone] == ["all"] and alone[0].single_rmse > 0.1
    with pytest.raises(ValueError, match="increasing"):
        fit_split(views, checker, widths, [0], (8.0, 3.0))
    with pytest.raises(ValueError, match="do not index"):
        fit_split(views, checker, widths, [3])
