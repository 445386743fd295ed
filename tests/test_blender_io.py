"""Import / export / restore / preview of splat objects, with the real bpy module (headless)."""

import sys
from pathlib import Path

import numpy as np
import pytest
from messages import names

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.scene.gaussians import SH_C0, GaussianScene
from dresg_addon.scene.io import read_scene, write_scene
from dresg_addon.scene.orbit import orbit_cameras
from dresg_addon.util.imageio import read_image

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender
REPO = Path(__file__).resolve().parents[1]
SCENES = ["luigi.ply", "graphdeco_it7000_sh3.ply", "bonsai-7k-mini.splat", "bonsai-7k-mini.compressed.ply"]


def import_splats(path, **options):
    assert bpy.ops.dresg.import_splats(filepath=str(path), **options) == {"FINISHED"}
    return bpy.context.active_object


def attribute(obj, name):
    from stylize_gaussians.operators.splat_object import read_attribute

    return read_attribute(obj.data, name)


def assert_scenes_equal(a: GaussianScene, b: GaussianScene):
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest", "normals"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        assert x is None or np.array_equal(x, y), name
    assert a.extras.keys() == b.extras.keys()
    for name in a.extras:
        assert np.array_equal(a.extras[name], b.extras[name]), name


def evaluated_mesh(obj):
    return obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data


@pytest.mark.parametrize("name", SCENES)
def test_import_matches_the_engine_reader(addon, shared_data, name):
    from stylize_gaussians.operators.splat_object import scene_from_object

    path = shared_data(f"scenes/{name}")
    reference = read_scene(path)
    obj = import_splats(path)
    mesh = obj.data
    assert len(mesh.vertices) == len(reference)
    assert_scenes_equal(scene_from_object(obj), reference)

    # Display attributes hold the activations the engine computes.
    np.testing.assert_allclose(attribute(obj, sm.OPACITY), reference.opacities, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(attribute(obj, sm.SCALE), reference.scales, rtol=1e-6)
    q = reference.quats / np.linalg.norm(reference.quats, axis=1, keepdims=True)
    np.testing.assert_allclose(attribute(obj, sm.ROTATION), q, atol=1e-6)
    color = attribute(obj, sm.COLOR)
    np.testing.assert_allclose(sm.linear_to_srgb(color[:, :3]), np.clip(reference.base_colors, 0, 1), atol=1e-5)
    assert mesh.attributes[sm.COLOR].data_type == "FLOAT_COLOR"
    assert mesh.attributes[sm.ROTATION].data_type == "QUATERNION"
    assert mesh.color_attributes.active_color_name == sm.COLOR
    if reference.sh_rest is not None:
        for k in range(reference.sh_rest.shape[1]):
            np.testing.assert_array_equal(attribute(obj, sm.sh_rest_name(k)), reference.sh_rest[:, k])

    # Provenance and the axis conversion, applied as the object transform only: Automatic, with no cameras beside
    # these files, goes by the splats (Luigi is a y-up model; the graphdeco file leaves them unsure: OpenCV).
    assert obj["dresg_source_path"] == str(path)
    assert obj["dresg_source_format"] in {"graphdeco PLY", "antimatter15 .splat", "PlayCanvas compressed PLY"}
    axes = "Y_UP_TO_BLENDER" if name == "luigi.ply" else "OPENCV_TO_BLENDER"
    assert obj["dresg_axis_conversion"] == axes
    np.testing.assert_allclose(np.array(obj.matrix_world)[:3, :3], sm.AXIS_CONVERSIONS[axes], atol=1e-7)


def test_import_without_axis_conversion_keeps_identity(addon, shared_data):
    obj = import_splats(shared_data("scenes/luigi.ply"), axis_conversion="NONE")
    assert obj["dresg_axis_conversion"] == "NONE"
    np.testing.assert_array_equal(np.array(obj.matrix_world), np.eye(4))


def test_import_errors_are_reported_with_the_file(addon, tmp_path):
    broken = tmp_path / "broken.ply"
    broken.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n")
    with pytest.raises(RuntimeError, match="broken.ply"):
        bpy.ops.dresg.import_splats(filepath=str(broken))
    with pytest.raises(RuntimeError) as error:
        bpy.ops.dresg.import_splats(filepath=str(tmp_path / "missing.ply"))
    names(error, "missing.ply", "not found")
    assert not [obj for obj in bpy.data.objects if obj.type == "MESH"]


@pytest.mark.parametrize("name", ["luigi.ply", "graphdeco_it7000_sh3.ply"])
def test_export_round_trip(addon, shared_data, tmp_path, name):
    path = shared_data(f"scenes/{name}")
    import_splats(path)
    out = tmp_path / "out.ply"
    assert bpy.ops.dresg.export_splats(filepath=str(out)) == {"FINISHED"}
    assert_scenes_equal(read_scene(out), read_scene(path))
    if name == "graphdeco_it7000_sh3.ply":  # a canonical file written back is identical
        assert out.read_bytes() == path.read_bytes()


def test_export_keeps_stylized_colours_geometry_and_extras(addon, tmp_path):
    from stylize_gaussians.operators.splat_object import write_colors, write_geometry

    rng = np.random.default_rng(3)
    n = 50
    scene = GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=rng.normal(-3, 0.5, size=(n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacity_logits=rng.normal(size=n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(size=(n, 3, 3)).astype(np.float32),
        extras={"segment": rng.integers(0, 9, n).astype(np.uint8)},
    )
    source = tmp_path / "source.ply"
    write_scene(scene, source)
    obj = import_splats(source)
    new_dc = rng.normal(size=(n, 3)).astype(np.float32)
    moved = scene.means + 0.01
    write_colors(obj, new_dc)
    write_geometry(obj, moved, scene.log_scales - 0.02, scene.quats[:, [1, 0, 2, 3]])
    obj["dresg_sh_rest"] = "zero"
    out = tmp_path / "out.ply"
    bpy.ops.dresg.export_splats(filepath=str(out))
    back = read_scene(out)
    np.testing.assert_array_equal(back.sh_dc, new_dc)
    np.testing.assert_array_equal(back.means, moved)
    np.testing.assert_array_equal(back.log_scales, scene.log_scales - 0.02)
    np.testing.assert_array_equal(back.quats, scene.quats[:, [1, 0, 2, 3]])
    np.testing.assert_array_equal(back.opacity_logits, scene.opacity_logits)
    assert back.sh_rest.shape == scene.sh_rest.shape and not back.sh_rest.any()
    assert back.extras["segment"].dtype == np.uint8
    np.testing.assert_array_equal(back.extras["segment"], scene.extras["segment"])


def test_restore_original_colours_is_lossless(addon, shared_data):
    from stylize_gaussians.operators.splat_object import scene_from_object, write_colors, write_geometry

    obj = import_splats(shared_data("scenes/luigi.ply"))
    original = scene_from_object(obj)
    rng = np.random.default_rng(0)
    write_colors(obj, rng.normal(size=original.sh_dc.shape).astype(np.float32))
    write_geometry(obj, original.means * 1.01, original.log_scales + 0.01, original.quats * 2)
    obj["dresg_sh_rest"] = "zero"
    obj["dresg_stylize_settings"] = "{}"
    assert not np.array_equal(
        attribute(obj, sm.COLOR), sm.display_colors(original.sh_dc, sm.sigmoid(original.opacity_logits))
    )
    assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
    assert_scenes_equal(scene_from_object(obj), original)
    np.testing.assert_array_equal(
        attribute(obj, sm.COLOR), sm.display_colors(original.sh_dc, sm.sigmoid(original.opacity_logits))
    )
    np.testing.assert_array_equal(attribute(obj, sm.ROTATION), sm.unit_quaternions(original.quats))
    assert sm.MEANS_ORIGINAL not in obj.data.attributes and "dresg_stylize_settings" not in obj


def _synthetic_scene(n=3, color=(0.8, 0.3, 0.1), spread=1.0, seed=0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    sh_dc = np.tile((np.asarray(color, np.float32) - 0.5) / SH_C0, (n, 1)).astype(np.float32)
    return GaussianScene(
        means=(spread * rng.normal(size=(n, 3))).astype(np.float32),
        log_scales=np.log(rng.uniform(0.05, 0.3, size=(n, 3))).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacity_logits=np.full(n, 4.0, np.float32),
        sh_dc=sh_dc,
    )


@pytest.mark.parametrize("shape", ["ICO", "DISK"])
def test_preview_instances_follow_scale_and_rotation(addon, tmp_path, shape):
    from stylize_gaussians.operators.splat_nodes import ensure_shape_object

    scene = _synthetic_scene(n=4)
    write_scene(scene, tmp_path / "s.ply")
    factor = 1.5
    obj = import_splats(tmp_path / "s.ply", shape=shape, scale_factor=factor)
    template = ensure_shape_object(shape).data
    unit = np.array([v.co for v in template.vertices])  # [V, 3]
    realized = evaluated_mesh(obj)
    positions = np.array([v.co for v in realized.vertices]).reshape(len(scene), len(unit), 3)
    q = sm.unit_quaternions(scene.quats).astype(np.float64)
    w, x, y, z = q.T
    rotations = np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    ).transpose(2, 0, 1)  # [N, 3, 3]
    for i in range(len(scene)):
        local = positions[i] - scene.means[i]  # [V, 3] in the splat's frame once rotated back
        # Same ellipsoid: each vertex maps to the unit sphere under the Gaussian's inverse transform.
        back = local @ rotations[i] / (factor * scene.scales[i])
        np.testing.assert_allclose(np.linalg.norm(back, axis=1), np.linalg.norm(unit, axis=1), atol=2e-4)
        if shape == "DISK":  # a flat disk across the two largest axes: no extent along the smallest
            smallest = np.argmin(scene.scales[i])
            np.testing.assert_allclose(local @ rotations[i][:, smallest], 0.0, atol=1e-5)
    assert realized.color_attributes.active_color_name == sm.COLOR
    np.testing.assert_allclose(
        np.array([c.color for c in realized.attributes[sm.COLOR].data])[:: len(unit)],
        attribute(obj, sm.COLOR),
        atol=1e-6,
    )


def test_display_options_hide_splats_but_keep_the_data(addon, tmp_path):
    from stylize_gaussians.operators.splat_nodes import INPUT_MAX_SPLATS, INPUT_MIN_OPACITY, INPUT_SOLID
    from stylize_gaussians.operators.splat_object import set_modifier_input, splat_modifier

    scene = _synthetic_scene(n=200)
    scene.opacity_logits[:50] = -6.0  # opacity 0.0025
    write_scene(scene, tmp_path / "s.ply")
    obj = import_splats(tmp_path / "s.ply", min_opacity=0.02)
    per_splat = len(evaluated_mesh(obj).vertices) // 150
    assert len(evaluated_mesh(obj).vertices) == 150 * per_splat
    modifier = splat_modifier(obj)
    set_modifier_input(modifier, INPUT_MAX_SPLATS, 100)
    set_modifier_input(modifier, INPUT_MIN_OPACITY, 0.0)
    obj.data.update()
    assert len(evaluated_mesh(obj).vertices) == 100 * per_splat
    set_modifier_input(modifier, INPUT_SOLID, False)  # instances only: nothing realized
    obj.data.update()
    assert len(evaluated_mesh(obj).vertices) == 0
    assert len(obj.data.vertices) == 200


def render_workbench(path, width=96, height=72) -> np.ndarray:
    """Workbench render (flat light, attribute colours, Standard view) -> [H, W, 4] in [0, 1].

    Soft splats (EEVEE's preview) are turned off: Workbench shows the realized splats' colours."""
    from stylize_gaussians.operators.splat_nodes import INPUT_SOFT
    from stylize_gaussians.operators.splat_object import set_modifier_input, splat_modifier

    scene = bpy.context.scene
    for obj in scene.objects:
        if splat_modifier(obj) is not None:
            set_modifier_input(splat_modifier(obj), INPUT_SOFT, False)
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "FLAT"
    scene.display.shading.color_type = "VERTEX"
    scene.view_settings.view_transform = "Standard"
    scene.render.film_transparent = True
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_image(path)


def test_workbench_render_shows_the_splat_colours(addon, shared_data, tmp_path):
    # A uniform colour renders exactly (8-bit) inside the splats.
    write_scene(_synthetic_scene(n=60, spread=0.3), tmp_path / "uniform.ply")
    obj = import_splats(tmp_path / "uniform.ply")
    bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y = 96, 72
    bpy.ops.dresg.add_orbit_cameras(count=1)
    bpy.context.scene.camera = bpy.data.objects["orbit_000"]
    image = render_workbench(tmp_path / "uniform.png")
    inside = image[..., 3] > 0.999
    assert inside.sum() > 200
    np.testing.assert_allclose(image[inside][:, :3].mean(0), [0.8, 0.3, 0.1], atol=1.5 / 255)

    # A real scene: the splat pixels average to the opacity-weighted mean colour of its splats.
    bpy.data.objects.remove(obj)
    obj = import_splats(shared_data("scenes/luigi.ply"))
    for camera in [o for o in bpy.data.objects if o.type == "CAMERA"]:
        bpy.data.objects.remove(camera)
    bpy.ops.dresg.add_orbit_cameras(count=1, elevation=10.0)
    bpy.context.scene.camera = bpy.data.objects["orbit_000"]
    image = render_workbench(tmp_path / "luigi.png")
    inside = image[..., 3] > 0.999
    reference = read_scene(shared_data("scenes/luigi.ply"))
    weights = reference.opacities[:, None]
    expected = (np.clip(reference.base_colors, 0, 1) * weights).sum(0) / weights.sum()
    assert inside.sum() > 500
    np.testing.assert_allclose(image[inside][:, :3].mean(0), expected, atol=0.05)
    rows, cols = np.nonzero(inside)  # the orbit camera looks at the scene's centre
    assert abs(rows.mean() / image.shape[0] - 0.5) < 0.15 and abs(cols.mean() / image.shape[1] - 0.5) < 0.15


def test_orbit_cameras_respect_the_object_transform(addon, shared_data):
    from stylize_gaussians.operators.views import active_cameras, engine_cameras

    obj = import_splats(shared_data("scenes/luigi.ply"))
    obj.location = (3.0, -2.0, 1.0)
    obj.rotation_euler = (-1.2, 0.3, 0.7)
    obj.scale = (2.0, 2.0, 2.0)
    bpy.context.view_layer.update()
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 320, 240, 50
    assert bpy.ops.dresg.add_orbit_cameras(count=5, elevation=15.0, fov=40.0) == {"FINISHED"}
    cameras = active_cameras(scene)
    assert [c.name for c in cameras] == [f"orbit_{i:03d}" for i in range(5)]
    from_blender = engine_cameras(scene, obj, cameras)
    up = sm.local_up(np.array(obj.matrix_world))
    expected = orbit_cameras(
        read_scene(shared_data("scenes/luigi.ply")), 5, width=160, height=120, fov_deg=40.0, elevation_deg=15.0, up=up
    )
    for got, want in zip(from_blender, expected):
        assert (got.width, got.height) == (want.width, want.height)
        np.testing.assert_allclose([got.fx, got.fy, got.cx, got.cy], [want.fx, want.fy, want.cx, want.cy], rtol=1e-5)
        np.testing.assert_allclose(got.world_to_camera, want.world_to_camera, atol=1e-4)
    # Cameras live in the splat object's local frame: moving both together changes nothing.
    from mathutils import Euler, Matrix

    move = Matrix.Translation((-4.0, 1.0, 2.5)) @ Euler((0.4, -0.2, 1.1)).to_matrix().to_4x4()
    for moved in (obj, *cameras):
        moved.matrix_world = move @ moved.matrix_world
    bpy.context.view_layer.update()
    for got, want in zip(engine_cameras(scene, obj, cameras), from_blender):
        np.testing.assert_allclose(got.world_to_camera, want.world_to_camera, atol=1e-4)


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_FSIZE stands in for a full disk on Unix")
def test_export_onto_a_full_disk_reports_one_line_and_changes_nothing(addon, tmp_path):
    """Issue 19: a full disk (a file size limit here) is an error report naming the file and the reason; the
    file that was there stays, and the object's colours are untouched."""
    import resource
    import signal

    from stylize_gaussians.operators.splat_object import scene_from_object

    source = tmp_path / "source.ply"
    write_scene(_small_scene(), source)
    obj = import_splats(source)
    before = scene_from_object(obj)
    out = tmp_path / "out.ply"
    out.write_bytes(b"an older export")
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (1024, hard))
    try:
        with pytest.raises(RuntimeError) as raised:
            bpy.ops.dresg.export_splats(filepath=str(out))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, handler)
    message = str(raised.value).strip().splitlines()
    assert message == [f"Error: {out}: cannot write: File too large"], message
    assert out.read_bytes() == b"an older export" and sorted(p.name for p in tmp_path.iterdir()) == [
        "out.ply",
        "source.ply",
    ]
    np.testing.assert_array_equal(scene_from_object(obj).sh_dc, before.sh_dc)


def _small_scene(n: int = 200) -> GaussianScene:
    rng = np.random.default_rng(5)
    return GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=rng.normal(-3, 0.5, size=(n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacity_logits=rng.normal(size=n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
    )


def test_strength_blends_shown_and_exported_colours_and_survives_save_and_reload(addon, tmp_path):
    """Issue 18: the stylized colours are kept in their own attribute; Strength blends them with the originals
    live (the display colour), in the export, and after the .blend is saved and opened again."""
    from stylize_gaussians.dresg_addon.scene.gaussians import blend_coefficients
    from stylize_gaussians.operators.splat_object import has_stylized_colors, scene_from_object, write_colors

    source = tmp_path / "source.ply"
    scene = _small_scene()
    write_scene(scene, source)
    obj = import_splats(source)
    assert not has_stylized_colors(obj)
    stylized = np.random.default_rng(6).normal(size=scene.sh_dc.shape).astype(np.float32)
    write_colors(obj, stylized)
    opacity = attribute(obj, sm.OPACITY)
    np.testing.assert_array_equal(attribute(obj, sm.SH_DC), stylized)  # strength 1 by default

    obj.dresg_strength = 0.25  # the slider: its update writes the shown colours at once
    blended = blend_coefficients(scene.sh_dc, stylized, 0.25)
    np.testing.assert_array_equal(attribute(obj, sm.SH_DC), blended)
    np.testing.assert_allclose(attribute(obj, sm.COLOR), sm.display_colors(blended, opacity), atol=1e-6)
    out = tmp_path / "quarter.ply"
    assert bpy.ops.dresg.export_splats(filepath=str(out)) == {"FINISHED"}
    np.testing.assert_array_equal(read_scene(out).sh_dc, blended)
    obj.dresg_strength = 0.0
    np.testing.assert_array_equal(attribute(obj, sm.SH_DC), scene.sh_dc)

    obj.dresg_strength = 0.5
    name, saved = obj.name, tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(saved))
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    obj = bpy.data.objects[name]
    assert obj.dresg_strength == 0.5 and has_stylized_colors(obj)
    np.testing.assert_array_equal(attribute(obj, sm.SH_DC_STYLIZED), stylized)
    np.testing.assert_array_equal(attribute(obj, sm.SH_DC), blend_coefficients(scene.sh_dc, stylized, 0.5))
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
    np.testing.assert_array_equal(scene_from_object(obj).sh_dc, scene.sh_dc)
    assert not has_stylized_colors(obj)
    obj.dresg_strength = 1.0  # nothing stylized: the slider changes nothing
    np.testing.assert_array_equal(attribute(obj, sm.SH_DC), scene.sh_dc)
