"""The extension as Blender sees it: packaging, registration, menus (F3), panels and preferences."""

import os
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest
from messages import names

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender
REPO = Path(__file__).resolve().parents[1]
PACKAGE = "stylize_gaussians"
F3_LABELS = {
    "dresg.import_splats": "Import Gaussian Splats",
    "dresg.export_splats": "Export Gaussian Splats",
    "dresg.stylize": "Stylize Gaussians",
    "dresg.select_views": "Select Views by Coverage",
    "dresg.add_orbit_cameras": "Add Orbit Cameras",
    "dresg.import_cameras": "Import Cameras",
    "dresg.restore_colors": "Restore Original Colours",
}


def _operator_class(idname):
    category, name = idname.split(".")
    return getattr(bpy.types, f"{category.upper()}_OT_{name}")


class FakeLayout:
    """Records a draw() and checks every call against the real UILayout API and the data it names."""

    FUNCTIONS = set(bpy.types.UILayout.bl_rna.functions.keys())
    PROPERTIES = set(bpy.types.UILayout.bl_rna.properties.keys())
    SUBLAYOUTS = {"row", "column", "box", "split", "grid_flow", "column_flow", "panel", "panel_prop"}

    def __init__(self, log):
        object.__setattr__(self, "_log", log)

    def __setattr__(self, name, value):
        if name not in self.PROPERTIES:
            raise AttributeError(f"UILayout has no property {name!r}")

    def __getattr__(self, name):
        if name not in self.FUNCTIONS:
            raise AttributeError(f"UILayout has no function {name!r}")

        def call(*args, **kwargs):
            self._log.append((name, args, kwargs))
            if name in self.SUBLAYOUTS:
                return FakeLayout(self._log)
            if name in {"prop", "template_ID"}:
                _check_property(args[0], args[1])
            if name == "template_list":
                assert hasattr(bpy.types, args[0]), args[0]
                _check_property(args[2], args[3])
                _check_property(args[4], args[5])
            if name == "menu":
                assert hasattr(bpy.types, args[0]), args[0]
            if name == "operator":
                return FakeOperatorProperties(args[0])
            return None

        return call

    def operators(self):
        return [args[0] for name, args, _ in self._log if name == "operator"]


class FakeOperatorProperties:
    def __init__(self, idname):
        category, name = idname.split(".")
        assert hasattr(bpy.types, f"{category.upper()}_OT_{name}"), f"{idname} is not registered"
        properties = getattr(getattr(bpy.ops, category), name).get_rna_type().properties
        object.__setattr__(self, "_names", set(properties.keys()))

    def __setattr__(self, name, value):
        assert name in self._names, f"operator has no property {name!r}"


def _check_property(data, name):
    if name.startswith('["'):
        assert name[2:-2] in data, name
    else:
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"


def draw(cls, context, **attributes):
    layout = FakeLayout([])
    cls.draw(types.SimpleNamespace(layout=layout, **attributes), context)
    return layout


def test_register_unregister_twice(addon):
    module = addon
    for _ in range(2):
        module.unregister()
        assert not hasattr(bpy.types, "DRESG_OT_stylize")
        assert not hasattr(bpy.types.Scene, "dresg")
        assert module.ui.menus.draw_import not in getattr(bpy.types.TOPBAR_MT_file_import.draw, "_draw_funcs", [])
        module.register()
        assert hasattr(bpy.types, "DRESG_OT_stylize") and hasattr(bpy.types, "DRESG_PT_main")
        assert bpy.context.scene.dresg.preset == "standard"
        assert module.ui.menus.draw_import in bpy.types.TOPBAR_MT_file_import.draw._draw_funcs


def test_every_operator_is_in_a_menu_under_its_f3_name(addon):
    menus = addon.ui.menus
    in_menus = set()
    for _, draw_function in menus.HOOKS:
        layout = FakeLayout([])
        draw_function(types.SimpleNamespace(layout=layout), bpy.context)
        in_menus.update(layout.operators())
    in_menus.update(draw(menus.VIEW3D_MT_dresg_splats, bpy.context).operators())
    for idname, label in F3_LABELS.items():
        assert _operator_class(idname).bl_label == label
        assert idname in in_menus, f"{label} is in no menu, so F3 cannot find it"
    # The Object menu entry leads to the submenu that lists them by label.
    layout = FakeLayout([])
    menus.draw_object_menu(types.SimpleNamespace(layout=layout), bpy.context)
    assert ("menu", ("VIEW3D_MT_dresg_splats",), {}) in layout._log


def _splat_object(tmp_path):
    from dresg_addon.scene.gaussians import GaussianScene
    from dresg_addon.scene.io import write_scene

    rng = np.random.default_rng(0)
    n = 40
    scene = GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=np.full((n, 3), -2.0, np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        opacity_logits=np.zeros(n, np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
    )
    write_scene(scene, tmp_path / "s.ply")
    bpy.ops.dresg.import_splats(filepath=str(tmp_path / "s.ply"))
    return bpy.context.active_object


def _states(addon, tmp_path):
    """Yield (name, apply) pairs that put the add-on in each state the panels must draw."""
    job = addon.operators.job
    JobState = addon.operators.tasks.JobState
    scene_module = addon.dresg_addon.scene.gaussians

    def fake_job(obj, state, **fields):
        empty = scene_module.GaussianScene(
            np.zeros((1, 3), np.float32),
            np.zeros((1, 3), np.float32),
            np.float32([[1, 0, 0, 0]]),
            np.zeros(1, np.float32),
            np.zeros((1, 3), np.float32),
        )
        run = job.StylizeJob(obj, empty, [], np.zeros((4, 4, 3), np.float32), bpy.context.scene.dresg.config())
        run._enter(JobState.RUNNING)  # a state without a worker: the panels only read it
        if state is not JobState.RUNNING:
            run._enter(state)
        for key, value in fields.items():
            setattr(run, key, value)
        run.make_current()

    yield "no splat object", lambda: None
    obj = _splat_object(tmp_path)
    yield "idle", job.StylizeJob.forget
    yield "running", lambda: fake_job(obj, JobState.RUNNING, fraction=0.4, text="Stage 2/5 | fit 3/15")
    yield "error", lambda: fake_job(obj, JobState.ERROR, error="camera 'Camera': a very long message " * 4)
    images = {"view": {k: np.zeros((4, 4, 3), np.float32) for k in ("render", "proposal", "target", "residual")}}
    yield "done", lambda: fake_job(obj, JobState.DONE, text="Done in 3s", images=images)
    yield "cancelled", lambda: fake_job(obj, JobState.CANCELLED, text="Cancelled after 1 stage(s)")

    def cameras_with_coverage():
        job.StylizeJob.forget()
        bpy.ops.dresg.add_orbit_cameras(count=3)
        bpy.data.objects["orbit_001"].dresg_view.coverage = 0.42
        bpy.data.objects["orbit_001"].dresg_view.pick = 1

    yield "cameras", cameras_with_coverage

    def sd15_from_image():
        settings = bpy.context.scene.dresg
        settings.proposal, settings.style_source = "sd15", "IMAGE"

    yield "sd15 and a Blender image", sd15_from_image

    def modifier_removed():
        obj.modifiers.clear()

    yield "modifier removed", modifier_removed


@pytest.mark.parametrize("torch_present", [True, False])
def test_panels_draw_in_every_state(addon, tmp_path, monkeypatch, torch_present):
    dependencies = addon.operators.dependencies
    monkeypatch.setattr(dependencies, "torch_available", lambda: torch_present)
    panels = addon.ui.panels
    drawn = 0
    for state, apply in _states(addon, tmp_path):
        apply()
        for cls in panels.classes:
            if not issubclass(cls, bpy.types.Panel):
                continue
            if hasattr(cls, "poll") and not cls.poll(bpy.context):
                continue
            layout = draw(cls, bpy.context)
            drawn += 1
            if cls is panels.DRESG_PT_main and state != "no splat object":
                ops = layout.operators()
                assert "dresg.restore_colors" in ops, state
                assert ("dresg.cancel_stylize" in ops) == (state == "running"), state
                assert ("dresg.install_dependencies" in ops) == (not torch_present), state
                assert ("dresg.open_view_images" in ops) == (state == "done"), state
                if state == "error":
                    texts = " ".join(kw.get("text", "") for name, _, kw in layout._log if name == "label")
                    assert "camera 'Camera'" in texts
        status = FakeLayout([])
        addon.ui.menus.draw_status(types.SimpleNamespace(layout=status), bpy.context)
        assert any(name == "progress" for name, _, _ in status._log) == (state == "running"), state
    assert drawn > 20
    addon.operators.job.StylizeJob.forget()


def test_camera_list_shows_only_cameras(addon, tmp_path):
    _splat_object(tmp_path)
    bpy.ops.dresg.add_orbit_cameras(count=3)
    scene = bpy.context.scene
    ui_list = addon.ui.panels.DRESG_UL_cameras
    fake = types.SimpleNamespace(filter_name="", bitflag_filter_item=1 << 30, use_filter_sort_reverse=False)
    flags, order = ui_list.filter_items(fake, bpy.context, scene, "objects")
    shown = [obj.name for obj, flag in zip(scene.objects, flags) if flag]
    assert sorted(shown) == ["orbit_000", "orbit_001", "orbit_002"]
    fake.filter_name = "*001"
    flags, _ = ui_list.filter_items(fake, bpy.context, scene, "objects")
    assert [obj.name for obj, flag in zip(scene.objects, flags) if flag] == ["orbit_001"]
    row = FakeLayout([])
    ui_list.draw_item(fake, bpy.context, row, scene, scene.objects["orbit_001"], 0, scene.dresg, "camera_index", 0)
    assert ("prop", (scene.objects["orbit_001"].dresg_view, "use"), {"text": ""}) in row._log


def test_preferences_draw_in_every_install_state(addon, monkeypatch):
    dependencies = addon.operators.dependencies
    prefs_cls = addon.ui.preferences.DRESG_AddonPreferences
    assert prefs_cls.bl_idname == PACKAGE
    fake_prefs = types.SimpleNamespace(sd15_path="", dino_path="", index_url="", bl_rna=prefs_cls.bl_rna)

    def draw_prefs():
        layout = FakeLayout([])
        prefs_cls.draw(types.SimpleNamespace(layout=layout, **vars(fake_prefs)), bpy.context)
        return layout

    monkeypatch.setattr(dependencies, "torch_available", lambda: True)
    assert "dresg.install_dependencies" not in draw_prefs().operators()
    monkeypatch.setattr(dependencies, "torch_available", lambda: False)
    assert "dresg.install_dependencies" in draw_prefs().operators()
    JobState = addon.operators.tasks.JobState
    running = dependencies.Installer([["true"]])
    running._enter(JobState.RUNNING)  # a state without a worker: the preferences only read it
    running.text = "Downloading torch-2.13.0.whl (190 MB)"
    running.make_current()
    layout = draw_prefs()
    assert "dresg.install_dependencies" not in layout.operators()
    assert "dresg.cancel_install" in layout.operators()
    assert any("Downloading" in kw.get("text", "") for _, _, kw in layout._log)
    failed = dependencies.Installer([["true"]])
    failed.lines, failed.error = ["ERROR: No matching distribution"], "x"
    failed._enter(JobState.RUNNING)
    failed._enter(JobState.ERROR)
    failed.make_current()
    layout = draw_prefs()
    assert "dresg.install_dependencies" in layout.operators() and "dresg.cancel_install" not in layout.operators()
    assert any("No matching distribution" in kw.get("text", "") for _, _, kw in layout._log)
    cancelled = dependencies.Installer([["true"]])
    cancelled.cancel()  # never started: cancelled at once
    cancelled.make_current()
    layout = draw_prefs()
    assert "dresg.install_dependencies" in layout.operators()
    assert any(kw.get("text") == dependencies.CANCELLED_MESSAGE for _, _, kw in layout._log)
    dependencies.Installer.forget()


def test_style_image_from_a_file_or_a_blender_image(addon, tmp_path):
    from dresg_addon.util.imageio import write_image

    settings = bpy.context.scene.dresg
    style_image = addon.operators.stylize.style_image
    picture = np.random.default_rng(2).uniform(size=(3, 5, 3)).astype(np.float32)
    write_image(tmp_path / "style.png", picture)
    settings.style_path = str(tmp_path / "style.png")
    array, name = style_image(settings)
    assert name == "style.png"
    np.testing.assert_allclose(array, picture, atol=0.5 / 255)

    image = bpy.data.images.new("painting", 5, 3, alpha=True)
    image.pixels.foreach_set(
        np.ascontiguousarray(np.concatenate([picture, np.ones((3, 5, 1), np.float32)], 2)[::-1]).ravel()
    )
    settings.style_source, settings.style_image = "IMAGE", image
    array, name = style_image(settings)
    assert name == "painting"
    np.testing.assert_allclose(array, picture, atol=0.5 / 255)  # top row first, as files are read

    image.source, image.filepath = "FILE", str(tmp_path / "gone.png")  # its file went missing
    with pytest.raises(addon.dresg_addon.util.errors.ImageError, match="painting"):
        style_image(settings)


def test_stylize_reports_input_errors_before_running(addon, tmp_path, monkeypatch):
    monkeypatch.setattr(addon.operators.dependencies, "torch_available", lambda: True)
    obj = _splat_object(tmp_path)
    bpy.context.scene.dresg.style_path = str(tmp_path / "missing.jpg")
    with pytest.raises(RuntimeError, match="missing.jpg"):
        bpy.ops.dresg.stylize()
    bpy.ops.dresg.add_orbit_cameras(count=1)
    obj.scale = (1.0, 2.0, 1.0)  # cameras cannot live in a non-uniformly scaled frame
    bpy.context.view_layer.update()
    from dresg_addon.util.imageio import write_image

    write_image(tmp_path / "style.png", np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32))
    bpy.context.scene.dresg.style_path = str(tmp_path / "style.png")
    with pytest.raises(RuntimeError, match="scale is not uniform"):
        bpy.ops.dresg.stylize()
    assert addon.operators.job.StylizeJob.current() is None


def test_the_proposal_menu_its_notes_and_the_operators_warning_come_from_the_registry(
    addon, tmp_path, capfd, monkeypatch
):
    """Issue 29: the panel's Proposal items are the registry's; the panel shows the backend's availability reason and
    CPU estimate, and Stylize reports the same slow_note the CLI prints."""
    backends = addon.dresg_addon.method.backends
    prop = bpy.context.scene.dresg.bl_rna.properties["proposal"]
    entries = backends.BACKENDS.values()
    assert [(i.identifier, i.name, i.description) for i in prop.enum_items] == [
        (e.name, e.label, e.description) for e in entries
    ]
    assert prop.default == addon.dresg_addon.method.config.PRESETS["standard"].proposal == "synth"

    monkeypatch.setattr(addon.operators.dependencies, "torch_available", lambda: True)
    _splat_object(tmp_path)
    settings = bpy.context.scene.dresg
    settings.proposal = "sd15"
    layout = draw(addon.ui.panels.DRESG_PT_style, bpy.context)
    shown = " ".join(kw.get("text", "") for name, _, kw in layout._log if name == "label")
    assert backends.BACKENDS["sd15"].unavailable("") in shown  # no model path in the preferences
    estimate = backends.duration(backends.proposal_seconds(settings.config()))
    assert f"Without a GPU: about {estimate} (estimate)" in shown
    settings.proposal = "synth"
    layout = draw(addon.ui.panels.DRESG_PT_style, bpy.context)
    assert not [kw for name, _, kw in layout._log if name == "label" and kw.get("icon") in ("ERROR", "INFO")]

    from dresg_addon.util.imageio import write_image

    write_image(tmp_path / "style.png", np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32))
    settings.style_path, settings.proposal = str(tmp_path / "style.png"), "sd15"
    capfd.readouterr()
    with pytest.raises(RuntimeError) as error:  # the registry's reason, from the run
        bpy.ops.dresg.stylize(model_path=str(tmp_path / "no-model"))
    names(error, "no-model")
    note = backends.slow_note(addon.operators.job.StylizeJob.current().config)
    assert note.startswith("sd15 on this CPU takes about ") and note in capfd.readouterr().out


def test_installer_runs_commands_and_reports_failures(addon, tmp_path):
    dependencies = addon.operators.dependencies
    JobState = addon.operators.tasks.JobState
    ok = dependencies.Installer([[sys.executable, "-c", "print('Collecting torch'); print('Successfully installed')"]])
    ok.start()
    assert ok.wait(30)
    assert ok.state is JobState.DONE and not ok.error and ok.text == "Successfully installed"
    script = "import sys; print('ERROR: Could not find a version that satisfies torch'); sys.exit(3)"
    bad = dependencies.Installer([[sys.executable, "-c", script], [sys.executable, "-c", "print('never')"]])
    bad.start()
    assert bad.wait(30)
    assert bad.state is JobState.ERROR and "exit code 3" in bad.error and "Could not find a version" in bad.error
    assert "never" not in bad.lines
    missing = dependencies.Installer([[str(tmp_path / "no-such-python")]])
    missing.start()
    assert missing.wait(30)
    assert missing.state is JobState.ERROR and "cannot run" in missing.error

    commands = dependencies.pip_commands(tmp_path / "site", index_url="https://example.invalid/simple")
    install = commands[-1]
    assert install[:4] == [sys.executable, "-m", "pip", "install"]
    assert install[install.index("--target") + 1] == str(tmp_path / "site")
    assert "torch==2.13.0" in install and install[-2:] == ["--index-url", "https://example.invalid/simple"]


def test_engine_modules_used_by_the_addon_do_not_import_bpy():
    code = "import sys, dresg_addon.blender.splat_mesh, dresg_addon.blender.camera, dresg_addon.scene.orbit; print('bpy' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


def test_import_export_and_view_work_without_torch(shared_data, tmp_path):
    """Enabling the add-on, importing, drawing the preview and exporting never import torch."""
    luigi = shared_data("scenes/luigi.ply")
    code = textwrap.dedent(
        f"""
        import runpy, sys
        sys.modules["torch"] = None  # any 'import torch' now raises ImportError
        headless = runpy.run_path({str(REPO / "scripts" / "stylize_headless.py")!r})  # as Blender's -P runs it
        import bpy
        bpy.ops.wm.read_factory_settings(use_empty=True)
        addon = headless["load_addon"]()
        assert not addon.operators.dependencies.torch_available()
        bpy.ops.dresg.import_splats(filepath={str(luigi)!r})
        obj = bpy.context.active_object
        obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        bpy.ops.dresg.restore_colors()
        bpy.ops.dresg.export_splats(filepath={str(tmp_path / "out.ply")!r})
        assert not bpy.ops.dresg.stylize.poll()
        print("torch loaded:", sys.modules["torch"] is not None)
        """
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "torch loaded: False" in result.stdout
    assert (tmp_path / "out.ply").stat().st_size == luigi.stat().st_size


@pytest.mark.slow
def test_extension_zip_builds_and_installs(tmp_path):
    """Build with Blender's extension tool, install the zip into a fresh user folder, enable it."""
    build = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "build_extension.py"), "--output-dir", str(tmp_path / "dist")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert build.returncode == 0, build.stdout + build.stderr
    archive = Path(build.stdout.strip().splitlines()[-1])
    import zipfile

    names = [n for n in zipfile.ZipFile(archive).namelist() if not n.endswith("/")]
    shipped = {
        n.split("/")[0] if "/" in n and not n.startswith("dresg_addon/") else "/".join(n.split("/")[:2]) for n in names
    }
    # What Blender runs, and nothing else: no CLI, evaluation (report, plots, stability suite), tests or benchmarks.
    assert shipped == {
        "blender_manifest.toml",
        "__init__.py",
        "LICENSE",
        "operators",
        "ui",
        "dresg_addon/__init__.py",
        "dresg_addon/blender",
        "dresg_addon/method",
        "dresg_addon/raster",
        "dresg_addon/scene",
        "dresg_addon/util",
    }, sorted(shipped)
    assert {
        "operators/stylize.py",
        "ui/panels.py",
        "dresg_addon/method/loop.py",
        "dresg_addon/scene/gaussians.py",
        "dresg_addon/blender/splat_mesh.py",
    } <= set(names)
    assert not [n for n in names if "__pycache__" in n or n.endswith((".pyc", ".jpg", ".png"))]

    code = textwrap.dedent(
        f"""
        import bpy, addon_utils
        result = bpy.ops.extensions.package_install_files(
            filepath={str(archive)!r}, repo="user_default", enable_on_install=True
        )
        assert result == {{"FINISHED"}}, result
        name = "bl_ext.user_default.{PACKAGE}"
        assert name in bpy.context.preferences.addons
        prefs = bpy.context.preferences.addons[name].preferences
        assert type(prefs).bl_idname == name
        print("site:", bpy.utils.extension_path_user(name, path="site-packages"))
        assert hasattr(bpy.types, "DRESG_OT_stylize")
        addon_utils.disable(name)
        assert not hasattr(bpy.types, "DRESG_OT_stylize")
        addon_utils.enable(name)
        assert hasattr(bpy.types, "DRESG_OT_stylize")
        import importlib  # what Stylize imports when it runs, from the installed zip
        for module in ("method.loop", "method.proposal.synth", "method.color_solve", "scene.io", "raster.workers"):
            importlib.import_module(name + ".dresg_addon." + module)
        print("installed ok")
        """
    )
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user")}
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert "installed ok" in result.stdout
    assert f"site: {tmp_path / 'user'}" in result.stdout
