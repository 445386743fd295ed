"""Issue 45 in the bpy module: a run that splits the splats wider than the marks gives the splat object its children
(every attribute from their parent, the split geometry), carries the selection, hidden state and vertex groups to
them, keeps a first run's colours through a second split, exports them, says so, and Restore (or Undo) gives back the
imported splats exactly. Tiny scenes and one-stage runs."""

from dataclasses import replace

import numpy as np
import pytest
from test_blender_artist import _import
from test_refine import wide_scene

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.scene.io import read_scene
from dresg_addon.util.imageio import write_image

bpy = pytest.importorskip("bpy")
pytest.importorskip("torch")
pytestmark = pytest.mark.blender
WIDE = 5  # wide_scene's wide splats lead it; 400 fine ones behind them are never split
# Stroke Size 0.5 at 96x72 fits of 32x24 proposals: marks 4.5 px, narrower than four of the five wide splats
RUN = {"stages": 1, "proposal_width": 32, "proposal_height": 24, "stroke_size": 0.5}


def _scene():
    """wide_scene with view-dependent colour, normals and an integer extra, which the children must carry."""
    scene = wide_scene()
    rng = np.random.default_rng(7)
    n = len(scene)
    return replace(
        scene,
        sh_rest=rng.normal(0, 0.1, (n, 3, 3)).astype(np.float32),
        normals=rng.normal(size=(n, 3)).astype(np.float32),
        extras={"label": rng.integers(0, 200, n).astype(np.uint8)},
    )


def _cameras(addon):
    from test_refine import cameras

    camera = addon.dresg_addon.scene.camera
    return [camera.Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.world_to_camera) for c in cameras()]


def _style() -> np.ndarray:
    return np.random.default_rng(3).uniform(0.0, 1.0, (24, 32, 3)).astype(np.float32)


def _mesh(addon, obj) -> dict[str, np.ndarray]:
    """Positions and every point attribute, by name."""
    so = addon.operators.splat_object
    with so.object_mode(obj):
        out = {a.name: a.values for a in so.read_point_attributes(obj.data)}
        out["position"] = so.read_positions(obj.data)
    return out


def _flags(obj, name: str) -> np.ndarray:
    values = np.zeros(len(obj.data.vertices), bool)
    obj.data.vertices.foreach_get(name, values)
    return values


def _weights(obj, group: str) -> np.ndarray:
    index = obj.vertex_groups[group].index
    return np.array([next((g.weight for g in v.groups if g.group == index), 0.0) for v in obj.data.vertices])


def _run(addon, obj, mask=None, split_cap=0.5):
    """A one-stage run of the splitting plan on ``obj`` (the job, as the operator runs it): (the job, the engine's
    result)."""
    ops = addon.operators
    config, plan = addon.dresg_addon.method.config.preset_run("preview", split_cap=split_cap, **RUN)
    splats = ops.splat_object.stylized_scene(obj)
    run = ops.job.StylizeJob(obj, splats, _cameras(addon), _style(), config, mask=mask, plan=plan)
    results = []
    apply = run._apply_result
    run._apply_result = lambda target, result: (results.append(result), apply(target, result))
    run.make_current()
    run.run_blocking()
    assert run.state is ops.tasks.JobState.DONE, run.error
    return run, results[0]


def test_a_split_run_gives_the_object_its_children_and_restore_gives_back_the_import_exactly(addon, tmp_path):
    obj = _import(tmp_path, _scene())
    n = len(obj.data.vertices)
    selected, hidden = np.zeros(n, bool), np.zeros(n, bool)
    selected[[0, 2, 7]], hidden[[1, 9]] = True, True
    obj.data.vertices.foreach_set("select", selected)
    obj.data.vertices.foreach_set("hide", hidden)
    obj.vertex_groups.new(name="front").add([0, 1, 3], 0.7, "REPLACE")
    obj.vertex_groups["front"].add([2], 0.25, "REPLACE")
    obj.data.attributes.new("painted", "BOOLEAN", "POINT").data.foreach_set("value", selected)
    obj["note"] = "mine"
    imported = _mesh(addon, obj)
    modifier, material = obj.modifiers[0].name, obj.data.materials[0].name

    run, result = _run(addon, obj)
    m = len(result.scene)
    parents = result.parents
    assert m == len(obj.data.vertices) > n and set(np.unique(parents[n:])) <= set(range(WIDE))
    assert any(line.startswith("split ") and "wide splats into" in line for line in run.notes())
    assert run.n_splats == m and run.n_selected == m and run.n_split == n
    after = _mesh(addon, obj)
    np.testing.assert_array_equal(after[sm.PARENT], parents)
    np.testing.assert_array_equal(after["position"], result.scene.means)
    np.testing.assert_array_equal(after[sm.LOG_SCALE], result.scene.log_scales)
    np.testing.assert_array_equal(after[sm.OPACITY_LOGIT], result.scene.opacity_logits)
    np.testing.assert_array_equal(after[sm.SH_DC_STYLIZED], result.scene.sh_dc)
    carried = (sm.SH_DC_ORIGINAL, sm.sh_rest_name(0), sm.sh_rest_name(2), sm.NORMAL, "dresg_extra_label", "painted")
    for name in carried:
        np.testing.assert_array_equal(after[name], imported[name][parents], err_msg=name)
    np.testing.assert_array_equal(after[sm.MEANS_ORIGINAL], imported["position"][parents])
    np.testing.assert_array_equal(_flags(obj, "select"), selected[parents])
    np.testing.assert_array_equal(_flags(obj, "hide"), hidden[parents])
    np.testing.assert_allclose(_weights(obj, "front"), np.array([0.7, 0.7, 0.25, 0.7] + [0.0] * (n - 4))[parents])
    assert obj.modifiers[0].name == modifier and obj.data.materials[0].name == material
    assert "dresg_stylize_settings" in obj and obj["dresg_source_path"] and obj["note"] == "mine"
    assert f"the split added {m - n:,} splats" in run.summary()

    # Strength 0 shows the imported colours on every splat, a child its parent's; 1 the run's.
    obj.dresg_strength = 0.0
    np.testing.assert_array_equal(_mesh(addon, obj)[sm.SH_DC], imported[sm.SH_DC][parents])
    obj.dresg_strength = 1.0
    shown = _mesh(addon, obj)
    np.testing.assert_array_equal(shown[sm.SH_DC], result.scene.sh_dc)
    np.testing.assert_allclose(
        shown[sm.COLOR], sm.display_colors(result.scene.sh_dc, result.scene.opacities), atol=1e-6
    )

    # Export writes the children.
    assert bpy.ops.dresg.export_splats(filepath=str(tmp_path / "out.ply")) == {"FINISHED"}
    exported = read_scene(tmp_path / "out.ply")
    assert len(exported) == m
    np.testing.assert_array_equal(exported.means, result.scene.means)
    np.testing.assert_array_equal(exported.sh_dc, result.scene.sh_dc)

    # Restore: the imported splats, every array bit for bit, the selection, hidden state and groups as they were.
    assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
    restored = _mesh(addon, obj)
    assert len(obj.data.vertices) == n and restored.keys() == imported.keys()
    for name, values in imported.items():
        np.testing.assert_array_equal(restored[name], values, err_msg=name)
    np.testing.assert_array_equal(_flags(obj, "select"), selected)
    np.testing.assert_array_equal(_flags(obj, "hide"), hidden)
    np.testing.assert_allclose(_weights(obj, "front"), [0.7, 0.7, 0.25, 0.7] + [0.0] * (n - 4))
    assert "dresg_stylize_settings" not in obj and obj.modifiers[0].name == modifier


def test_a_second_run_keeps_the_first_runs_colours_and_splits_the_split_object_again(addon, tmp_path):
    obj = _import(tmp_path, _scene())
    n = len(obj.data.vertices)
    imported = _mesh(addon, obj)
    first = np.zeros(n, bool)
    first[[0, 1]] = True  # two wide splats
    _, result = _run(addon, obj, mask=first)
    m = len(result.scene)
    assert set(np.unique(result.parents[n:])) == {0, 1}
    after_first = _mesh(addon, obj)

    second = np.zeros(m, bool)
    second[[2, 3]] = True  # two other wide splats
    second[n] = True  # and a child of the first run (split again if it is still wider than the marks)
    _, again = _run(addon, obj, mask=second)
    k = len(again.scene)
    assert k == len(obj.data.vertices) > m
    after = _mesh(addon, obj)
    kept = np.flatnonzero(~second)  # splats of the first run's mesh the second did not select
    assert (kept >= n).sum() > 0  # children of the first run among them
    np.testing.assert_array_equal(after[sm.SH_DC_STYLIZED][kept], after_first[sm.SH_DC_STYLIZED][kept])
    parent = result.parents[again.parents]
    np.testing.assert_array_equal(after[sm.PARENT], parent)
    np.testing.assert_array_equal(after[sm.SH_DC_ORIGINAL], imported[sm.SH_DC][parent])
    np.testing.assert_array_equal(after[sm.MEANS_ORIGINAL], imported["position"][parent])

    assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
    restored = _mesh(addon, obj)
    assert len(obj.data.vertices) == n
    for name, values in imported.items():
        np.testing.assert_array_equal(restored[name], values, err_msg=name)


def test_the_operator_says_the_split_keeps_the_edit_mode_selection_and_undo_brings_the_count_back(
    addon, tmp_path, monkeypatch, capfd
):
    """Stylize from the panel in Edit Mode on a selection, with a plan that splits: the Info lines say the split, the
    children of selected splats are selected in Edit Mode; an undo step after it goes back to the imported count."""
    config = addon.dresg_addon.method.config
    monkeypatch.setitem(config.PLANS, "preview", config.PLANS["preview"].with_(split_cap=0.5))
    obj = _import(tmp_path, _scene())
    n, object_name = len(obj.data.vertices), obj.name
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 96, 72, 100
    bpy.ops.dresg.add_orbit_cameras(count=3, elevation=10.0)
    settings = scene.dresg
    settings.preset = "preview"
    for name, value in {"stages": 1, "proposal_width": 32, "proposal_height": 24, "stroke_size": 0.5}.items():
        setattr(settings, name, value)
    settings.max_views, settings.render_scale = 3, 1.0
    write_image(tmp_path / "style.png", _style())
    settings.style_path = str(tmp_path / "style.png")
    window = bpy.context.window_manager.windows[0]
    selected = np.zeros(n, bool)
    selected[:WIDE] = True
    obj.data.vertices.foreach_set("select", selected)

    with bpy.context.temp_override(window=window, screen=window.screen):
        bpy.ops.ed.undo_push(message="imported")
        bpy.context.view_layer.objects.active = obj
        assert bpy.ops.object.mode_set(mode="EDIT") == {"FINISHED"}
        settings.selection = "AUTO"  # the Edit Mode selection
        capfd.readouterr()
        assert bpy.ops.dresg.stylize() == {"FINISHED"}
        printed = capfd.readouterr().out
        assert obj.mode == "EDIT"
        assert bpy.ops.object.mode_set(mode="OBJECT") == {"FINISHED"}
        m = len(obj.data.vertices)
        assert m > n, printed
        assert any("split" in line and "wide splats into" in line for line in printed.splitlines()), printed
        parent = _mesh(addon, obj)[sm.PARENT]
        np.testing.assert_array_equal(_flags(obj, "select"), selected[parent])
        bpy.ops.ed.undo_push(message="stylized")  # the step Blender pushes after an operator with UNDO
        assert bpy.ops.ed.undo() == {"FINISHED"}
        obj = bpy.data.objects[object_name]  # undo replaced the object
        assert len(obj.data.vertices) == n
        assert obj.data.attributes.get(sm.PARENT) is None and obj.data.attributes.get(sm.SH_DC_STYLIZED) is None
        assert bpy.ops.ed.redo() == {"FINISHED"}
        obj = bpy.data.objects[object_name]
        assert len(obj.data.vertices) == m

        # Restore in Edit Mode: the imported count, still in Edit Mode.
        bpy.context.view_layer.objects.active = obj
        assert bpy.ops.object.mode_set(mode="EDIT") == {"FINISHED"}
        capfd.readouterr()
        assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
        assert f"Restored the {n:,} imported splats: the {m - n:,} split from them are gone" in capfd.readouterr().out
        assert obj.mode == "EDIT"
        assert bpy.ops.object.mode_set(mode="OBJECT") == {"FINISHED"}
        assert len(obj.data.vertices) == n
        np.testing.assert_array_equal(_flags(obj, "select"), selected)


def test_a_run_cancelled_after_a_split_stage_keeps_it_and_restore_still_gives_back_the_import(addon, tmp_path):
    """Geometry offsets on, two stages, cancelled once the first is shown: the object holds that stage's split splats
    and moved geometry, consistently; the geometry kept is the import's, so Restore is still exact."""
    ops = addon.operators
    obj = _import(tmp_path, _scene())
    n = len(obj.data.vertices)
    imported = _mesh(addon, obj)
    preset_run = addon.dresg_addon.method.config.preset_run
    config, plan = preset_run("preview", split_cap=0.5, **{**RUN, "stages": 2, "optimize_geometry": True})
    run = ops.job.StylizeJob(obj, ops.splat_object.stylized_scene(obj), _cameras(addon), _style(), config, plan=plan)
    apply = run._apply_stage

    def apply_then_cancel(target, update):
        apply(target, update)
        run.cancel()

    run._apply_stage = apply_then_cancel
    run.make_current()
    run.run_blocking()
    assert run.state is ops.tasks.JobState.CANCELLED and run.stages_applied == 1, run.error
    after = _mesh(addon, obj)
    parent = after[sm.PARENT]
    assert len(obj.data.vertices) == len(parent) > n
    np.testing.assert_array_equal(after[sm.MEANS_ORIGINAL], imported["position"][parent])
    np.testing.assert_array_equal(after[sm.SH_DC_ORIGINAL], imported[sm.SH_DC][parent])
    assert np.abs(after["position"][n:] - imported["position"][parent[n:]]).max(1).min() > 0  # children moved apart
    np.testing.assert_allclose(after[sm.COLOR], sm.display_colors(after[sm.SH_DC], after[sm.OPACITY]), atol=1e-6)
    np.testing.assert_array_equal(after[sm.OPACITY], sm.sigmoid(after[sm.OPACITY_LOGIT]))

    assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
    restored = _mesh(addon, obj)
    assert len(obj.data.vertices) == n and restored.keys() == imported.keys()
    for name, values in imported.items():
        np.testing.assert_array_equal(restored[name], values, err_msg=name)
