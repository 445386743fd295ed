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


# --- A run that split splats (issue 45) ------------------------------------------------------------------------


def split_of(scene: GaussianScene, parents: np.ndarray, seed: int = 1) -> GaussianScene:
    """A stand-in for refine's split scene: the parents' colours and SH, new geometry for every splat."""
    other = random_scene(n=len(parents), rest=0, normals=False, seed=seed)
    return GaussianScene(
        means=other.means,
        log_scales=other.log_scales,
        quats=scene.quats[parents],
        opacity_logits=other.opacity_logits,
        sh_dc=scene.sh_dc[parents],
    )


def mesh_after_split(means, attributes, parents, split):
    """(positions, name -> PointAttribute) of a mesh after :func:`sm.split_attributes`."""
    means, out = sm.split_attributes(means, attributes, parents, split)
    return means, {a.name: a for a in out}


def test_a_split_gives_the_children_their_parents_attributes_and_the_split_geometry():
    scene = random_scene(n=6)
    attributes = sm.scene_attributes(scene, seed=3)
    stylized = np.random.default_rng(5).normal(size=(6, 3)).astype(np.float32)
    user = np.array([True, False, True, False, False, True])
    attributes += [
        sm.PointAttribute(sm.SH_DC_STYLIZED, "FLOAT_VECTOR", stylized),
        sm.PointAttribute("painted", "BOOLEAN", user),
    ]
    parents = np.array([0, 1, 2, 3, 4, 5, 1, 1, 4, 1])
    split = split_of(scene, parents)
    before = {a.name: a.values for a in attributes}
    means, after = mesh_after_split(scene.means, attributes, parents, split)

    np.testing.assert_array_equal(means, split.means)
    np.testing.assert_array_equal(after[sm.LOG_SCALE].values, split.log_scales)
    np.testing.assert_array_equal(after[sm.OPACITY_LOGIT].values, split.opacity_logits)
    np.testing.assert_array_equal(after[sm.OPACITY].values, sm.sigmoid(split.opacity_logits))
    np.testing.assert_array_equal(after[sm.COLOR].values[:, 3], sm.sigmoid(split.opacity_logits))
    for name in (sm.SH_DC_ORIGINAL, sm.SH_DC_STYLIZED, sm.sh_rest_name(7), sm.NORMAL, "dresg_extra_label", "painted"):
        np.testing.assert_array_equal(after[name].values, before[name][parents], err_msg=name)
        assert after[name].data_type == {a.name: a for a in attributes}[name].data_type
    # The imported geometry, kept for Restore, and the parents.
    np.testing.assert_array_equal(after[sm.MEANS_ORIGINAL].values, scene.means[parents])
    np.testing.assert_array_equal(after[sm.OPACITY_LOGIT_ORIGINAL].values, scene.opacity_logits[parents])
    np.testing.assert_array_equal(after[sm.QUAT_ORIGINAL].values, scene.quats[parents])
    np.testing.assert_array_equal(after[sm.PARENT].values, parents)
    # Ranks: a permutation in the parents' order, each parent's children right after it.
    rank, old = after[sm.DISPLAY_RANK].values, before[sm.DISPLAY_RANK]
    assert sorted(rank) == list(range(10)) and rank.dtype == np.int32
    np.testing.assert_array_equal(np.argsort(rank[:6]), np.argsort(old))
    by_rank = np.argsort(rank)
    assert list(by_rank[rank[1] : rank[1] + 4]) == [1, 6, 7, 9]
    assert list(by_rank[rank[4] : rank[4] + 2]) == [4, 8]


def test_a_second_split_indexes_the_split_mesh_and_restore_gives_back_the_imported_splats_exactly():
    scene = random_scene(n=5)
    imported = sm.scene_attributes(scene, seed=2)
    first = np.array([0, 1, 2, 3, 4, 2, 2])
    means, after = mesh_after_split(scene.means, imported, first, split_of(scene, first))
    split_once = sm.scene_from_attributes(means, store(list(after.values())))
    second = np.array([0, 1, 2, 3, 4, 5, 6, 6, 5, 0])  # a child of the first split is split again, and splat 0
    means, after = mesh_after_split(means, list(after.values()), second, split_of(split_once, second, seed=4))
    np.testing.assert_array_equal(after[sm.PARENT].values, first[second])
    np.testing.assert_array_equal(after[sm.SH_DC_ORIGINAL].values, scene.sh_dc[first[second]])
    np.testing.assert_array_equal(after[sm.MEANS_ORIGINAL].values, scene.means[first[second]])

    # Restore: the imported splats lead the mesh; cut to them, their arrays are the import's.
    n = sm.imported_count(after[sm.PARENT].values)
    assert n == 5
    cut = store([sm.PointAttribute(a.name, a.data_type, a.values[:n]) for a in after.values()])
    restored_means, restored = sm.restored_attributes(cut)
    np.testing.assert_array_equal(restored_means, scene.means)
    restored = {a.name: a.values for a in restored}
    for item in imported:
        if item.name in restored:
            np.testing.assert_array_equal(restored[item.name], item.values, err_msg=item.name)
    assert {sm.COLOR, sm.OPACITY, sm.OPACITY_LOGIT, sm.DISPLAY_RANK, sm.LOG_SCALE, sm.QUAT} <= restored.keys()
    for name in (sm.sh_rest_name(0), sm.NORMAL, "dresg_extra_id"):  # never changed: kept by the cut
        np.testing.assert_array_equal(cut(name), {a.name: a.values for a in imported}[name])


def test_parents_that_do_not_fit_the_mesh_are_refused_in_one_line():
    for parents in (np.array([0, 1]), np.array([0, 2, 2, 1]), np.array([0, 1, 2, 3]), np.array([0.0, 1, 2, 1])):
        with pytest.raises(SceneFormatError, match="parent indices"):
            sm.check_parents(parents, 3)
    np.testing.assert_array_equal(sm.check_parents(np.array([0, 1, 2, 0], np.int32), 3), [0, 1, 2, 0])
    assert sm.imported_count(np.array([0, 1, 2, 1, 1])) == 3
    assert sm.imported_count(np.arange(4)) == 4
    for edited in (np.array([0, 2, 1, 1]), np.array([0, 1, 2, 4, 1]), np.array([1, 0])):  # splats deleted or added
        with pytest.raises(SceneFormatError, match="Restore cannot tell the imported ones"):
            sm.imported_count(edited)


def test_children_of_lists_each_split_splats_appended_children():
    got = sm.children_of(np.array([0, 1, 2, 3, 2, 0, 2]), 4)
    assert [(p, list(c)) for p, c in got] == [(0, [5]), (2, [4, 6])]
    assert sm.children_of(np.arange(3), 3) == []
