"""dresg_addon.blender.splat_mesh: the numpy side of the Blender splat object (no bpy needed)."""

import numpy as np
import pytest

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.scene.gaussians import SH_C0, GaussianScene
from dresg_addon.util.errors import SceneFormatError


def random_scene(n=64, rest=8, normals=True, seed=0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    return GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=rng.normal(-3, 1, size=(n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),  # not normalised, as trainers write them
        opacity_logits=rng.normal(0, 3, size=n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(size=(n, rest, 3)).astype(np.float32) if rest else None,
        normals=rng.normal(size=(n, 3)).astype(np.float32) if normals else None,
        extras={
            "f_extra": rng.normal(size=n).astype(np.float32),
            "label": rng.integers(0, 200, size=n).astype(np.uint8),
            "id": rng.integers(-(2**31), 2**31 - 1, size=n).astype(np.int32),
        },
    )


def store(attributes):
    """A stand-in for a mesh: name -> values, read back with the same reshape Blender's foreach_get gives."""
    table = {a.name: np.asarray(a.values).reshape(len(a.values), -1) for a in attributes}
    for a in attributes:
        assert a.values.shape[1:] == (() if sm.WIDTHS[a.data_type] == 1 else (sm.WIDTHS[a.data_type],)), a.name
    return lambda name: (
        None if name not in table else table[name].squeeze(1) if table[name].shape[1] == 1 else table[name]
    )


@pytest.mark.parametrize("rest", [0, 3, 8, 15])
def test_scene_round_trip_is_lossless(rest):
    scene = random_scene(rest=rest, normals=rest != 3)
    read = store(sm.scene_attributes(scene))
    back = sm.scene_from_attributes(scene.means, read, extras=sm.extra_dtypes(scene))
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest", "normals"):
        a, b = getattr(scene, name), getattr(back, name)
        assert (a is None and b is None) or np.array_equal(a, b), name
    assert back.extras.keys() == scene.extras.keys()
    for name, values in scene.extras.items():
        assert back.extras[name].dtype == values.dtype and np.array_equal(back.extras[name], values), name


def test_display_attributes_follow_the_activations():
    scene = random_scene()
    attributes = {a.name: a for a in sm.scene_attributes(scene)}
    assert attributes[sm.COLOR].data_type == "FLOAT_COLOR"
    rgb_linear = attributes[sm.COLOR].values[:, :3]
    expected = np.clip(0.5 + SH_C0 * scene.sh_dc, 0, 1)
    np.testing.assert_allclose(sm.linear_to_srgb(rgb_linear), expected, atol=2e-6)
    np.testing.assert_allclose(attributes[sm.COLOR].values[:, 3], scene.opacities, rtol=1e-6)
    np.testing.assert_allclose(attributes[sm.OPACITY].values, scene.opacities, rtol=1e-6)
    np.testing.assert_allclose(attributes[sm.SCALE].values, np.exp(scene.log_scales), rtol=1e-6)
    q = attributes[sm.ROTATION].values
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(q, scene.quats / np.linalg.norm(scene.quats, axis=1, keepdims=True), rtol=1e-5)
    assert sorted(attributes[sm.DISPLAY_RANK].values) == list(range(len(scene)))
    np.testing.assert_array_equal(attributes[sm.SH_DC_ORIGINAL].values, scene.sh_dc)


def test_srgb_transfer_matches_the_standard_and_inverts():
    # IEC 61966-2-1 reference points: 0.5 -> 0.21404, 0.04045 -> 0.0031308.
    np.testing.assert_allclose(
        sm.srgb_to_linear(np.array([0.0, 0.04045, 0.5, 1.0])), [0, 0.0031308, 0.21404, 1], atol=1e-5
    )
    v = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(sm.linear_to_srgb(sm.srgb_to_linear(v)), v, atol=2e-6)


def test_extreme_values_stay_finite():
    logits = np.array([-1e30, -100.0, 0.0, 100.0, 1e30], dtype=np.float32)
    dc = np.array([[np.inf, -np.inf, np.nan]] * 5, dtype=np.float32)
    colors = sm.display_colors(dc, sm.sigmoid(logits))
    assert np.isfinite(colors).all()
    np.testing.assert_allclose(colors[:, 3], [0, 0, 0.5, 1, 1], atol=1e-7)
    np.testing.assert_allclose(colors[0, :3], [1.0, 0.0, sm.srgb_to_linear(np.float32(0.5))], atol=1e-6)
    q = sm.unit_quaternions(np.zeros((2, 4), np.float32))
    np.testing.assert_array_equal(q, [[1, 0, 0, 0], [1, 0, 0, 0]])


def test_wide_integer_extras_are_refused():
    scene = random_scene(n=4)
    scene.extras["big"] = np.array([0, 1, 2, 2**40], dtype=np.int64)
    with pytest.raises(SceneFormatError, match="big"):
        sm.scene_attributes(scene)


def test_missing_raw_attribute_names_the_problem():
    scene = random_scene(n=4)
    read = store([a for a in sm.scene_attributes(scene) if a.name != sm.QUAT])
    with pytest.raises(SceneFormatError, match="dresg_quat"):
        sm.scene_from_attributes(scene.means, read)


def test_zero_sh_rest_keeps_the_shape():
    scene = random_scene(rest=15)
    back = sm.scene_from_attributes(scene.means, store(sm.scene_attributes(scene)), sh_rest_scale=0.0)
    assert back.sh_rest.shape == scene.sh_rest.shape and not back.sh_rest.any()


def test_blender_pixels_are_bottom_up_and_composited_over_white():
    h, w = 3, 2
    image = np.random.default_rng(1).uniform(size=(h, w, 3)).astype(np.float32)
    flat = sm.pixels_from_image(image)
    assert flat.shape == (h * w * 4,)
    np.testing.assert_array_equal(flat.reshape(h, w, 4)[0, :, :3], image[-1])  # Blender's first row is the bottom
    np.testing.assert_array_equal(sm.image_from_pixels(flat, w, h, 4), image)
    rgba = np.zeros((1, 1, 4), np.float32)
    rgba[..., 0], rgba[..., 3] = 1.0, 0.25  # red at 25 % over white
    np.testing.assert_allclose(sm.image_from_pixels(rgba.ravel(), 1, 1, 4)[0, 0], [1.0, 0.75, 0.75])
    grey = sm.image_from_pixels(np.array([0.2, 0.4], np.float32), 2, 1, 1)
    np.testing.assert_allclose(grey[0], [[0.2] * 3, [0.4] * 3])
    with pytest.raises(ValueError, match="2x2x4"):
        sm.image_from_pixels(np.zeros(3), 2, 2, 4)


def test_axis_conversion_and_local_up():
    r = sm.AXIS_CONVERSIONS["OPENCV_TO_BLENDER"]
    np.testing.assert_allclose(r @ r.T, np.eye(3))
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ [0, -1, 0], [0, 0, 1])  # OpenCV up (-y) -> Blender up (+z)
    np.testing.assert_allclose(r @ [0, 0, 1], [0, 1, 0])  # OpenCV forward -> Blender +y (front view)
    matrix = np.eye(4)
    matrix[:3, :3] = 2.5 * r  # uniform scale does not change the direction
    np.testing.assert_allclose(sm.local_up(matrix), [0, -1, 0], atol=1e-12)


def test_disk_frames_move_the_smallest_axis_to_z():
    px = sm.euler_xyz_matrix(sm.DISK_FRAME_X_SMALLEST)
    py = sm.euler_xyz_matrix(sm.DISK_FRAME_Y_SMALLEST)
    np.testing.assert_allclose(px, np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]]), atol=1e-12)  # columns e_y, e_z, e_x
    np.testing.assert_allclose(py, np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]]), atol=1e-12)  # columns e_z, e_x, e_y
    # The permuted frame with the permuted scales is the same ellipsoid.
    s = np.diag([0.1, 2.0, 3.0])
    np.testing.assert_allclose(px @ np.diag([2.0, 3.0, 0.1]) ** 2 @ px.T, s**2, atol=1e-12)
