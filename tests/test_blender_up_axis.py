"""The right way up without a re-import (issue 28, item 3): Automatic axes from the splats when no cameras lie
beside the file, and the splat object's Up Axis and Flip, which turn it in place and are saved with the .blend.
bpy module."""

import types

import numpy as np
import pytest
from messages import names
from test_up_axis import TURN_Z_TO, blob, floor_and_object, turned

from dresg_addon.blender import splat_mesh as sm
from dresg_addon.scene.io import write_scene

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender


def _import(path, capfd, **options):
    capfd.readouterr()
    assert bpy.ops.dresg.import_splats(filepath=str(path), **options) == {"FINISHED"}
    out = capfd.readouterr()
    return bpy.context.active_object, out.out + out.err


def _automatic_note(printed: str) -> str:
    """The one line an import with Axes: Automatic prints about the axis it chose."""
    lines = [line for line in printed.splitlines() if "Automatic" in line]
    assert len(lines) == 1, printed
    return lines[0]


def _rotation(obj) -> np.ndarray:
    return np.array(obj.matrix_basis.to_3x3().normalized())  # matrix_world follows at the next depsgraph update


def _panel_props(addon) -> list[str]:
    """The properties the main panel shows, from a layout that records its calls."""
    props = []

    class Layout:
        def __getattr__(self, name):
            def call(*args, **kwargs):
                if name == "prop":
                    props.append(args[1])
                return Layout()

            return call

        def __setattr__(self, name, value):
            pass

    addon.ui.panels.DRESG_PT_main.draw(types.SimpleNamespace(layout=Layout()), bpy.context)
    return props


def test_import_without_cameras_takes_the_up_axis_from_the_splats(addon, tmp_path, capfd):
    path = tmp_path / "floor.ply"  # no cameras.json, COLMAP model or poses_bounds.npy beside it
    write_scene(turned(floor_and_object(), TURN_Z_TO["+Y"]), path)
    obj, printed = _import(path, capfd)  # Axes: Automatic, the default
    names(_automatic_note(printed), "+Y", "splats", "confident")  # the axis, what it is from, how sure
    assert obj.dresg_up_axis == "+Y" and not obj.dresg_up_flip  # the panel shows what it chose
    assert obj["dresg_axis_conversion"] == "Y_UP_TO_BLENDER"
    np.testing.assert_allclose(_rotation(obj), sm.up_axis_rotation("+Y"), atol=1e-6)
    assert {"dresg_up_axis", "dresg_up_flip"} <= set(_panel_props(addon))

    write_scene(turned(floor_and_object(), TURN_Z_TO["-X"]), path)  # an axis none of the named Axes is
    obj, printed = _import(path, capfd)
    names(_automatic_note(printed), "-X", "splats")
    assert obj.dresg_up_axis == "-X" and obj["dresg_axis_conversion"] == ""
    np.testing.assert_allclose(_rotation(obj) @ [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], atol=1e-6)

    write_scene(blob(), path)  # nothing to go by: OpenCV, as before, and it says so
    obj, printed = _import(path, capfd)
    names(_automatic_note(printed), "-Y", "not sure", "Up Axis")  # the fallback, and the setting to check
    assert obj.dresg_up_axis == "-Y" and obj["dresg_axis_conversion"] == "OPENCV_TO_BLENDER"

    obj, printed = _import(path, capfd, axis_conversion="Y_UP_TO_BLENDER")  # a named Axes: no guess, no note
    assert obj.dresg_up_axis == "+Y" and "Axes: Automatic" not in printed


def test_luigi_stands_up_without_a_re_import(addon, shared_data, capfd):
    obj, printed = _import(shared_data("scenes/luigi.ply"), capfd)
    assert obj.dresg_up_axis == "+Y" and "from the splats" in printed and "confident" in printed
    head = np.array(obj.matrix_world.to_3x3()) @ [0.0, 0.62, 0.0]  # the top of Luigi's cap in the file
    assert head[2] > 0.6


def test_up_axis_and_flip_turn_the_object_in_place_and_survive_save_and_reopen(addon, tmp_path, capfd):
    path = tmp_path / "blob.ply"
    write_scene(blob(), path)
    obj, _ = _import(path, capfd)
    obj.location, obj.scale = (1.0, 2.0, 3.0), (2.0, 2.0, 2.0)
    obj.dresg_up_axis = "+Y"  # the panel's enum: its update turns the object at once
    np.testing.assert_allclose(_rotation(obj), sm.AXIS_CONVERSIONS["Y_UP_TO_BLENDER"], atol=1e-6)
    np.testing.assert_allclose(obj.location, (1.0, 2.0, 3.0))
    np.testing.assert_allclose(obj.scale, (2.0, 2.0, 2.0))
    bpy.context.view_layer.update()
    world = np.array(obj.matrix_world)
    np.testing.assert_allclose(world[:3, :3] @ [0.0, 1.0, 0.0] + world[:3, 3], [1.0, 2.0, 5.0], atol=1e-5)
    assert obj["dresg_axis_conversion"] == "Y_UP_TO_BLENDER"

    obj.dresg_up_flip = True  # upside down: the same as the opposite axis
    np.testing.assert_allclose(_rotation(obj), sm.AXIS_CONVERSIONS["OPENCV_TO_BLENDER"], atol=1e-6)
    assert obj["dresg_axis_conversion"] == "OPENCV_TO_BLENDER"
    obj.dresg_up_axis = "+X"
    np.testing.assert_allclose(_rotation(obj), sm.up_axis_rotation("+X", flip=True), atol=1e-6)
    np.testing.assert_allclose(_rotation(obj) @ [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], atol=1e-6)
    assert obj["dresg_axis_conversion"] == ""
    np.testing.assert_allclose(obj.location, (1.0, 2.0, 3.0))
    np.testing.assert_allclose(obj.scale, (2.0, 2.0, 2.0))

    bpy.ops.object.mode_set(mode="EDIT")  # only the object's transform changes: Edit Mode is no matter
    obj.dresg_up_flip = False
    bpy.ops.object.mode_set(mode="OBJECT")
    np.testing.assert_allclose(_rotation(obj), sm.up_axis_rotation("+X"), atol=1e-6)

    name, saved = obj.name, tmp_path / "up.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(saved))
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    obj = bpy.data.objects[name]
    assert obj.dresg_up_axis == "+X" and not obj.dresg_up_flip
    np.testing.assert_allclose(_rotation(obj), sm.up_axis_rotation("+X"), atol=1e-6)
    np.testing.assert_allclose(obj.location, (1.0, 2.0, 3.0))
    obj.dresg_up_axis = "-Z"  # and it still turns the object after the reopen
    np.testing.assert_allclose(_rotation(obj), sm.up_axis_rotation("-Z"), atol=1e-6)
    np.testing.assert_allclose(obj.scale, (2.0, 2.0, 2.0))
