"""Blender's F12 against the engine's render of the same camera: an EEVEE render of the imported Luigi must look
like `dresg render` of it (issue 10), thin splats keep their weight in EEVEE and a Workbench F12 shows the splats'
colours with the import's defaults (issue 18). bpy module, EEVEE and Workbench."""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytest.importorskip("torch")
pytestmark = pytest.mark.blender

import blender_preview  # noqa: E402  (bench/, on pytest's pythonpath; needs bpy)


@pytest.mark.slow
def test_eevee_soft_splats_look_like_the_engine_render(addon, shared_data):
    result = blender_preview.compare(
        shared_data("scenes/luigi.ply"), "Y_UP_TO_BLENDER", width=160, height=120, samples=1, view=1
    )
    assert result["covered"] > 0.05
    assert np.isfinite(result["blender"]).all() and result["blender"].max() > 0.2  # not a blank or grey render
    assert result["ssim_luminance"] >= 0.7, result["ssim_luminance"]
    assert result["mean_colour_error"] <= 0.08, result["mean_colour_error"]


@pytest.mark.slow
def test_eevee_draws_splats_thinner_than_a_pixel_with_the_rasterizers_low_pass(addon, tmp_path):
    """Sprinkles under a pixel wide: without the 0.3 px^2 low-pass EEVEE draws them thinner and fainter."""
    thin = blender_preview.thin_splats_ply(tmp_path / "thin.ply", n=1500)  # n and size keep llvmpipe under a minute
    result = blender_preview.compare(thin, "NONE", width=160, height=120, view=1)
    assert result["covered"] > 0.05
    assert result["ssim_luminance"] >= 0.75, result["ssim_luminance"]
    assert result["mean_colour_error"] <= 0.06, result["mean_colour_error"]
    # The same render without it (the bench's comparison) draws them as sparse dots.
    without = blender_preview.compare(thin, "NONE", width=160, height=120, view=1, low_pass=False)
    assert without["ssim_luminance"] < 0.5 and without["mean_colour_error"] > 0.2


def _chroma(image: np.ndarray) -> np.ndarray:
    return image.max(-1) - image.min(-1)


def test_workbench_f12_shows_the_splat_colours_with_the_import_defaults(addon, shared_data):
    result = blender_preview.compare(
        shared_data("scenes/luigi.ply"), "Y_UP_TO_BLENDER", width=160, height=120, view=1, engine_name="WORKBENCH"
    )
    covered = result["engine"].max(-1) > 0  # where the engine draws anything
    shown = result["blender"][covered]
    assert _chroma(shown).mean() > 0.5 * _chroma(result["engine"][covered]).mean()  # colours, not one grey
    assert shown.std(0).mean() > 0.05
    assert result["mean_colour_error"] <= 0.1, result["mean_colour_error"]


@pytest.mark.slow
def test_render_settings_are_put_back_after_each_render(addon, tmp_path):
    """The handlers change the splat objects' modifiers for a render only: the file keeps the user's settings."""
    from stylize_gaussians.operators.render_setup import WORKBENCH_CORE_ALPHA
    from stylize_gaussians.operators.splat_nodes import (
        INPUT_CORE_ALPHA,
        INPUT_PIXEL,
        INPUT_PIXEL_WIDTH,
        INPUT_SOFT,
        INPUT_SOLID,
    )
    from stylize_gaussians.operators.splat_object import modifier_input, splat_modifier

    thin = blender_preview.thin_splats_ply(tmp_path / "thin.ply", n=200)
    assert bpy.ops.dresg.import_splats(filepath=str(thin), axis_conversion="NONE") == {"FINISHED"}
    obj = bpy.context.active_object
    bpy.ops.dresg.add_orbit_cameras(count=2)
    scene = bpy.context.scene
    scene.camera = addon.operators.views.scene_cameras(scene)[0]
    scene.render.resolution_x, scene.render.resolution_y = 64, 48
    scene.eevee.taa_render_samples = 1  # blended splats need one; llvmpipe takes minutes for EEVEE's default 64
    modifier = splat_modifier(obj)
    names = (INPUT_SOFT, INPUT_SOLID, INPUT_PIXEL, INPUT_PIXEL_WIDTH, INPUT_CORE_ALPHA)
    before = {name: modifier_input(modifier, name) for name in names}
    assert before == {
        INPUT_SOFT: True,
        INPUT_SOLID: True,
        INPUT_PIXEL: 0.0,
        INPUT_PIXEL_WIDTH: 0.0,
        INPUT_CORE_ALPHA: 0.0,
    }
    seen = {}

    def during(scene_, *_):
        seen[scene_.render.engine] = {name: modifier_input(modifier, name) for name in before}

    bpy.app.handlers.render_post.insert(0, during)  # before the add-on's own handler puts things back
    try:
        for engine in ("BLENDER_WORKBENCH", blender_preview.eevee_engine()):
            scene.render.engine = engine
            bpy.ops.render.render()
            assert {name: modifier_input(modifier, name) for name in before} == before
    finally:
        bpy.app.handlers.render_post.remove(during)
    workbench = {**before, INPUT_SOFT: False, INPUT_CORE_ALPHA: WORKBENCH_CORE_ALPHA}
    assert seen["BLENDER_WORKBENCH"] == pytest.approx(workbench)
    eevee = seen[blender_preview.eevee_engine()]
    pixel = addon.operators.render_setup.pixel_size(scene)
    assert pixel == pytest.approx(1 / addon.operators.views.engine_cameras(scene, obj, [scene.camera])[0].fx, rel=1e-3)
    assert eevee == pytest.approx({**before, INPUT_PIXEL: pixel})


def test_render_handlers_change_the_objects_only_where_blender_says_it_is_safe(addon, tmp_path, monkeypatch, capsys):
    """An F12 in the UI calls the render handlers on the render job's thread; Blender's docs (bpy.app.handlers, "Note
    on Altering Data") say to lock the interface when a handler changes data there. Off the main thread the set-up
    runs only with the lock on (the import turns it on); Workbench renders show its effect, the object comes back."""
    import threading
    import types

    from stylize_gaussians.dresg_addon.scene.demo import demo_scene
    from stylize_gaussians.dresg_addon.scene.io import write_scene
    from stylize_gaussians.operators.splat_object import INPUT_SOFT, modifier_input, splat_modifier

    write_scene(demo_scene(0), tmp_path / "demo.ply")
    assert bpy.ops.dresg.import_splats(filepath=str(tmp_path / "demo.ply"), axis_conversion="NONE") == {"FINISHED"}
    scene = bpy.context.scene
    assert scene.render.use_lock_interface
    modifier = splat_modifier(bpy.context.active_object)
    bpy.ops.dresg.add_orbit_cameras(count=2)
    scene.camera = addon.operators.views.scene_cameras(scene)[0]
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 96, 72, 100
    scene.render.film_transparent = True
    scene.render.image_settings.file_format, scene.render.image_settings.color_mode = "PNG", "RGBA"
    render_thread = types.SimpleNamespace(current_thread=lambda: None, main_thread=threading.main_thread)
    monkeypatch.setattr(addon.operators.render_setup, "threading", render_thread)  # as F12's job thread
    soft = []
    during = lambda *_: soft.append(modifier_input(modifier, INPUT_SOFT))  # noqa: E731
    bpy.app.handlers.render_post.insert(0, during)  # before the add-on's own handler puts things back
    try:
        images = {}
        for locked in (False, True):
            scene.render.use_lock_interface = locked
            images[locked] = _eevee_rgba(scene, tmp_path / f"locked_{locked}.png")
            assert modifier_input(modifier, INPUT_SOFT) is True  # as the user left it
    finally:
        bpy.app.handlers.render_post.remove(during)
    assert soft == [True, False]  # unlocked: left alone; locked: the Workbench set-up
    assert "Lock Interface is off" in capsys.readouterr().out
    covered = (images[True][..., 3] > 0.5) & (images[False][..., 3] > 0.5)
    assert covered.mean() > 0.02, covered.mean()
    assert _chroma(images[True][..., :3])[covered].mean() > 2 * _chroma(images[False][..., :3])[covered].mean() + 0.1


def _eevee_rgba(scene, path) -> np.ndarray:
    from stylize_gaussians.dresg_addon.util.imageio import read_image

    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_image(str(path))


@pytest.mark.slow
def test_orthographic_renders_get_the_low_pass_as_a_pixel_width(addon, tmp_path):
    """An orthographic camera's pixels do not grow with depth: the low-pass comes from its pixel width. Its render
    of sub-pixel sprinkles matches a perspective camera far away with a long lens (nearly orthographic) framing
    the same, which the engine-checked perspective low-pass draws; without the low-pass it is sparse dots."""
    from mathutils import Vector
    from stylize_gaussians.operators.splat_nodes import INPUT_PIXEL, INPUT_PIXEL_WIDTH

    thin = blender_preview.thin_splats_ply(tmp_path / "thin.ply", n=800)
    assert bpy.ops.dresg.import_splats(filepath=str(thin), axis_conversion="NONE") == {"FINISHED"}
    obj = bpy.context.active_object
    obj.scale = (2.0, 2.0, 2.0)  # the pixel width goes into the object's units
    scene = bpy.context.scene
    scene.render.engine = blender_preview.eevee_engine()
    scene.eevee.taa_render_samples = 1
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 160, 120, 100
    scene.render.film_transparent = True
    scene.render.image_settings.file_format, scene.render.image_settings.color_mode = "PNG", "RGBA"
    camera = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    direction = Vector((0.0, -1.0, 0.8)).normalized()  # from the torus's centre towards the camera
    camera.rotation_euler = direction.to_track_quat("Z", "Y").to_euler()  # the camera looks down its -Z

    distance, far = 8.0, 400.0
    camera.location = direction * far
    camera.data.type, camera.data.lens, camera.data.clip_end = "PERSP", 50.0 * far / distance, 2 * far
    perspective = _eevee_rgba(scene, tmp_path / "perspective.png")
    camera.location = direction * distance
    camera.data.type = "ORTHO"
    camera.data.ortho_scale = camera.data.sensor_width * distance / 50.0  # the same framing at the torus
    seen = {}

    def during(scene_, *_):
        modifier = addon.operators.splat_object.splat_modifier(obj)
        seen.update(
            {
                name: addon.operators.splat_object.modifier_input(modifier, name)
                for name in (INPUT_PIXEL, INPUT_PIXEL_WIDTH)
            }
        )

    bpy.app.handlers.render_post.insert(0, during)
    try:
        orthographic = _eevee_rgba(scene, tmp_path / "orthographic.png")
    finally:
        bpy.app.handlers.render_post.remove(during)
    assert seen[INPUT_PIXEL] == 0.0
    assert seen[INPUT_PIXEL_WIDTH] == pytest.approx(camera.data.ortho_scale / 160 / 2.0, rel=1e-5)
    with blender_preview.without_render_setup(addon):
        unfiltered = _eevee_rgba(scene, tmp_path / "unfiltered.png")

    covered = perspective[..., 3] > 0.5
    assert covered.mean() > 0.05

    def luminance_ssim(image):  # straight alpha over black
        return blender_preview.luminance_ssim(
            image[..., :3] * image[..., 3:], perspective[..., :3] * perspective[..., 3:], covered
        )

    assert luminance_ssim(orthographic) >= 0.9
    assert luminance_ssim(unfiltered) < 0.6
