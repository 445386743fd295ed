"""The fast rasterizer against the float64 brute-force reference, gradients by gradcheck, and extreme cases."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dresg_addon.raster import ColorOnlyRenderer, RasterSettings, colors_from_sh, render, render_scene
from dresg_addon.raster.reference import reference_render
from dresg_addon.scene.camera import Camera, look_at

F64 = torch.float64


def random_scene(n, seed, spread=0.6, log_scale=(-3.5, -1.5)):
    rng = np.random.default_rng(seed)
    return (
        rng.normal(size=(n, 3)) * spread,
        rng.normal(size=(n, 4)),
        rng.uniform(*log_scale, size=(n, 3)),
        rng.normal(size=n) * 2.0,
        rng.uniform(size=(n, 3)),
    )


def tensors(arrays, dtype=F64, grad=False):
    return [torch.tensor(np.asarray(a), dtype=dtype, requires_grad=grad) for a in arrays]


def camera(width=40, height=30, f=35.0, eye=(0.0, 0.0, -3.0), cx=None, cy=None):
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    return Camera(width, height, f, f, cx, cy, look_at(eye, (0.0, 0.0, 0.0)))


def assert_matches_reference(scene, cam, settings=RasterSettings(), atol=1e-5):
    ref = reference_render(*scene, cam, near=settings.near, background=settings.background)
    out = render(*tensors(scene), cam, settings, visibility="all")
    assert np.abs(out.rgb.numpy() - ref["rgb"]).max() <= atol
    assert np.abs(out.alpha.numpy() - ref["alpha"]).max() <= atol
    assert np.abs(out.depth.numpy() - ref["depth"]).max() <= 1e-4
    assert np.abs(out.visibility.numpy() - ref["visibility"]).max() <= atol * 10
    return out, ref


def all_finite(*tensors_):
    return all(bool(torch.isfinite(t).all()) for t in tensors_ if t is not None)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_reference_random_scenes(seed):
    scene = random_scene(150, seed)
    out, _ = assert_matches_reference(scene, camera(), RasterSettings(background=(0.2, 0.3, 0.4)))
    assert out.n_pairs > 500  # the scene really covers the image


@pytest.mark.parametrize("seed", [3, 4])
def test_float32_inputs_match_reference(seed):
    # float32 colours: float32 per-sample arithmetic, float64 scans (the default for real scenes).
    scene = random_scene(200, seed)
    cam = camera()
    ref = reference_render(*scene, cam)
    out = render(*tensors(scene, dtype=torch.float32), cam, visibility="all")
    assert out.rgb.dtype == torch.float32
    assert np.abs(out.rgb.numpy() - ref["rgb"]).max() <= 1e-5
    assert np.abs(out.alpha.numpy() - ref["alpha"]).max() <= 1e-5


def test_offscreen_centre_with_onscreen_footprint_is_kept():
    # Centres outside the image (one far outside the 1.3x frustum guard) whose ellipses reach into it:
    # the conservative screen cull must keep them, and the clamped Jacobian must match the reference.
    means = [[-1.6, 0.0, 0.0], [0.0, 1.2, 0.5], [-9.0, 0.3, 1.0]]
    quats = [[1.0, 0.0, 0.0, 0.0], [0.9, 0.1, 0.3, 0.0], [0.7, 0.0, 0.7, 0.1]]
    log_scales = [[-0.5, -0.6, -0.7], [-0.4, -0.9, -1.0], [1.2, 0.2, 0.1]]
    logits = [2.0, 1.0, 3.0]
    colors = [[1.0, 0.2, 0.1], [0.1, 0.9, 0.3], [0.2, 0.3, 1.0]]
    cam = camera()
    out, _ = assert_matches_reference((means, quats, log_scales, logits, colors), cam)
    assert out.alpha[:, 0].max() > 0.1 and out.alpha[-1, :].max() > 0.1


def test_band_workers_match_one_thread_and_repeat_exactly():
    scene = random_scene(300, 8)
    cam = camera(64, 48, 50.0)
    weights = torch.rand(48, 64, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    settings = RasterSettings(band_pairs=2_000)  # many bands, so both workers get several

    def run(threads):
        before = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            args = tensors(scene, grad=True)
            out = render(*args, cam, settings)
            (out.rgb * weights).sum().backward()
            return out.rgb.detach(), [a.grad for a in args]
        finally:
            torch.set_num_threads(before)

    rgb1, grads1 = run(1)
    rgb2, grads2 = run(2)
    again_rgb, again_grads = run(2)
    assert torch.equal(rgb1, rgb2)  # bands are independent: the image does not depend on the split
    for g1, g2, g3 in zip(grads1, grads2, again_grads):
        assert torch.allclose(g1, g2, rtol=1e-10, atol=1e-12)  # per-worker partial sums: order differs
        assert torch.equal(g2, g3)  # a fixed split: repeatable bit for bit


def test_gradcheck_clamped_jacobian_and_small_quaternion():
    # Centres beyond the 1.3x frustum guard (clamped Jacobian), a quaternion of norm 1e-3, a flat splat.
    means = torch.tensor([[2.5, 0.1, 0.2], [-0.2, -0.8, 0.6], [0.1, 0.2, 0.0]], dtype=F64, requires_grad=True)
    quats = torch.tensor([[1e-3, 2e-4, -5e-4, 1e-4], [0.6, 0.2, -0.3, 0.7], [0.1, 0.9, 0.2, 0.3]], dtype=F64)
    quats.requires_grad_(True)
    log_scales = torch.tensor([[-0.2, -0.5, -0.4], [-0.3, -0.2, -0.6], [-0.5, -0.6, -6.0]], dtype=F64)
    log_scales.requires_grad_(True)
    logits = torch.tensor([1.0, 2.0, 0.5], dtype=F64, requires_grad=True)
    colors = torch.rand(3, 3, dtype=F64, generator=torch.Generator().manual_seed(1), requires_grad=True)
    cam = camera(10, 8, 4.0, eye=(0.0, 0.0, -1.2))
    wr = torch.rand(8, 10, 3, dtype=F64, generator=torch.Generator().manual_seed(2))

    def loss(*args):
        return (render(*args, cam).rgb * wr).sum()

    p_cam = means.detach().numpy() @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    assert abs(p_cam[0, 0] / p_cam[0, 2]) > 1.3 * cam.width / (2 * cam.fx)  # the guard clamps it
    out = render(means, quats, log_scales, logits, colors, cam, visibility="all")
    assert out.n_pairs > 20 and bool((out.visibility > 0).all())
    assert torch.autograd.gradcheck(loss, (means, quats, log_scales, logits, colors), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_matches_reference_offcentre_nonsquare_and_near_plane():
    scene = random_scene(120, 7, spread=1.5)
    cam = Camera(37, 23, 30.0, 26.0, 15.3, 13.9, look_at((0.3, -0.2, -2.0), (0.0, 0.1, 0.0)))
    assert_matches_reference(scene, cam, RasterSettings(near=0.5))


def test_bands_and_float32_agree():
    scene = random_scene(150, 3)
    cam = camera()
    exact = render(*tensors(scene), cam)
    banded = render(*tensors(scene), cam, RasterSettings(band_pairs=300))
    mixed = render(*tensors(scene), cam, RasterSettings(dtype=torch.float32))
    assert torch.allclose(banded.rgb, exact.rgb, atol=1e-12)
    assert (mixed.rgb - exact.rgb).abs().max() < 1e-5  # float32 samples, float64 scans


def test_speed_knobs_change_what_they_say():
    scene = random_scene(150, 4)
    cam = camera()
    exact = render(*tensors(scene), cam)
    truncated = render(*tensors(scene), cam, RasterSettings(truncation_sigma=1.0))
    assert truncated.n_pairs < exact.n_pairs
    assert (truncated.rgb - exact.rgb).abs().max() > 1e-3


def test_depth_consistent_visibility_leaves_out_hidden_gaussians():
    # A small Gaussian hidden behind an opaque wall: visible weight > 0 in total, but not depth-consistent.
    means = [[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]]
    quats = [[1.0, 0.0, 0.0, 0.0]] * 2
    log_scales = [[0.0, 0.0, -4.0], [-2.0, -2.0, -2.0]]
    logits = [1.5, 5.0]
    colors = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    cam = camera(eye=(0.0, 0.0, -3.0))
    scene = tensors([means, quats, log_scales, logits, colors])
    every = render(*scene, cam, visibility="all").visibility
    consistent = render(*scene, cam, visibility="depth_consistent").visibility
    assert every[1] > 1e-3
    assert consistent[1] == 0
    assert consistent[0] == pytest.approx(float(every[0]))


def test_gradcheck_small_scene():
    scene = tensors(random_scene(10, 11), grad=True)
    cam = camera(12, 10, 12.0)
    wr, wa = torch.rand(10, 12, 3, dtype=F64), torch.rand(10, 12, dtype=F64)

    def loss(*args):
        out = render(*args, cam, RasterSettings(background=(0.1, 0.2, 0.3)))
        return (out.rgb * wr).sum() + (out.alpha * wa).sum()

    assert torch.autograd.gradcheck(loss, scene, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradcheck_through_sh_colours():
    rng = np.random.default_rng(5)
    means, quats, log_scales, logits, _ = random_scene(3, 5, spread=0.3)
    sh_dc = torch.tensor(rng.normal(size=(3, 3)), dtype=F64, requires_grad=True)
    sh_rest = torch.tensor(rng.normal(size=(3, 15, 3)) * 0.2, dtype=F64, requires_grad=True)
    cam = camera(8, 6, 8.0)
    geometry = tensors([means, quats, log_scales, logits])
    centre = torch.tensor(cam.center, dtype=F64)

    def loss(dc, rest):
        colors = colors_from_sh(dc, rest, geometry[0], centre)
        return render(geometry[0], geometry[1], geometry[2], geometry[3], colors, cam).rgb.pow(2).sum()

    assert torch.autograd.gradcheck(loss, (sh_dc, sh_rest), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_colour_only_path_matches_full_render_and_gradients():
    scene = random_scene(150, 9)
    cam = camera()
    means, quats, log_scales, logits, colors = tensors(scene)
    fast = ColorOnlyRenderer(means, quats, log_scales, logits, cam, RasterSettings(background=(0.5, 0.5, 0.5)))
    c1 = colors.clone().requires_grad_()
    c2 = colors.float().clone().requires_grad_()
    full = render(means, quats, log_scales, logits, c1, cam, RasterSettings(background=(0.5, 0.5, 0.5))).rgb
    sparse = fast(c2)
    assert (sparse.double() - full).abs().max() < 1e-5
    weights = torch.rand_like(full)
    (full * weights).sum().backward()
    (sparse * weights.float()).sum().backward()
    assert (c1.grad.float() - c2.grad).abs().max() < 1e-4
    assert fast.seen.sum() < len(means)  # some Gaussians are outside the view and can be skipped


# --- Stiff and extreme cases: nothing non-finite in outputs or gradients -------------------------------


def render_with_grads(scene, cam, settings=RasterSettings()):
    args = tensors(scene, grad=True)
    out = render(*args, cam, settings, visibility="all")
    (out.rgb.sum() + out.alpha.sum()).backward()
    assert all_finite(out.rgb, out.alpha, out.depth, out.visibility, *[a.grad for a in args])
    return out, args


def test_gaussians_behind_and_at_the_near_plane_and_camera_inside():
    means = [[0.0, 0.0, -3.0], [0.0, 0.0, -3.0 + 0.01], [0.0, 0.0, -5.0], [0.1, 0.0, -2.7], [0.0, 0.0, 0.0]]
    quats = [[1.0, 0.0, 0.0, 0.0]] * 5
    log_scales = [[0.0] * 3, [-1.0] * 3, [-1.0] * 3, [1.0, 1.0, 1.0], [-1.0] * 3]  # #3 contains the camera
    scene = (means, quats, log_scales, [2.0] * 5, np.eye(3)[[0, 1, 2, 0, 1]])
    out, args = render_with_grads(scene, camera())
    assert args[0].grad[[0, 1, 2]].abs().sum() == 0  # at/behind the near plane: skipped, zero gradient
    assert out.alpha.min() > 0.5  # the Gaussian around the camera covers the view


@pytest.mark.parametrize("log_scale", [np.log(1e-7), np.log(1e4)])
def test_extreme_scales(log_scale):
    scene = random_scene(20, 1)
    scene = (scene[0], scene[1], np.full((20, 3), log_scale), scene[3], scene[4])
    out, _ = render_with_grads(scene, camera())
    if log_scale > 0:
        assert out.alpha.min() > 0.9  # huge Gaussians cover everything
    else:
        assert out.n_pairs <= 20 * 9  # points: a few pixels each (the 0.3 low-pass)


def test_anisotropy_1e6():
    rng = np.random.default_rng(3)
    log_scales = np.stack([np.full(20, np.log(1.0)), np.full(20, np.log(1e-6)), np.full(20, np.log(1e-3))], -1)
    scene = (
        rng.normal(size=(20, 3)) * 0.3,
        rng.normal(size=(20, 4)),
        log_scales,
        np.full(20, 3.0),
        rng.uniform(size=(20, 3)),
    )
    out, _ = render_with_grads(scene, camera())
    assert_matches_reference(scene, camera(), atol=1e-5)
    assert out.n_pairs > 0


def test_degenerate_quaternions_and_saturated_opacities():
    scene = random_scene(4, 2, spread=0.2)
    quats = np.array([[0.0, 0.0, 0.0, 0.0], [1e-20, 0.0, 0.0, 0.0], [0.0, 1e-20, 1e-20, 0.0], [1.0, 0.0, 0.0, 0.0]])
    logits = np.array([50.0, -50.0, 50.0, 0.0])
    scene = (scene[0], quats, scene[2], logits, scene[4])
    out, args = render_with_grads(scene, camera())
    assert args[3].grad[1] == 0  # sigmoid(-50) * 255 < 1: never contributes
    assert_matches_reference(scene, camera())


def test_ten_thousand_gaussians_on_one_pixel():
    n = 10_000
    rng = np.random.default_rng(0)
    means = np.stack([np.zeros(n), np.zeros(n), rng.uniform(-1.0, 1.0, n)], -1)
    scene = (means, np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), -6.0), np.full(n, -4.5), rng.uniform(size=(n, 3)))
    cam = Camera(1, 1, 10.0, 10.0, 0.5, 0.5, look_at((0, 0, -3.0), (0, 0, 0)))
    out, _ = render_with_grads(scene, cam)
    ref = reference_render(*scene, cam)
    assert abs(float(out.rgb[0, 0, 0].detach()) - ref["rgb"][0, 0, 0]) < 1e-9
    assert 1.0 - float(out.alpha[0, 0].detach()) >= 1e-4 * (1 - 0.0109)  # stopped at the transmittance floor


def test_empty_and_transparent_scenes():
    cam = camera()
    empty = render_with_grads(
        (np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3))), cam
    )[0]
    assert empty.alpha.abs().max() == 0 and empty.n_pairs == 0
    scene = random_scene(30, 0)
    transparent = render_with_grads((*scene[:3], np.full(30, -20.0), scene[4]), cam)[0]
    assert transparent.n_pairs == 0
    assert torch.equal(transparent.rgb, torch.zeros_like(transparent.rgb))


def test_one_by_one_and_4096_images_stay_sparse():
    scene = random_scene(50, 8, log_scale=(-5.0, -4.0))
    render_with_grads(scene, camera(1, 1, 1.0))
    big = camera(4096, 4096, 3500.0)
    out = render(*tensors(scene, dtype=torch.float32), big, RasterSettings(dtype=torch.float32), visibility="all")
    assert out.rgb.shape == (4096, 4096, 3)
    assert out.n_pairs < 1_000_000  # work follows the splats' area, not pixels x Gaussians (8e8)
    assert all_finite(out.rgb, out.alpha)


def test_non_finite_inputs_are_skipped():
    scene = [np.array(a, dtype=np.float64) for a in random_scene(30, 6)]
    scene[0][0, 0] = np.nan
    scene[1][1, 2] = np.inf
    scene[2][2, 1] = -np.inf
    scene[3][3] = np.nan
    scene[4][4, 0] = np.inf
    out, args = render_with_grads(scene, camera())
    for arg in args:
        assert arg.grad[:5].abs().sum() == 0
    clean = [a[5:] for a in scene]
    ref = reference_render(*clean, camera())
    assert np.abs(out.rgb.detach().numpy() - ref["rgb"]).max() < 1e-5


FROZEN_CASES = {  # scene -> (log-scales, quaternions) overrides: the extreme cases of the projection
    "random": (None, None),
    "points 1e-7": (np.full((40, 3), np.log(1e-7)), None),
    "huge 1e4": (np.full((40, 3), np.log(1e4)), None),
    "needles 1e6": (np.log(np.tile([1.0, 1e-6, 1e-3], (40, 1))), None),
    "degenerate quaternions": (None, np.tile([[0.0, 0.0, 0.0, 0.0], [1e-20, 0.0, 0.0, 0.0]], (20, 1))),
}


@pytest.mark.parametrize("case", list(FROZEN_CASES))
def test_frozen_geometry_projects_as_the_differentiable_path(case):
    """Without a gradient and with the splats' covariances made once, the projection takes a shorter float64 path:
    the same Gaussians, centres, conics and covariances to ~1e-12, and the render matches the reference."""
    from dresg_addon.raster.projection import project_gaussians, splat_covariances

    means, quats, log_scales, logits, colors = random_scene(40, 5)
    log_scales = FROZEN_CASES[case][0] if FROZEN_CASES[case][0] is not None else log_scales
    quats = FROZEN_CASES[case][1] if FROZEN_CASES[case][1] is not None else quats
    cam = camera()
    w2c = torch.tensor(cam.world_to_camera, dtype=F64)
    args = (w2c, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, 0.01)
    m, q, s = tensors((means, quats, log_scales))
    covariances = splat_covariances(q, s, F64)
    with torch.no_grad():
        frozen = project_gaussians(m, q, s, *args, None, covariances)
    grad = project_gaussians(m, q.clone().requires_grad_(True), s, *args, None, covariances)
    assert frozen.index.numel() > 0 and torch.equal(frozen.index, grad.index)
    for name in ("mx", "my", "conic_a", "conic_b", "conic_c", "cxx", "cxy", "cyy", "depth"):
        a, b = getattr(frozen, name), getattr(grad, name).detach()
        assert torch.isfinite(a).all(), name
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12 * float(b.abs().max())), name
    scene = (means, quats, log_scales, logits, colors)
    out = render(*tensors(scene), cam, RasterSettings(), "all", covariances=covariances)
    ref = reference_render(*scene, cam)
    assert np.abs(out.rgb.numpy() - ref["rgb"]).max() <= 1e-5
    assert np.abs(out.alpha.numpy() - ref["alpha"]).max() <= 1e-5


def test_bad_shapes_raise():
    scene = tensors(random_scene(5, 0))
    scene[4] = scene[4][:, :2]
    with pytest.raises(ValueError, match="colors has shape"):
        render(*scene, camera())


# --- Real scenes (skip when ../shared/data is absent) -------------------------------------------------------


def _bonsai_camera(shared_data, width=64, height=48):
    hint = json.loads(shared_data("scenes/bonsai-7k-mini.camera_hint.json").read_text())
    w2c = look_at(hint["initialCameraPosition"], hint["initialCameraLookAt"], hint["cameraUp"])
    f = 0.9 * width
    return Camera(width, height, f, f, width / 2, height / 2, w2c)


def _scene_arrays(scene):
    colors = np.maximum(0.5 + 0.28209479177387814 * scene.sh_dc, 0.0)
    return scene.means, scene.quats, scene.log_scales, scene.opacity_logits, colors


def test_real_luigi_matches_reference(shared_data):
    from dresg_addon.scene.io import read_scene

    scene = read_scene(shared_data("scenes/luigi.ply"))
    centre = np.median(scene.means, 0)
    extent = np.quantile(np.linalg.norm(scene.means - centre, axis=1), 0.9)
    eye = centre + np.array([0.0, -0.3, -2.5]) * extent
    cam = Camera(32, 24, 30.0, 30.0, 16.0, 12.0, look_at(eye, centre))
    out, _ = assert_matches_reference(_scene_arrays(scene), cam)
    assert out.alpha.mean() > 0.05


def test_real_bonsai_window_matches_reference(shared_data):
    from dresg_addon.scene.io import read_scene

    # Every 16th splat (17k): the reference projects Gaussians one at a time in Python.
    scene = read_scene(shared_data("scenes/bonsai-7k-mini.splat")).subset(slice(None, None, 16))
    cam = _bonsai_camera(shared_data)
    arrays = _scene_arrays(scene)
    out = render(*tensors(arrays, dtype=torch.float32), cam, RasterSettings())
    window = (24, 16, 12, 10)
    ref = reference_render(*arrays, cam, window=window)
    x0, y0, w, h = window
    assert np.abs(out.rgb[y0 : y0 + h, x0 : x0 + w].numpy() - ref["rgb"]).max() < 1e-5
    assert ref["alpha"].mean() > 0.3
    full = render_scene(scene, cam)
    assert torch.allclose(full.rgb, out.rgb, atol=1e-6)


def test_colour_only_restrict_to_seen_gaussians():
    scene = random_scene(150, 9)
    cam = camera()
    means, quats, log_scales, logits, colors = tensors(scene, dtype=torch.float32)
    full = ColorOnlyRenderer(means, quats, log_scales, logits, cam)
    expected = full(colors)
    keep = torch.nonzero(full.seen).squeeze(-1)
    narrowed = ColorOnlyRenderer(means, quats, log_scales, logits, cam).restrict(keep)
    assert torch.allclose(narrowed(colors[keep]), expected, atol=1e-6)
    with pytest.raises(ValueError, match="must be kept"):
        ColorOnlyRenderer(means, quats, log_scales, logits, cam).restrict(keep[1:])


def test_the_colour_only_map_holds_the_renders_samples_once():
    """The samples live only in the map's CSR matrix: the contributions derived from it are the render's, W^T is
    built on the first product that needs it, and a filtered, restricted or masked map draws what its samples do."""
    means, quats, log_scales, logits, colors = tensors(random_scene(300, 8), dtype=torch.float32)
    cam = camera(64, 48, 50.0)
    settings = RasterSettings(band_pairs=2_000)  # several bands
    pixel, gauss, weight = render(
        means, quats, log_scales, logits, colors, cam, settings, keep_contributions=True
    ).contributions
    fast = ColorOnlyRenderer(means, quats, log_scales, logits, cam, settings)
    for got, expected in zip(fast.contributions(), (pixel, gauss, weight)):
        assert got.dtype == expected.dtype and torch.equal(got, expected)
    fast(colors)
    assert fast.map._transposed is None  # rendering alone never transposes

    def dense(p, g, w, n):
        return torch.zeros(48 * 64, n, dtype=F64).index_put_((p, g), w.double(), accumulate=True)

    y = torch.rand(48 * 64, 3, generator=torch.Generator().manual_seed(1))
    strong = weight >= 1e-3
    faint = fast.linear_map(1e-3)
    assert faint.nnz == int(strong.sum()) < fast.map.nnz
    for m, w in (
        (faint, dense(pixel[strong], gauss[strong], weight[strong], 300)),
        (fast.map, dense(pixel, gauss, weight, 300)),
    ):
        torch.testing.assert_close(m.matvec(colors).double(), w @ colors.double(), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(m.rmatvec(y).double(), w.T @ y.double(), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(m.column_energy(), w.square().sum(0), atol=1e-6, rtol=0)
        torch.testing.assert_close(m.squared_rmatvec(y).double(), w.square().T @ y.double(), atol=1e-5, rtol=1e-5)
        keep = torch.arange(300) % 3 > 0
        masked = m.only_columns(keep)
        torch.testing.assert_close(masked.rmatvec(y).double(), (w * keep).T @ y.double(), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(masked.column_energy(), (w * keep).square().sum(0), atol=1e-6, rtol=0)

    keep = torch.arange(0, 300, 2)  # half the splats the view draws kept, the others in fixed colours
    restricted = ColorOnlyRenderer(means, quats, log_scales, logits, cam, settings).restrict(keep, colors)
    torch.testing.assert_close(restricted(colors[keep]), fast(colors), atol=1e-5, rtol=1e-5)
    kept = gauss % 2 == 0
    p, g, w = restricted.contributions()
    assert torch.equal(p, pixel[kept]) and torch.equal(g, gauss[kept] // 2) and torch.equal(w, weight[kept])


def test_a_render_is_freed_with_its_outputs():
    # An output kept on the autograd context outside save_for_backward forms a cycle through its grad_fn
    # that is never freed: every optimisation step would leak a view's samples (1 GB at 1M Gaussians).
    import weakref

    args = tensors(random_scene(50, 1), grad=True)
    out = render(*args, camera())
    node = out.alpha.grad_fn
    while node is not None and "Rasterize" not in type(node).__name__:
        node = node.next_functions[0][0]
    assert node is not None
    alive = weakref.ref(node)
    del node
    (out.rgb.sum() + out.alpha.sum()).backward()
    del out
    assert alive() is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    scene = random_scene(200, 12)
    cam = camera()
    weights = torch.rand(30, 40, 3, dtype=F64, generator=torch.Generator().manual_seed(3))
    results = []
    for device in ("cpu", "cuda"):
        args = [t.to(device).detach().requires_grad_(True) for t in tensors(scene)]
        out = render(*args, cam)
        (out.rgb * weights.to(device)).sum().backward()
        results.append((out.rgb.detach().cpu(), [a.grad.cpu() for a in args]))
    (rgb_cpu, grads_cpu), (rgb_gpu, grads_gpu) = results
    assert torch.allclose(rgb_cpu, rgb_gpu, atol=1e-10)
    for g_cpu, g_gpu in zip(grads_cpu, grads_gpu):
        assert torch.allclose(g_cpu, g_gpu, rtol=1e-8, atol=1e-10)


def test_blender_preview_uses_the_rasterizers_low_pass():
    """splat_mesh keeps its own copy (the add-on imports it without torch); they must agree."""
    from dresg_addon.blender import splat_mesh
    from dresg_addon.raster.projection import LOW_PASS

    assert splat_mesh.LOW_PASS == LOW_PASS


@pytest.mark.filterwarnings("ignore:Sparse CSR tensor support is in beta state")
def test_rendering_leaves_the_warnings_filters_alone(monkeypatch):
    """warnings.filters is process-wide: changing it, even for a moment, races with other threads (issue 42)."""
    import warnings

    before, seen = list(warnings.filters), []
    original = torch.sparse_csr_tensor

    def sparse_csr_tensor(*args, **kwargs):
        seen.append(list(warnings.filters))
        return original(*args, **kwargs)

    monkeypatch.setattr(torch, "sparse_csr_tensor", sparse_csr_tensor)
    means, quats, log_scales, logits, colors = tensors(random_scene(300, 8), dtype=torch.float32)
    settings = RasterSettings(band_pairs=2_000)  # several bands: the band pool runs
    render(means, quats, log_scales, logits, colors, camera(64, 48, 50.0), settings)
    fast = ColorOnlyRenderer(means, quats, log_scales, logits, camera(64, 48, 50.0), settings)
    fast.linear_map(1e-3).only_columns(torch.ones(300, dtype=torch.bool))
    assert len(seen) >= 2 and all(filters == before for filters in seen)  # the colour maps' CSR matrices
    assert warnings.filters == before
