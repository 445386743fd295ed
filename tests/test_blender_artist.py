"""What an artist meets in Blender (issue 10): words, camera import and clipping, Max Views, the fit
resolution, the y-up conversion, a Stylize button that says why it is grey, and background jobs that leave bpy to
the main thread (issue 18). bpy module."""

import sys
import threading
import time
import types
from pathlib import Path

import numpy as np
import pytest
from messages import names

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.scene.camera_io import write_cameras_json
from dresg_addon.scene.gaussians import GaussianScene
from dresg_addon.scene.io import write_scene
from dresg_addon.scene.orbit import orbit_cameras

bpy = pytest.importorskip("bpy")
from mathutils import Vector  # noqa: E402  (comes with bpy)

pytestmark = pytest.mark.blender
REPO = Path(__file__).resolve().parents[1]
JARGON = ("w_c", "Sec.", "Eq.", "abar", "gamma", "OPENCV", "snr-", "\n")


def _scene(n: int = 60, spread: float = 1.0, centre=(0.0, 0.0, 0.0), seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    return GaussianScene(
        means=(np.asarray(centre) + spread * rng.normal(size=(n, 3))).astype(np.float32),
        log_scales=np.full((n, 3), np.log(0.05 * spread), np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        opacity_logits=np.full(n, 2.0, np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
    )


def _import(tmp_path, scene: GaussianScene, **options):
    write_scene(scene, tmp_path / "s.ply")
    assert bpy.ops.dresg.import_splats(filepath=str(tmp_path / "s.ply"), **options) == {"FINISHED"}
    return bpy.context.active_object


def _descriptions(rna) -> list[tuple[str, str]]:
    out = []
    for prop in rna.properties:
        if prop.identifier in {"rna_type", "name"}:
            continue
        out.append((prop.identifier, prop.description))
        for item in getattr(prop, "enum_items", []):
            out.append((f"{prop.identifier}:{item.identifier}", item.description))
            out.append((f"{prop.identifier}:{item.identifier} label", item.name))
    return out


def test_every_setting_and_operator_speaks_to_an_artist(addon):
    settings = bpy.types.Scene.bl_rna.properties["dresg"].fixed_type
    texts = _descriptions(settings) + _descriptions(bpy.types.Object.bl_rna.properties["dresg_view"].fixed_type)
    for name, cls in vars(bpy.types).items():
        if name.startswith("DRESG_OT_"):
            texts.append((name, cls.bl_rna.description))
            texts += [(f"{name}.{k}", v) for k, v in _descriptions(cls.bl_rna)]
    for name, text in texts:
        assert text.strip(), f"{name} has no tooltip or label"
        assert not any(word in text for word in JARGON), f"{name}: {text!r}"
    for menu in ("medium", "proposal", "sh_rest", "selection", "view_source", "fit_resolution"):  # labels
        assert all(item.name != item.identifier for item in settings.properties[menu].enum_items)
    assert {item.name for item in settings.properties["preset"].enum_items} >= {"Standard", "Preview"}
    assert addon.ui.panels.CATEGORY == "Stylize Gaussians"


def test_stylize_is_grey_until_a_style_image_is_chosen(addon, tmp_path, monkeypatch):
    monkeypatch.setattr(addon.operators.dependencies, "torch_available", lambda: True)
    _import(tmp_path, _scene())
    settings = bpy.context.scene.dresg
    assert not bpy.ops.dresg.stylize.poll()
    settings.style_path = str(tmp_path / "painting.jpg")
    assert bpy.ops.dresg.stylize.poll()
    settings.style_source = "IMAGE"
    assert not bpy.ops.dresg.stylize.poll()
    settings.style_image = bpy.data.images.new("painting", 4, 4)
    assert bpy.ops.dresg.stylize.poll()


def test_orbit_cameras_clip_to_the_scene_far_from_the_origin(addon, tmp_path):
    # A scene 2000 units across sitting 3000 units away: Blender's default clip_end of 100 would show nothing.
    obj = _import(tmp_path, _scene(spread=500.0, centre=(3000.0, 0.0, 0.0)))
    obj.scale = (2.0, 2.0, 2.0)
    bpy.context.view_layer.update()
    bpy.ops.dresg.add_orbit_cameras(count=4)
    box = np.array([tuple(obj.matrix_world @ Vector(corner)) for corner in obj.bound_box])
    for camera_object in bpy.data.collections["DReSG Orbit Cameras"].objects:
        position = np.array(camera_object.matrix_world.translation)
        farthest = np.linalg.norm(box - position, axis=1).max()
        assert camera_object.data.clip_end >= farthest
        assert 0 < camera_object.data.clip_start <= camera_object.data.clip_end / 1e3


def test_import_cameras_reproduces_the_file_and_sets_the_render_size(addon, tmp_path):
    scene = _scene()
    cameras = orbit_cameras(scene, 3, width=160, height=120, fov_deg=40.0)
    write_cameras_json(tmp_path / "cameras.json", cameras)
    obj = _import(tmp_path, scene)
    assert bpy.ops.dresg.import_cameras(filepath=str(tmp_path / "cameras.json")) == {"FINISHED"}
    render = bpy.context.scene.render
    assert (render.resolution_x, render.resolution_y, render.resolution_percentage) == (160, 120, 100)
    views = addon.operators.views
    objects = views.scene_cameras(bpy.context.scene)
    assert len(objects) == 3 and all(o.dresg_view.use for o in objects)
    back = views.engine_cameras(bpy.context.scene, obj, objects)
    by_name = {c.name: c for c in cameras}
    for camera in back:
        original = by_name[camera.name]
        assert (camera.width, camera.height) == (original.width, original.height)
        np.testing.assert_allclose(
            [camera.fx, camera.fy, camera.cx, camera.cy],
            [original.fx, original.fy, original.cx, original.cy],
            rtol=1e-5,
        )
        np.testing.assert_allclose(camera.world_to_camera, original.world_to_camera, atol=1e-4)
    with pytest.raises(RuntimeError, match="nope.json"):
        bpy.ops.dresg.import_cameras(filepath=str(tmp_path / "nope.json"))


def test_max_views_applies_to_ticked_cameras(addon, tmp_path):
    _import(tmp_path, _scene())
    settings = bpy.context.scene.dresg
    from dresg_addon.util.imageio import write_image

    write_image(tmp_path / "style.png", np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32))
    settings.style_path = str(tmp_path / "style.png")
    bpy.ops.dresg.add_orbit_cameras(count=5)  # all ticked
    prepare_job = addon.operators.stylize.prepare_job
    settings.max_views = 2
    run, note = prepare_job(bpy.context)
    assert run.views is None and len(run.cameras) == 5  # the engine picks 2 of the 5 by coverage
    assert note == "Views: 5 ticked cameras: the 2 that see the most are used"
    settings.max_views = 0
    run, note = prepare_job(bpy.context)
    assert run.views == [0, 1, 2, 3, 4] and note == "Views: 5 ticked cameras: only they will be used"


def test_stroke_size_paint_scene_light_and_medium_reach_the_run(addon, tmp_path):
    settings_rna = bpy.types.Scene.bl_rna.properties["dresg"].fixed_type.properties
    stroke, weight, light = settings_rna["stroke_size"], settings_rna["scene_weight"], settings_rna["scene_light"]
    assert (stroke.name, weight.name, light.name) == ("Stroke Size", "Paint <-> Scene", "Scene Light")
    assert (light.hard_min, light.hard_max, light.subtype) == (0.0, 1.0, "FACTOR")
    assert (stroke.soft_min, stroke.soft_max, stroke.hard_min, stroke.hard_max) == (0.5, 4.0, 0.25, 8.0)
    assert (weight.hard_min, weight.hard_max, weight.subtype) == (0.0, 1.0, "FACTOR")
    assert "content_weight" not in settings_rna
    config = addon.dresg_addon.method.config
    settings = bpy.context.scene.dresg
    assert settings.stroke_size == config.PRESETS[config.DEFAULT_PRESET].stroke_size
    assert settings.scene_weight == pytest.approx(config.PRESETS[config.DEFAULT_PRESET].scene_weight)
    assert settings.scene_light == pytest.approx(config.PRESETS[config.DEFAULT_PRESET].scene_light)
    _import(tmp_path, _scene())
    from dresg_addon.util.imageio import write_image

    write_image(tmp_path / "style.png", np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32))
    settings.style_path = str(tmp_path / "style.png")
    bpy.ops.dresg.add_orbit_cameras(count=2)
    settings.stroke_size, settings.scene_weight, settings.scene_light = 2.5, 0.8, 0.0
    medium = settings_rna["medium"]
    assert medium.name == "Medium" and [item.identifier for item in medium.enum_items] == ["auto", "paint", "ink"]
    assert settings.medium == config.PRESETS[config.DEFAULT_PRESET].medium == "auto"
    settings.medium = "ink"
    run, _ = addon.operators.stylize.prepare_job(bpy.context)
    proposal = run.config
    assert (proposal.stroke_size, proposal.scene_weight, proposal.scene_light) == pytest.approx((2.5, 0.8, 0.0))
    assert proposal.medium == "ink"
    settings.preset = "preview"  # a preset brings its own values back
    assert settings.scene_weight == pytest.approx(config.PRESETS["preview"].scene_weight)
    assert settings.stroke_size == config.PRESETS["preview"].stroke_size
    assert settings.scene_light == pytest.approx(config.PRESETS["preview"].scene_light)
    assert settings.medium == "auto"
    panel = [args[1] for name, args, kw in _drawn(addon.ui.panels.DRESG_PT_style) if name == "prop"]
    assert panel.index("stroke_size") < panel.index("scene_weight") < panel.index("scene_light") < panel.index("medium")
    assert panel.index("preset") < panel.index("stroke_size")  # the preset above the controls it sets

    panels = addon.ui.panels

    def active(prop: str) -> bool:  # the row's last `active` before the property is drawn in it
        calls = _drawn(panels.DRESG_PT_style) + _drawn(panels.DRESG_PT_style_advanced)
        at = next(i for i, (name, args, _) in enumerate(calls) if name == "prop" and args[1] == prop)
        return calls[at - 1] != ("=active", (False,), {})

    assert all(active(prop) for prop in ("stages", "optimize_geometry", "scene_light"))
    settings.medium = "ink"  # drawn in one stage of its own, colours only, with no scene light
    assert not any(active(prop) for prop in ("stages", "optimize_geometry", "scene_light"))
    settings.proposal = "sd15"  # its stages are the scheduler's
    assert active("stages") and not active("optimize_geometry")


def _quick_selection_scene(tmp_path):
    """300 splats imported, 3 orbit cameras and a one-stage preview at 32x24: (the object, the settings)."""
    obj = _import(tmp_path, _scene(n=300, spread=0.5))
    bpy.ops.dresg.add_orbit_cameras(count=3)
    settings = bpy.context.scene.dresg
    for name, value in {"stages": 1, "proposal_width": 32, "proposal_height": 24}.items():
        setattr(settings, name, value)
    settings.preset, settings.max_views = "preview", 3
    return obj, settings


def _drawn(panel) -> list:
    """The layout calls of a panel's draw()."""
    calls = []

    class Layout:
        def __getattr__(self, name):
            def call(*args, **kwargs):
                calls.append((name, args, kwargs))
                return Layout()

            return call

        def __setattr__(self, name, value):
            calls.append(("=" + name, (value,), {}))

    panel.draw(types.SimpleNamespace(layout=Layout()), bpy.context)
    return calls


def test_fit_resolution_defaults_to_the_presets_size(addon, tmp_path):
    _import(tmp_path, _scene())
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 1920, 1080, 50
    settings = scene.dresg
    from dresg_addon.util.imageio import write_image

    write_image(tmp_path / "style.png", np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32))
    settings.style_path = str(tmp_path / "style.png")
    bpy.ops.dresg.add_orbit_cameras(count=2)
    stylize = addon.operators.stylize
    assert settings.fit_resolution == "PRESET"
    assert addon.operators.views.fit_size(scene) == (448, 252)
    run, _ = stylize.prepare_job(bpy.context)
    assert {(c.width, c.height) for c in run.cameras} == {(448, 252)}
    settings.fit_resolution = "SCENE"
    assert addon.operators.views.fit_size(scene) == (960, 540)
    run, _ = stylize.prepare_job(bpy.context)
    assert {(c.width, c.height) for c in run.cameras} == {(960, 540)}


def test_y_up_files_stand_upright(addon, tmp_path):
    # A column of splats along the file's +y: with the y-up conversion it points along Blender's +z.
    scene = _scene(n=20)
    scene.means[:] = np.stack([np.zeros(20), np.linspace(0.0, 2.0, 20), np.zeros(20)], 1)
    obj = _import(tmp_path, scene, axis_conversion="Y_UP_TO_BLENDER")
    world = np.array(obj.matrix_world)
    tip = world[:3, :3] @ scene.means[-1]
    np.testing.assert_allclose(tip, [0.0, 0.0, 2.0], atol=1e-6)
    np.testing.assert_allclose(sm.local_up(world), [0.0, 1.0, 0.0], atol=1e-6)  # float32 world matrix
    assert obj["dresg_axis_conversion"] == "Y_UP_TO_BLENDER"
    assert sm.AXIS_LABELS["Y_UP_TO_BLENDER"] == "Y up"


def test_automatic_axes_follow_the_cameras_beside_the_file(addon, tmp_path):
    scene = _scene()
    write_cameras_json(tmp_path / "cameras.json", orbit_cameras(scene, 3, up=(0.0, 1.0, 0.0)))
    obj = _import(tmp_path, scene)  # Axes: Automatic, the default
    assert obj["dresg_axis_conversion"] == "Y_UP_TO_BLENDER"
    (tmp_path / "cameras.json").unlink()
    obj = _import(tmp_path, scene)
    assert obj["dresg_axis_conversion"] == "OPENCV_TO_BLENDER"


def test_view_selection_runs_on_a_worker_thread_and_cancels(addon, tmp_path):
    pytest.importorskip("torch")
    views = addon.operators.views
    obj = _import(tmp_path, _scene())
    bpy.ops.dresg.add_orbit_cameras(count=4)
    scene = bpy.context.scene
    objects = views.scene_cameras(scene)
    cameras = views.fitting_cameras(scene, obj, objects)
    splats = addon.operators.splat_object.scene_from_object(obj)

    JobState = addon.operators.tasks.JobState
    job = views.SelectionJob(splats, cameras, scene.dresg.config(), [o.name for o in objects])
    job.start()
    assert job.wait(120)
    assert job.state is JobState.DONE and not job.error
    expected = addon.dresg_addon.method.views.select_active_views(splats, cameras, scene.dresg.config())
    assert job.result.indices == expected.indices and job.result.per_view_coverage == expected.per_view_coverage
    assert job.fraction == 1.0 and job.reports == [(1, 4), (2, 4), (3, 4), (4, 4)]  # a report after each camera

    many = cameras * 8  # far more renders than the worker can do before the cancel below
    stopped = views.SelectionJob(splats, many, scene.dresg.config(), [o.name for o in objects] * 8)
    stopped.make_current()
    stopped.start()
    stopped.cancel()  # the engine checks before each camera's render
    assert views.SelectionJob.active() is stopped and stopped.state is JobState.CANCELLING
    assert stopped.wait(120)
    assert stopped.state is JobState.CANCELLED and stopped.result is None and len(stopped.reports) < len(many)
    assert views.SelectionJob.active() is None


class _MainThreadOnly:
    """bpy as it must be treated: any use off Blender's main thread fails instead of crashing Blender later."""

    def __init__(self, module) -> None:
        self._module = module

    def __getattr__(self, name: str):
        if threading.current_thread() is not threading.main_thread():
            raise RuntimeError(f"bpy.{name} used off the main thread")
        return getattr(self._module, name)


def test_every_background_job_leaves_bpy_to_the_main_thread(addon, tmp_path, monkeypatch):
    """View selection, a stylization and the dependency installer run on workers with bpy made to fail off the
    main thread: each finishes, and its progress and results reach the main thread through its queue."""
    pytest.importorskip("torch")
    ops = addon.operators
    obj = _import(tmp_path, _scene())
    bpy.ops.dresg.add_orbit_cameras(count=4)
    scene = bpy.context.scene
    objects = ops.views.scene_cameras(scene)
    cameras = ops.views.fitting_cameras(scene, obj, objects)
    splats = ops.splat_object.scene_from_object(obj)
    for module in (ops.tasks, ops.job, ops.views, ops.dependencies, ops.splat_object, ops.splat_nodes, ops.stylize):
        monkeypatch.setattr(module, "bpy", _MainThreadOnly(bpy))
    with pytest.raises(RuntimeError, match="off Blender's main thread"):  # the guard is real
        failures = []
        worker = threading.Thread(target=lambda: _catch(ops.tasks.tag_redraw, failures))
        worker.start()
        worker.join()
        raise failures[0]

    selection = ops.views.SelectionJob(splats, cameras, scene.dresg.config(), [o.name for o in objects])
    selection.start()
    assert selection.wait(120)
    assert selection.state is ops.tasks.JobState.DONE and not selection.error and selection.result.indices
    assert selection.fraction == 1.0

    config = addon.dresg_addon.method.config.preset("preview", stages=2, proposal_width=32, proposal_height=24)
    small = addon.dresg_addon.scene.orbit.orbit_cameras(splats, 2, width=32, height=24)
    style = np.random.default_rng(1).uniform(size=(24, 32, 3)).astype(np.float32)
    run = ops.job.StylizeJob(obj, splats, small, style, config)
    run.start()
    deadline = time.monotonic() + 120
    while not run.poll() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert run.state is ops.tasks.JobState.DONE, run.error
    assert run.stages_applied >= 1 and run.messages and run.fraction == 1.0

    installer = ops.dependencies.Installer([[sys.executable, "-c", "print('Collecting torch')"]])
    installer.start()
    assert installer.wait(30)
    assert installer.state is ops.tasks.JobState.DONE and installer.lines == ["Collecting torch"]


def _catch(function, failures: list) -> None:
    try:
        function()
    except Exception as error:
        failures.append(error)


@pytest.mark.slow
def test_two_paintings_on_two_selections_and_restore_per_selection(addon, tmp_path):
    """Issue 18: a run on a vertex group, then one on the Edit Mode selection with another painting: each
    changes only its splats and the second keeps the first's colours; Restore works per selection and for
    all; Select Views runs on the selection."""
    pytest.importorskip("torch")
    from dresg_addon.util.imageio import write_image

    ops = addon.operators
    sm_ = addon.dresg_addon.blender.splat_mesh
    obj, settings = _quick_selection_scene(tmp_path)
    for name, colour in (("red", (0.9, 0.1, 0.1)), ("blue", (0.1, 0.2, 0.9))):
        noise = np.random.default_rng(len(name)).uniform(-0.1, 0.1, (24, 32, 3))
        write_image(tmp_path / f"{name}.png", np.clip(np.float32(colour) + noise, 0, 1).astype(np.float32))
    original = ops.splat_object.read_attribute(obj.data, sm_.SH_DC).copy()
    x = np.array([v.co.x for v in obj.data.vertices])
    left, right = x < 0, x >= 0

    group = obj.vertex_groups.new(name="left")
    group.add([int(i) for i in np.flatnonzero(left)], 1.0, "REPLACE")
    settings.selection, settings.selection_group = "GROUP", "left"
    settings.style_path = str(tmp_path / "red.png")
    assert bpy.ops.dresg.select_views() == {"FINISHED"}
    assert bpy.ops.dresg.stylize() == {"FINISHED"}
    first = ops.splat_object.read_attribute(obj.data, sm_.SH_DC).copy()
    np.testing.assert_array_equal(first[right], original[right])
    assert (np.abs(first[left] - original[left]).max(1) > 1e-4).mean() > 0.5

    for vertex in obj.data.vertices:
        vertex.select = bool(right[vertex.index])
    settings.selection, settings.style_path = "SELECTED", str(tmp_path / "blue.png")
    assert bpy.ops.dresg.stylize() == {"FINISHED"}
    second = ops.splat_object.read_attribute(obj.data, sm_.SH_DC).copy()
    np.testing.assert_array_equal(second[left], first[left])  # the first painting's colours stay
    assert (np.abs(second[right] - original[right]).max(1) > 1e-4).mean() > 0.5
    red, blue = (0.5 + sm_.SH_C0 * second[left]).mean(0), (0.5 + sm_.SH_C0 * second[right]).mean(0)
    assert red[0] > red[2] and blue[2] > blue[0]  # each side took its painting's colour

    assert bpy.ops.dresg.restore_colors(selection_only=True) == {"FINISHED"}  # the right side only
    restored = ops.splat_object.read_attribute(obj.data, sm_.SH_DC)
    np.testing.assert_array_equal(restored[right], original[right])
    np.testing.assert_array_equal(restored[left], first[left])
    assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
    np.testing.assert_array_equal(ops.splat_object.read_attribute(obj.data, sm_.SH_DC), original)

    settings.selection_group, settings.selection = "nowhere", "GROUP"
    with pytest.raises(RuntimeError) as error:
        bpy.ops.dresg.stylize()
    names(error, "'nowhere'")
