"""What the artist set is what runs, and what the run learns reaches the panel (issue 43): the Views panel's line
for 0, 1 and many cameras, a preset that sets every control it names and a panel that shows the ones changed
since, the Edit Mode selection by default, the run's notes in the panel, paintings too small to paint from, and
the report's count of the splats whose colours changed. bpy module, real operators."""

import numpy as np
import pytest
from test_blender_artist import _drawn, _import, _quick_selection_scene, _scene
from test_blender_edit_mode import _enter_edit_mode, _leave_edit_mode, _select_in_edit_mode

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.util.imageio import write_image

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender


def _labels(panel) -> list[str]:
    return [kw.get("text", "") for name, _, kw in _drawn(panel) if name == "label"]


def _text(panel) -> str:
    """What a panel's labels say, its wrapped lines joined again."""
    return " ".join(_labels(panel))


def _painting(tmp_path, size=(24, 32), name="style.png") -> str:
    noise = np.random.default_rng(3).uniform(-0.1, 0.1, (*size, 3))
    write_image(tmp_path / name, np.clip(np.float32([0.9, 0.2, 0.1]) + noise, 0, 1).astype(np.float32))
    return str(tmp_path / name)


def _add_camera(name: str):
    obj = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    obj.location = (0.0, -6.0, 0.0)
    obj.rotation_euler = (1.5708, 0.0, 0.0)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def test_the_views_panel_says_which_views_a_run_uses_for_0_1_and_many_cameras(addon, tmp_path):
    ops, panels = addon.operators, addon.ui.panels
    obj = _import(tmp_path, _scene())
    scene, settings = bpy.context.scene, bpy.context.scene.dresg
    settings.style_path = _painting(tmp_path)
    settings.max_views = 0

    assert "no cameras: a 12-view orbit" in _text(panels.DRESG_PT_views)
    run, note = ops.stylize.prepare_job(bpy.context)
    assert len(run.cameras) == 12 and run.views is None and note == "Views: no cameras: a 12-view orbit"

    # One camera, added to render the scene: the panel says it alone is used and warns before the run.
    render_camera = _add_camera("Render Camera")
    plan = ops.views.view_plan(scene)
    assert plan.single and plan.line == "1 scene camera: only it will be used"
    assert plan.line in _text(panels.DRESG_PT_views) and ops.stylize.SINGLE_VIEW in _text(panels.DRESG_PT_views)
    offers = [(args, kw) for name, args, kw in _drawn(panels.DRESG_PT_views) if name == "prop_enum"]
    assert offers == [((settings, "view_source", "ORBIT"), {"text": "Use an Orbit Ring", "icon": "CON_FOLLOWPATH"})]
    assert ops.stylize.SINGLE_VIEW in _text(panels.DRESG_PT_main)  # beside the Stylize button too
    run, _ = ops.stylize.prepare_job(bpy.context)
    assert len(run.cameras) == 1
    settings.view_source = "ORBIT"  # the offer taken: the orbit, the camera left alone
    assert ops.views.view_plan(scene).line == "Orbit Ring chosen: a 12-view orbit"
    run, _ = ops.stylize.prepare_job(bpy.context)
    assert len(run.cameras) == 12 and ops.stylize.SINGLE_VIEW not in _text(panels.DRESG_PT_main)
    settings.view_source = "CAMERAS"

    # Many: the ticked ones, else those that see the most (Max Views), and what they saw when it was too little.
    bpy.ops.dresg.add_orbit_cameras(count=4)  # ticked
    assert ops.views.view_plan(scene).line == "4 ticked cameras: only they will be used"
    bpy.ops.dresg.tick_views(use=False)
    assert ops.views.view_plan(scene).line == "5 scene cameras, none ticked: those that see the splats are used"
    settings.max_views = 2
    line = "5 scene cameras, none ticked: the 2 that see the most are used"
    assert ops.views.view_plan(scene).line == line and line in _text(panels.DRESG_PT_views)
    assert not any(name == "prop_enum" for name, _, _ in _drawn(panels.DRESG_PT_views))
    ops.views.record_seen(obj, ops.views.view_plan(scene).key(), 0.84)  # as a run or Select Views measures it
    assert "The cameras saw 84% of the splats: the other 16% keep their colours" in _text(panels.DRESG_PT_views)
    assert any(name == "prop_enum" for name, _, _ in _drawn(panels.DRESG_PT_views))
    render_camera.name = "Another Name"  # other cameras: what was measured no longer applies
    assert ops.views.seen_share(obj, ops.views.view_plan(scene)) is None


def test_a_preset_sets_every_control_it_names_and_the_panel_shows_those_changed_since(addon, tmp_path):
    panels, config = addon.ui.panels, addon.dresg_addon.method.config
    _import(tmp_path, _scene())
    settings = bpy.context.scene.dresg
    drawn = [args[1] for name, args, _ in _drawn(panels.DRESG_PT_style) if name == "prop"]
    assert drawn.index("preset") < min(drawn.index(p) for p in ("stroke_size", "scene_weight", "scene_light", "medium"))
    assert settings.preset_changes() == [] and "(modified)" not in _text(panels.DRESG_PT_style)

    # The artist's controls, then a preset: as Blender's preset menus, it sets every value it names, visibly.
    settings.stroke_size, settings.scene_weight, settings.scene_light, settings.medium = 3.0, 0.9, 0.1, "paint"
    assert "Standard (modified): Stroke Size, Paint <-> Scene, Scene Light, Medium" in _text(panels.DRESG_PT_style)
    assert any(
        name == "operator" and args == ("dresg.reset_preset",) for name, args, _ in _drawn(panels.DRESG_PT_style)
    )
    settings.preset = "preview"
    preview = config.PRESETS["preview"]
    assert (settings.stroke_size, settings.medium, settings.stages, settings.max_views) == (
        preview.stroke_size,
        preview.medium,
        preview.stages,
        preview.max_views,
    )
    assert (settings.scene_weight, settings.scene_light) == pytest.approx((preview.scene_weight, preview.scene_light))
    assert settings.preset_changes() == [] and "(modified)" not in _text(panels.DRESG_PT_style)

    settings.stroke_size, settings.max_views = 3.0, 4  # one in the Style panel, one in Advanced
    assert "Preview (modified): Stroke Size, Max Views" in _text(panels.DRESG_PT_style)
    assert bpy.ops.dresg.reset_preset() == {"FINISHED"}
    assert (settings.stroke_size, settings.max_views) == (preview.stroke_size, preview.max_views)
    assert "(modified)" not in _text(panels.DRESG_PT_style)


def test_edit_mode_stylizes_the_selection_by_default_and_the_run_notes_reach_the_panel(addon, tmp_path):
    """Blender's own tools act on the Edit Mode selection: so does Stylize, unless set to All Splats, which its
    button then says. The run's notes (the medium it read, the views it used) and its count of the splats whose
    colours changed stay under the button until the next run."""
    pytest.importorskip("torch")
    ops, panels = addon.operators, addon.ui.panels
    obj, settings = _quick_selection_scene(tmp_path)
    settings.style_path = _painting(tmp_path)
    assert settings.selection == "AUTO"
    assert panels.stylize_label(obj, settings) == "Stylize Gaussians"  # Object Mode: every splat
    before = ops.splat_object.scene_from_object(obj).sh_dc
    _enter_edit_mode(obj)
    left = np.array([v.co.x for v in obj.data.vertices]) < 0
    _select_in_edit_mode(obj, left)
    assert panels.stylize_label(obj, settings) == f"Stylize {left.sum():,} Selected Splats"
    settings.selection = "ALL"
    assert panels.stylize_label(obj, settings) == "Stylize All (selection ignored)"
    buttons = [kw.get("text") for name, args, kw in _drawn(panels.DRESG_PT_main) if args == ("dresg.stylize",)]
    assert buttons == ["Stylize All (selection ignored)"]
    settings.selection = "AUTO"

    assert bpy.ops.dresg.stylize() == {"FINISHED"}
    assert obj.mode == "EDIT"
    _leave_edit_mode(obj)
    stylized = ops.splat_object.read_attribute(obj.data, sm.SH_DC_STYLIZED)
    np.testing.assert_array_equal(stylized[~left], before[~left])  # no splat outside the selection changed
    run = ops.job.StylizeJob.current()
    changed = ops.job.changed_count(before, stylized)
    assert run.mask is not None and run.n_selected == left.sum() and run.n_changed == changed > 0

    # The notes under the button: the medium read, the views used; the summary counts the changed splats.
    summary = run.summary()
    assert summary.startswith(f"Stylized {changed:,} of the {left.sum():,} selected splats in ") or (
        changed == left.sum() and summary.startswith(f"Stylized {changed:,} selected splats in ")
    )
    text = _text(panels.DRESG_PT_main)
    assert "The painting reads as paint" in text and "Active views: 3 of 3 cameras" in text
    assert summary.split(" in ")[0] in text
    assert len(run.notes()) >= 2 and all("\n" not in line for line in run.notes())


@pytest.mark.parametrize("size", [(1, 1), (4, 4)])
def test_a_painting_too_small_to_paint_from_gets_one_line_before_the_run(addon, tmp_path, size):
    pytest.importorskip("torch")
    obj = _import(tmp_path, _scene())
    settings = bpy.context.scene.dresg
    settings.style_path = _painting(tmp_path, size, "tiny.png")
    bpy.ops.dresg.add_orbit_cameras(count=2)
    before = dict(obj.items())
    with pytest.raises(RuntimeError) as raised:  # background mode: the operator's error report
        bpy.ops.dresg.stylize()
    message = str(raised.value).strip()
    assert f"tiny.png: the painting is {size[1]}x{size[0]} px, smaller than the 9 px patches" in message
    assert len(message.splitlines()) == 1
    assert addon.operators.job.StylizeJob.current() is None and dict(obj.items()).keys() == before.keys()
