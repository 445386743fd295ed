"""Issue 28: the splat object in Edit Mode (Stylize and Restore on the Edit Mode selection and on all splats, the
Strength slider, Export, Select Views), and a corrupt style image already loaded into Blender. bpy module, real
operators."""

import numpy as np
import pytest
from messages import names
from test_blender_artist import _import, _quick_selection_scene, _scene

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.util.imageio import write_image

bpy = pytest.importorskip("bpy")
import bmesh  # noqa: E402  (comes with bpy)

pytestmark = pytest.mark.blender


def _edit_mesh(obj):
    assert obj.mode == "EDIT"
    return bmesh.from_edit_mesh(obj.data)


def _edit_selection(obj) -> np.ndarray:
    bm = _edit_mesh(obj)
    bm.verts.ensure_lookup_table()
    return np.array([v.select for v in bm.verts])


def _select_in_edit_mode(obj, mask: np.ndarray) -> None:
    bm = _edit_mesh(obj)
    bm.verts.ensure_lookup_table()
    for vertex in bm.verts:
        vertex.select_set(bool(mask[vertex.index]))
    bm.select_flush_mode()
    bmesh.update_edit_mesh(obj.data)


def _edit_colours(obj, name: str = sm.SH_DC) -> np.ndarray:
    """[N, 3] of a vector attribute as the edit mesh holds it (what the artist sees and what Tab keeps)."""
    bm = _edit_mesh(obj)
    layer = bm.verts.layers.float_vector[name]
    bm.verts.ensure_lookup_table()
    return np.array([tuple(v[layer]) for v in bm.verts], np.float32)


def _enter_edit_mode(obj) -> None:
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.object.mode_set(mode="EDIT") == {"FINISHED"}


def _leave_edit_mode(obj) -> None:
    assert bpy.ops.object.mode_set(mode="OBJECT") == {"FINISHED"}


@pytest.mark.slow
def test_stylize_restore_export_and_views_on_the_edit_mode_selection(addon, tmp_path, capfd):
    """With the object in Edit Mode and half its splats selected there: Stylize (Selected Splats) changes only
    those, and the object stays in Edit Mode with the same selection; Select Views and Export work there; Restore
    (Selection) brings back the selected ones' colours, Restore (All) every one; Stylize on All in Edit Mode too."""
    pytest.importorskip("torch")
    ops = addon.operators
    obj, settings = _quick_selection_scene(tmp_path)
    noise = np.random.default_rng(3).uniform(-0.1, 0.1, (24, 32, 3))
    write_image(tmp_path / "red.png", np.clip(np.float32([0.9, 0.1, 0.1]) + noise, 0, 1).astype(np.float32))
    settings.style_path = str(tmp_path / "red.png")
    original = ops.splat_object.read_attribute(obj.data, sm.SH_DC).copy()
    left = np.array([v.co.x for v in obj.data.vertices]) < 0

    _enter_edit_mode(obj)
    _select_in_edit_mode(obj, left)
    settings.selection = "SELECTED"
    assert bpy.ops.dresg.select_views() == {"FINISHED"}
    assert obj.mode == "EDIT"
    assert bpy.ops.dresg.stylize() == {"FINISHED"}
    assert obj.mode == "EDIT"
    np.testing.assert_array_equal(_edit_selection(obj), left)
    stylized = _edit_colours(obj)
    np.testing.assert_array_equal(stylized[~left], original[~left])
    assert (np.abs(stylized[left] - original[left]).max(1) > 1e-4).mean() > 0.5

    assert bpy.ops.dresg.export_splats(filepath=str(tmp_path / "out.ply")) == {"FINISHED"}
    assert obj.mode == "EDIT"
    from dresg_addon.scene.io import read_scene

    np.testing.assert_allclose(read_scene(tmp_path / "out.ply").sh_dc, stylized, atol=1e-6)

    assert bpy.ops.dresg.restore_colors(selection_only=True) == {"FINISHED"}
    assert obj.mode == "EDIT"
    np.testing.assert_array_equal(_edit_selection(obj), left)
    np.testing.assert_array_equal(_edit_colours(obj), original)

    settings.selection = "ALL"
    assert bpy.ops.dresg.stylize() == {"FINISHED"}
    assert obj.mode == "EDIT"
    np.testing.assert_array_equal(_edit_selection(obj), left)
    everywhere = _edit_colours(obj)
    assert (np.abs(everywhere - original).max(1) > 1e-4).mean() > 0.5
    assert (np.abs(everywhere[~left] - original[~left]).max(1) > 1e-4).mean() > 0.5

    assert bpy.ops.dresg.restore_colors() == {"FINISHED"}
    assert obj.mode == "EDIT"
    np.testing.assert_array_equal(_edit_colours(obj), original)
    assert _edit_mesh(obj).verts.layers.float_vector.get(sm.SH_DC_STYLIZED) is None
    _leave_edit_mode(obj)
    np.testing.assert_array_equal(ops.splat_object.read_attribute(obj.data, sm.SH_DC), original)
    assert "Traceback" not in capfd.readouterr().err


def test_an_empty_edit_mode_selection_says_no_splat_is_selected(addon, tmp_path):
    pytest.importorskip("torch")
    obj = _import(tmp_path, _scene())
    write_image(tmp_path / "style.png", np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32))
    settings = bpy.context.scene.dresg
    settings.style_path, settings.selection = str(tmp_path / "style.png"), "SELECTED"
    _enter_edit_mode(obj)
    _select_in_edit_mode(obj, np.zeros(len(obj.data.vertices), bool))
    with pytest.raises(RuntimeError) as error:
        bpy.ops.dresg.stylize()
    names(error, obj.name, "selected")
    with pytest.raises(RuntimeError) as error:
        bpy.ops.dresg.restore_colors(selection_only=True)
    names(error, obj.name, "selected")
    assert obj.mode == "EDIT"


def test_strength_moves_the_colours_in_edit_mode(addon, tmp_path, capfd):
    """The Strength slider's update callback writes the shown colours with the object in Edit Mode (it printed a
    traceback and left them as they were), and keeps the Edit Mode selection."""
    ops = addon.operators
    scene = _scene()
    obj = _import(tmp_path, scene)
    original = ops.splat_object.read_attribute(obj.data, sm.SH_DC).copy()
    stylized = original + 0.5
    ops.splat_object.write_colors(obj, stylized)  # what a run leaves
    selected = np.arange(len(scene)) % 3 == 0

    _enter_edit_mode(obj)
    _select_in_edit_mode(obj, selected)
    obj.dresg_strength = 0.0
    assert obj.mode == "EDIT" and ops.splat_object.splat_modifier(obj).show_viewport  # the preview is back
    np.testing.assert_array_equal(_edit_selection(obj), selected)
    np.testing.assert_allclose(_edit_colours(obj), original, atol=1e-6)
    obj.dresg_strength = 0.5
    _leave_edit_mode(obj)
    mesh = obj.data
    np.testing.assert_allclose(ops.splat_object.read_attribute(mesh, sm.SH_DC), original + 0.25, atol=1e-5)
    colour = ops.splat_object.read_attribute(mesh, sm.COLOR)[:, :3]
    shown = sm.display_colors(original + 0.25, ops.splat_object.read_attribute(mesh, sm.OPACITY))
    np.testing.assert_allclose(colour, shown[:, :3], atol=1e-5)
    assert "Traceback" not in capfd.readouterr().err


def test_a_corrupt_image_loaded_in_blender_says_why_it_cannot_be_read(addon, tmp_path, capfd):
    """A style image chosen as a Blender image whose file is corrupt: the report names the file and gives the
    reader's reason, as the command line does; one whose file is gone says it is missing."""
    pytest.importorskip("torch")
    _import(tmp_path, _scene())
    bad = tmp_path / "bad_style.png"
    bad.write_bytes(b"not a png at all")
    image = bpy.data.images.load(str(bad), check_existing=False)
    settings = bpy.context.scene.dresg
    settings.style_source, settings.style_image = "IMAGE", image
    with pytest.raises(RuntimeError) as caught:
        bpy.ops.dresg.stylize()
    message = names(caught, "bad_style.png", "PNG")  # the file, and the reader's reason
    assert "missing" not in message  # the file is there

    image.filepath = str(tmp_path / "gone.png")
    image.reload()
    with pytest.raises(RuntimeError) as error:
        bpy.ops.dresg.stylize()
    names(error, "gone.png", "missing")
    assert "Traceback" not in capfd.readouterr().err
