"""Stylize Gaussians end to end in the bpy module: background runs, the worker thread, cancel, restore,
view selection and the headless script. Small settings (tiny renders, few steps) keep it CPU-fast."""

import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.method.optim import GeometryBounds
from dresg_addon.scene.io import read_scene
from dresg_addon.util.imageio import read_image

bpy = pytest.importorskip("bpy")
pytest.importorskip("torch")
pytestmark = pytest.mark.blender
REPO = Path(__file__).resolve().parents[1]
SETTINGS = {  # a quick run: 2 stages on 64x48 renders of 2 views
    "stages": 2,
    "proposal_width": 64,
    "proposal_height": 48,
    "max_views": 2,
    "render_scale": 0.5,
    "optimize_geometry": False,
}


@pytest.fixture
def luigi(addon, shared_data):
    """Luigi imported, 2 orbit cameras at 128x96, the quick settings and a style image."""
    path = shared_data("scenes/luigi.ply")
    bpy.ops.dresg.import_splats(filepath=str(path))
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 128, 96, 100
    bpy.ops.dresg.add_orbit_cameras(count=2, elevation=10.0)
    settings = scene.dresg
    for name, value in SETTINGS.items():
        setattr(settings, name, value)
    settings.style_path = str(shared_data("styles/starry_night.jpg"))
    return bpy.context.active_object


def attribute(obj, name):
    from stylize_gaussians.operators.splat_object import read_attribute

    return read_attribute(obj.data, name)


def render_mean_colour(path) -> np.ndarray:
    scene = bpy.context.scene
    scene.camera = bpy.data.objects["orbit_000"]
    scene.render.engine = "BLENDER_WORKBENCH"  # shows the realized splats, not the soft ones
    from stylize_gaussians.operators import render_setup
    from stylize_gaussians.operators.splat_nodes import INPUT_SOFT
    from stylize_gaussians.operators.splat_object import set_modifier_input, splat_modifier

    for obj in scene.objects:
        if splat_modifier(obj) is not None:
            set_modifier_input(splat_modifier(obj), INPUT_SOFT, False)
    # The Solid preview's look (every splat at Scale Factor sigmas), not F12's opacity-sized cores.
    render_setup.unregister()
    scene.display.shading.light = "FLAT"
    scene.display.shading.color_type = "VERTEX"
    scene.view_settings.view_transform = "Standard"
    scene.render.film_transparent = True
    scene.render.filepath = str(path)
    try:
        bpy.ops.render.render(write_still=True)
    finally:
        render_setup.register()
    image = read_image(path)
    inside = image[..., 3] > 0.999
    assert inside.sum() > 300
    return image[inside][:, :3].mean(0)


def engine_mean_colour(obj) -> np.ndarray:
    """Mean colour of the engine's render of ``obj`` from the camera ``render_mean_colour`` uses, covered pixels."""
    from stylize_gaussians.operators.splat_object import scene_from_object
    from stylize_gaussians.operators.views import engine_cameras

    from dresg_addon.raster import render_scene

    camera = engine_cameras(bpy.context.scene, obj, [bpy.data.objects["orbit_000"]])[0]
    out = render_scene(scene_from_object(obj), camera)
    covered = out.alpha.numpy() > 0.5
    return out.rgb.numpy()[covered].mean(0)


def test_background_stylize_changes_colours_only(luigi, tmp_path):
    obj = luigi
    before = {name: attribute(obj, name) for name in (sm.SH_DC, sm.OPACITY, sm.LOG_SCALE, sm.QUAT)}
    positions_before = np.array([v.co for v in obj.data.vertices])
    render_before = render_mean_colour(tmp_path / "before.png")
    engine_before = engine_mean_colour(obj)

    assert bpy.app.background
    assert bpy.ops.dresg.stylize() == {"FINISHED"}  # background mode: synchronous
    from stylize_gaussians.operators import job
    from stylize_gaussians.operators.tasks import JobState

    run = job.StylizeJob.current()
    assert run.state is JobState.DONE and run.stages_applied >= 1
    sh_dc = attribute(obj, sm.SH_DC)
    assert np.abs(sh_dc - before[sm.SH_DC]).mean() > 1e-3
    assert np.isfinite(sh_dc).all()
    for name in (sm.OPACITY, sm.LOG_SCALE, sm.QUAT):
        np.testing.assert_array_equal(attribute(obj, name), before[name])
    np.testing.assert_array_equal(np.array([v.co for v in obj.data.vertices]), positions_before)
    np.testing.assert_array_equal(attribute(obj, sm.SH_DC_ORIGINAL), before[sm.SH_DC])
    np.testing.assert_allclose(attribute(obj, sm.COLOR), sm.display_colors(sh_dc, before[sm.OPACITY]), atol=1e-6)
    assert "dresg_stylize_settings" in obj

    # The viewport look follows: Blender's render of the splats moves as the engine's render of the stylized
    # scene from the same camera does (the splats' mean colour would be a poor proxy: a painted surface varies).
    render_after = render_mean_colour(tmp_path / "after.png")
    engine_after = engine_mean_colour(obj)
    np.testing.assert_allclose(render_after, engine_after, atol=0.1)
    assert np.abs(render_after - render_before).max() > 0.01
    assert np.dot(render_after - render_before, engine_after - engine_before) > 0

    # Export carries the stylized colours; the per-view images of the last stage open as images.
    bpy.ops.dresg.export_splats(filepath=str(tmp_path / "out.ply"))
    exported = read_scene(tmp_path / "out.ply")
    np.testing.assert_array_equal(exported.sh_dc, sh_dc)
    assert bpy.ops.dresg.open_view_images() == {"FINISHED"}
    for view, kinds in run.images.items():
        for kind, array in kinds.items():
            image = bpy.data.images[f"DReSG {view} {kind}"]
            assert tuple(image.size) == (array.shape[1], array.shape[0])


def test_threaded_run_cancels_and_restores(luigi):
    from stylize_gaussians.operators.splat_object import scene_from_object
    from stylize_gaussians.operators.stylize import prepare_job
    from stylize_gaussians.operators.tasks import JobState

    obj = luigi
    original = scene_from_object(obj)
    settings = bpy.context.scene.dresg
    settings.stages, settings.optimize_geometry = 6, True
    run, _ = prepare_job(bpy.context)
    run.make_current()
    run.start()
    deadline = time.monotonic() + 300
    while run.stages_applied < 1 and run.running and time.monotonic() < deadline:
        run.poll()
        time.sleep(0.05)
    assert run.stages_applied >= 1, run.error
    run.cancel()
    cancelled_at = time.monotonic()
    while not run.poll():
        time.sleep(0.02)
    run.wait(30)
    print(f"stopped {time.monotonic() - cancelled_at:.2f} s after cancel")
    assert run.state is JobState.CANCELLED and run.stages_applied < 6

    # One consistent stage: display colours match the stored coefficients, geometry within its bounds.
    sh_dc, opacity = attribute(obj, sm.SH_DC), attribute(obj, sm.OPACITY)
    np.testing.assert_allclose(attribute(obj, sm.COLOR), sm.display_colors(sh_dc, opacity), atol=1e-6)
    moved = np.array([v.co for v in obj.data.vertices])
    extent = float(re.search(r"scene extent ([0-9.e+-]+):", "\n".join(run.messages)).group(1))
    assert np.abs(moved - original.means).max() <= GeometryBounds().means * extent * (1 + 1e-5) + 1e-6
    np.testing.assert_array_equal(attribute(obj, sm.MEANS_ORIGINAL), original.means)
    np.testing.assert_array_equal(opacity, sm.sigmoid(original.opacity_logits))

    assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
    restored = scene_from_object(obj)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc"):
        np.testing.assert_array_equal(getattr(restored, name), getattr(original, name), err_msg=name)


def test_worker_errors_reach_the_job_and_the_report(luigi, tmp_path):
    from stylize_gaussians.operators import job
    from stylize_gaussians.operators.tasks import JobState

    settings = bpy.context.scene.dresg
    settings.proposal = "sd15"
    missing = tmp_path / "no-model"
    with pytest.raises(RuntimeError, match="no-model"):
        bpy.ops.dresg.stylize(model_path=str(missing))
    run = job.StylizeJob.current()
    assert run.state is JobState.ERROR and "no-model" in run.error
    np.testing.assert_array_equal(attribute(luigi, sm.SH_DC), attribute(luigi, sm.SH_DC_ORIGINAL))


def test_select_views_by_coverage_ticks_the_engine_choice(luigi):
    from stylize_gaussians.dresg_addon.method.views import select_active_views
    from stylize_gaussians.operators.splat_object import scene_from_object
    from stylize_gaussians.operators.views import fitting_cameras, scene_cameras

    bpy.ops.dresg.add_orbit_cameras(count=4, elevation=40.0)
    scene = bpy.context.scene
    objects = scene_cameras(scene)
    assert len(objects) == 6
    assert bpy.ops.dresg.select_views() == {"FINISHED"}
    expected = select_active_views(
        scene_from_object(luigi), fitting_cameras(scene, luigi, objects), scene.dresg.config()
    )
    assert [obj.dresg_view.use for obj in objects] == [i in expected.indices for i in range(len(objects))]
    assert [obj.dresg_view.pick for obj in objects] == [
        expected.indices.index(i) + 1 if i in expected.indices else 0 for i in range(len(objects))
    ]
    np.testing.assert_allclose([obj.dresg_view.coverage for obj in objects], expected.per_view_coverage, rtol=1e-6)


@pytest.mark.slow
def test_headless_script_with_a_blend_file(addon, shared_data, tmp_path):
    # A .blend with two cameras framing Luigi (imported with the OpenCV conversion, as the script does).
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = 128, 96
    bpy.ops.dresg.import_splats(filepath=str(shared_data("scenes/luigi.ply")))
    bpy.ops.dresg.add_orbit_cameras(count=2)
    bpy.data.objects.remove(bpy.context.active_object)  # the script imports the splats itself
    blend = tmp_path / "cameras.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))

    out = tmp_path / "stylized.ply"
    command = [sys.executable, str(REPO / "scripts" / "stylize_headless.py"), "--blend", str(blend)]
    command += ["--ply", str(shared_data("scenes/luigi.ply")), "--style", str(shared_data("styles/the_scream.jpg"))]
    command += ["--out", str(out), "--stages", "1", "--width", "64"]
    command += ["--height", "48", "--max-views", "2", "--render-scale", "0.5", "--no-geometry"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "using the .blend's cameras: orbit_000, orbit_001" in result.stdout
    assert "[stylize]" in result.stdout  # printed progress
    source, stylized = read_scene(shared_data("scenes/luigi.ply")), read_scene(out)
    np.testing.assert_array_equal(stylized.means, source.means)
    np.testing.assert_array_equal(stylized.opacity_logits, source.opacity_logits)
    assert np.abs(stylized.sh_dc - source.sh_dc).mean() > 1e-3

    bad = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "stylize_headless.py"), "--ply", str(tmp_path / "nope.ply")]
        + ["--style", "x.jpg", "--out", str(tmp_path / "o.ply")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "nope.ply" in bad.stderr


@pytest.mark.slow
def test_headless_script_without_a_blend_file(shared_data, tmp_path):
    from dresg_addon.scene.camera_io import write_cameras_json
    from dresg_addon.scene.orbit import orbit_cameras

    ply, style = shared_data("scenes/luigi.ply"), shared_data("styles/the_scream.jpg")
    quick = ["--stages", "1", "--width", "64", "--height", "48"]
    quick += ["--max-views", "2", "--render-scale", "0.5", "--no-geometry"]
    script = [sys.executable, str(REPO / "scripts" / "stylize_headless.py"), "--ply", str(ply), "--style", str(style)]

    # No .blend: Blender's startup camera is not a view; the orbit ring is, and the script says so.
    result = subprocess.run(
        script + ["--out", str(tmp_path / "a.ply"), "--orbit", "3"] + quick, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "no .blend: starting from an empty scene" in result.stdout
    assert "no cameras: added 3 orbit cameras" in result.stdout
    assert "Camera" not in result.stdout.replace("Cameras", "")
    assert re.search(r"active views: 2 of 3", result.stdout)

    # --cameras: the file's cameras are the views.
    cameras = orbit_cameras(read_scene(ply), 4, width=96, height=72, up=(0.0, 1.0, 0.0))
    write_cameras_json(tmp_path / "cameras.json", cameras)
    result = subprocess.run(
        script
        + ["--out", str(tmp_path / "b.ply"), "--cameras", str(tmp_path / "cameras.json"), "--axes", "y-up"]
        + quick,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert f"using the cameras of {tmp_path / 'cameras.json'}" in result.stdout
    assert re.search(r"active views: 2 of 4", result.stdout)
    assert read_scene(tmp_path / "b.ply").means.shape == read_scene(ply).means.shape
