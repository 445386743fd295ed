"""What the add-on changes in Blender's process and file beyond its own data, said and undone (issue 42)."""

import importlib

import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender


def _import(tmp_path, capfd):
    from dresg_addon.scene.demo import demo_scene
    from dresg_addon.scene.io import write_scene

    write_scene(demo_scene(0), tmp_path / "demo.ply")
    capfd.readouterr()
    assert bpy.ops.dresg.import_splats(filepath=str(tmp_path / "demo.ply"), axis_conversion="NONE") == {"FINISHED"}
    return capfd.readouterr().out


def _panel_operators(addon):
    from test_blender_addon import draw  # the panel drawn against the real UILayout API

    return draw(addon.ui.panels.DRESG_PT_main, bpy.context).operators()


def test_the_import_says_it_locked_the_interface_and_one_click_undoes_it(addon, tmp_path, capfd):
    """F12's handlers change the splat objects only with Render > Lock Interface on (render_setup.py): the import turns
    it on, says so in its report and in the panel, and Unlock Interface puts it back off."""
    io_ops = addon.operators.io_ops
    scene = bpy.context.scene
    assert not scene.render.use_lock_interface  # Blender's default
    report = _import(tmp_path, capfd)
    assert scene.render.use_lock_interface and io_ops.LOCKED_NOTE in report and "Unlock Interface" in report
    assert "dresg.unlock_interface" in _panel_operators(addon)

    assert bpy.ops.dresg.unlock_interface() == {"FINISHED"}
    assert not scene.render.use_lock_interface
    assert "dresg.unlock_interface" not in _panel_operators(addon)
    assert not bpy.ops.dresg.unlock_interface.poll()

    # A second import locks it again; Keep hides the note and leaves the lock on.
    assert io_ops.LOCKED_NOTE in _import(tmp_path, capfd)
    assert bpy.ops.dresg.unlock_interface(keep=True) == {"FINISHED"}
    assert scene.render.use_lock_interface and "dresg.unlock_interface" not in _panel_operators(addon)

    # Already locked (by the user, or kept): the import neither changes nor mentions it.
    assert io_ops.LOCKED_NOTE not in _import(tmp_path, capfd)
    assert scene.render.use_lock_interface and "dresg.unlock_interface" not in _panel_operators(addon)


def test_the_user_turning_the_lock_off_hides_the_note(addon, tmp_path, capfd):
    _import(tmp_path, capfd)
    bpy.context.scene.render.use_lock_interface = False
    assert "dresg.unlock_interface" not in _panel_operators(addon)


def test_unregistering_ends_the_rasterizer_threads(addon):
    """The band pool a render starts is the add-on's: disabling the add-on ends its threads."""
    workers = importlib.import_module(f"{addon.__name__}.dresg_addon.raster.workers")  # as a run imports it
    assert workers.in_workers(lambda worker, item: item, [1, 2], 2) == [1, 2]
    assert workers.POOL.threads == 2
    addon.unregister()
    try:
        assert workers.POOL.threads == 0
    finally:
        addon.register()  # the fixture unregisters it again
    assert workers.in_workers(lambda worker, item: item, [1, 2], 2) == [1, 2] and workers.POOL.threads == 2
    workers.shutdown()
