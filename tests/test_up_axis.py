"""Which way is up from the splats alone (issue 28): the Automatic axes when no cameras lie beside the file,
and the six Up Axis rotations of the splat object (numpy only, no bpy)."""

from __future__ import annotations

import numpy as np
import pytest
from messages import names

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.scene.camera_io import detect_up_axis
from dresg_addon.scene.demo import demo_scene
from dresg_addon.scene.gaussians import GaussianScene
from dresg_addon.scene.io import read_scene, write_scene
from dresg_addon.scene.up_axis import up_axis_from_splats

# Quaternions (w, x, y, z) that turn +z into each up axis (90 or 180 degrees about x or y).
H = np.sqrt(0.5)
TURN_Z_TO = {
    "+Z": (1.0, 0.0, 0.0, 0.0),
    "-Z": (0.0, 1.0, 0.0, 0.0),
    "+X": (H, 0.0, H, 0.0),
    "-X": (H, 0.0, -H, 0.0),
    "+Y": (H, -H, 0.0, 0.0),
    "-Y": (H, H, 0.0, 0.0),
}


def _quat_multiply(a, b):  # (w, x, y, z) products, b: [N, 4]
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = np.asarray(b, np.float64).T
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        1,
    )


def _matrix(quat) -> np.ndarray:
    w, x, y, z = quat
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def turned(scene: GaussianScene, quat) -> GaussianScene:
    """The scene rotated as a whole: positions and each splat's orientation."""
    out = scene.copy()
    out.means = (scene.means.astype(np.float64) @ _matrix(quat).T).astype(np.float32)
    out.quats = _quat_multiply(quat, scene.quats).astype(np.float32)
    return out


def floor_and_object(seed: int = 0) -> GaussianScene:
    """A 4 x 4 floor of flat splats (z = 0, up +z, tilted 8 degrees) and a ball of round splats standing on it."""
    rng = np.random.default_rng(seed)
    grid = np.linspace(-2.0, 2.0, 60)
    floor = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2)
    floor = np.column_stack([floor + rng.normal(0.0, 0.01, floor.shape), rng.normal(0.0, 0.005, len(floor))])
    turn = rng.uniform(0.0, np.pi, len(floor))  # flat splats turned at random about their normal (z)
    floor_quats = np.column_stack([np.cos(turn / 2), np.zeros((len(floor), 2)), np.sin(turn / 2)])
    direction = rng.normal(size=(1500, 3))
    ball = 0.5 * direction / np.linalg.norm(direction, axis=1, keepdims=True) + [0.3, -0.2, 0.55]
    scene = GaussianScene(
        means=np.concatenate([floor, ball]).astype(np.float32),
        log_scales=np.log(
            np.concatenate([np.tile([0.05, 0.05, 0.004], (len(floor), 1)), np.full((1500, 3), 0.04)])
        ).astype(np.float32),
        quats=np.concatenate([floor_quats, np.tile([1.0, 0.0, 0.0, 0.0], (1500, 1))]).astype(np.float32),
        opacity_logits=rng.normal(2.0, 1.0, len(floor) + 1500).astype(np.float32),
        sh_dc=rng.normal(size=(len(floor) + 1500, 3)).astype(np.float32),
    )
    tilt = np.radians(8.0)
    return turned(scene, (np.cos(tilt / 2), np.sin(tilt / 2), 0.0, 0.0))


def blob(n: int = 5000, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(n, 4))
    return GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=np.full((n, 3), np.log(0.05), np.float32),
        quats=(quats / np.linalg.norm(quats, axis=1, keepdims=True)).astype(np.float32),
        opacity_logits=np.full(n, 1.0, np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
    )


def test_up_axis_rotations_are_the_named_axes():
    for up in sm.UP_AXES:
        for flip in (False, True):
            r = sm.up_axis_rotation(up, flip)
            np.testing.assert_array_equal(r @ r.T, np.eye(3))
            assert np.linalg.det(r) == pytest.approx(1.0)
            np.testing.assert_array_equal(r @ sm.up_axis_vector(up), [0.0, 0.0, -1.0 if flip else 1.0])
        opposite = ("-" if up[0] == "+" else "+") + up[1]
        np.testing.assert_array_equal(sm.up_axis_rotation(up, flip=True), sm.up_axis_rotation(opposite))
        assert sm.up_axis_for(sm.up_axis_vector(up) + 0.3) == up
    # The import's named Axes are three of them, written once.
    for key, up in sm.AXIS_CONVERSION_UP.items():
        np.testing.assert_array_equal(sm.AXIS_CONVERSIONS[key], sm.up_axis_rotation(up))
        assert sm.axis_conversion_of(up) == key
    np.testing.assert_array_equal(sm.AXIS_CONVERSIONS["NONE"], np.eye(3))
    assert sm.axis_conversion_of("+Y", flip=True) == "OPENCV_TO_BLENDER" and sm.axis_conversion_of("+X") == ""
    with pytest.raises(ValueError, match="not one of"):
        sm.up_axis_vector("Y")


@pytest.mark.parametrize("up", sm.UP_AXES)
def test_a_floor_with_an_object_on_it_is_found_in_every_orientation(up):
    guess = up_axis_from_splats(turned(floor_and_object(), TURN_Z_TO[up]))
    assert guess.axis == up
    assert guess.sure and guess.plane_ratio > 3.0 and guess.footprint_ratio > 1.5
    bottom = ("-" if up[0] == "+" else "+") + up[1]
    assert f"across {up[1]}" in guess.evidence() and f"wider at {bottom}" in guess.evidence()


def test_an_isotropic_blob_is_not_sure_and_the_import_keeps_opencv(tmp_path):
    for seed in range(3):
        guess = up_axis_from_splats(blob(seed=seed))
        assert not guess.sure and guess.confidence < 0.7, guess
    path = tmp_path / "blob.ply"
    write_scene(blob(), path)
    up, reason = detect_up_axis(path, read_scene(path))
    assert up == "-Y"
    names(reason, "not sure", "Up Axis")  # says it guessed, and which setting to check


def test_degenerate_scenes_are_not_sure():
    few = blob(10)
    assert not up_axis_from_splats(few).sure
    flat = blob(500)
    flat.means[:, 2] = 0.0  # a sheet: the layer is clear, which side is up is not
    guess = up_axis_from_splats(flat)
    assert guess.axis[1] == "Z" and guess.plane_ratio > 3.0 and not guess.sure
    broken = blob(500)
    broken.means[:] = np.nan
    assert not up_axis_from_splats(broken).sure


def test_automatic_axes_come_from_the_splats_without_cameras(tmp_path):
    path = tmp_path / "floor.ply"
    write_scene(turned(floor_and_object(), TURN_Z_TO["+Y"]), path)
    up, reason = detect_up_axis(path, read_scene(path))
    assert up == "+Y" and reason.startswith("+Y up (OpenGL, glTF) from the splats") and "confident" in reason
    up, reason = detect_up_axis(path)  # no scene given: the usual frame, and why
    assert up == "-Y" and "no cameras found" in reason


# Measured (bench/up_axis.py, its table in bench/README.md): the truth of each scene, what the
# splats say and the margins they say it by.
SHARED = {
    "bonsai-7k-mini.splat": ("-Y", True),  # COLMAP capture: the camera hint's up is (0.02, -0.76, -0.65)
    "luigi.ply": ("+Y", True),  # a y-up model (T-pose figurine, seen upright in renders with up +y)
    "graphdeco_it7000_sh3.ply": ("-Y", False),  # truth unknown (no cameras, unrecognisable): not sure, OpenCV
}


@pytest.mark.parametrize("name", sorted(SHARED))
def test_the_shared_scenes(shared_data, name):
    truth, sure = SHARED[name]
    guess = up_axis_from_splats(read_scene(shared_data(f"scenes/{name}")))
    assert guess.sure == sure, guess
    if sure:
        assert guess.axis == truth and guess.confidence > 1.5, guess
    up, _reason = detect_up_axis(shared_data(f"scenes/{name}"), read_scene(shared_data(f"scenes/{name}")))
    assert up == truth


def test_the_demo_scene_stands_on_its_ground():
    guess = up_axis_from_splats(demo_scene())  # objects stand on the plane y = 0 at negative y
    assert guess.axis == "-Y" and guess.sure and guess.plane_ratio > 5.0
