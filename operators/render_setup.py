"""What a final render (F12) of splat objects needs beyond the viewport: set before each frame, put back after.

- Workbench draws no instance attributes and draws every face opaque: the soft splats would come out as one
  flat grey with opaque shards at their edges. For a Workbench render each splat object shows its realized
  solid shapes instead, carrying the colours, each the size of its splat's core: out to where the splat's
  alpha falls to ``WORKBENCH_CORE_ALPHA`` (faint splats small or gone, as they look; measured on Luigi and
  the bonsai at 160x120 against the engine's render, mean colour error on covered pixels for core alphas
  0.02 / 0.035 / 0.05: Luigi 0.075 / 0.084 / 0.094, bonsai 0.070 / 0.060 / 0.057, where 0.02 draws the
  bonsai's faint background floaters as large opaque shards and 0.035 leaves a few specks).
- EEVEE and Cycles get the rasterizer's screen-space low-pass (``splat_mesh.LOW_PASS`` px^2 added to each splat's 2D
  covariance, as 3DGS does), so splats thinner than a pixel keep their weight: the modifier's Render Pixel
  Size (perspective) or Render Pixel Width (orthographic) is set from the render camera and resolution (0, no
  low-pass, in the viewport, whose size varies).

``render_pre`` runs before the render's depsgraph is built; every value changed is restored in ``render_post``
/ ``render_cancel``, so the file is saved as the user left it. An F12 in the UI calls these handlers on the
render job's thread while the main thread may draw the viewport from the same objects: Blender's API docs
(bpy.app.handlers, "Note on Altering Data", https://docs.blender.org/api/5.0/bpy.app.handlers.html, the same
in 4.2) say to lock the interface (Render > Lock Interface) before such a render, and a locked interface
neither draws nor updates the depsgraph while the job runs. So the handlers change the objects only then, or
on the main thread (a script's or ``blender -b``'s render blocks it); the import turns the lock on.
"""

import threading

import bpy

from ..dresg_addon.blender.camera import blender_intrinsics
from .splat_nodes import INPUT_CORE_ALPHA, INPUT_PIXEL, INPUT_PIXEL_WIDTH, INPUT_SOFT, INPUT_SOLID
from .splat_object import modifier_input, set_modifier_input, splat_modifier
from .views import camera_params

WORKBENCH_CORE_ALPHA = 0.035

_changed: list[tuple[str, str, str, object]] = []  # (object name, modifier name, input, value before the render)


def pixel_size(scene) -> float:
    """Width of one render pixel one unit in front of the scene's camera (1 / focal length in pixels); 0 when
    there is no perspective camera (an orthographic view's pixels do not grow with depth)."""
    camera = scene.camera
    if camera is None or camera.type != "CAMERA" or camera.data.type != "PERSP":
        return 0.0
    _, _, fx, fy, _, _ = blender_intrinsics(camera_params(scene, camera))
    return 1.0 / (fx * fy) ** 0.5


def orthographic_pixel_width(scene) -> float:
    """Width of one render pixel in world units for an orthographic scene camera (its Orthographic Scale spans
    the sensor-fit side of the image); 0 for any other camera."""
    camera = scene.camera
    if camera is None or camera.type != "CAMERA" or camera.data.type != "ORTHO":
        return 0.0
    render, fit = scene.render, camera.data.sensor_fit
    percent = render.resolution_percentage / 100.0
    width, height = render.resolution_x * percent, render.resolution_y * percent
    if fit == "AUTO":
        fit = "HORIZONTAL" if width * render.pixel_aspect_x >= height * render.pixel_aspect_y else "VERTICAL"
    return camera.data.ortho_scale / max(width if fit == "HORIZONTAL" else height, 1.0)


def _settings_for(scene) -> dict[str, object]:  # the orthographic pixel width in world units (see _in_object_units)
    if scene.render.engine == "BLENDER_WORKBENCH":
        return {INPUT_SOFT: False, INPUT_SOLID: True, INPUT_CORE_ALPHA: WORKBENCH_CORE_ALPHA}
    return {INPUT_PIXEL: pixel_size(scene), INPUT_PIXEL_WIDTH: orthographic_pixel_width(scene)}


def _in_object_units(settings: dict[str, object], obj) -> dict[str, object]:
    """The node group works in the object's space: a world-space pixel width is divided by the object's scale (the
    perspective pixel size is a ratio of lengths, the same in any unit)."""
    if not settings.get(INPUT_PIXEL_WIDTH):
        return settings
    scale = sum(abs(v) for v in obj.matrix_world.to_scale()) / 3.0
    return {**settings, INPUT_PIXEL_WIDTH: settings[INPUT_PIXEL_WIDTH] / max(scale, 1e-12)}


def _splat_modifiers(scene):
    for obj in scene.objects:
        modifier = splat_modifier(obj)
        if modifier is not None:
            yield obj, modifier


def may_change_objects(scene) -> bool:
    """Whether a render handler may write to the splat objects now (see the module's docstring)."""
    return threading.current_thread() is threading.main_thread() or scene.render.use_lock_interface


@bpy.app.handlers.persistent
def _before_render(scene, *_):
    if not may_change_objects(scene):
        print(
            "Stylize Gaussians: Render > Lock Interface is off, so this render shows the splat objects as the "
            "viewport does (Workbench: flat grey; EEVEE: no low-pass); turn it on for final renders of splats"
        )
        return
    _restore()
    settings = _settings_for(scene)
    for obj, modifier in _splat_modifiers(scene):
        for name, value in _in_object_units(settings, obj).items():
            before = modifier_input(modifier, name)
            if before is None or before == value:
                continue
            _changed.append((obj.name, modifier.name, name, before))
            set_modifier_input(modifier, name, value)
        obj.update_tag()


@bpy.app.handlers.persistent
def _after_render(*_):
    _restore()


def _restore() -> None:
    while _changed:
        object_name, modifier_name, name, value = _changed.pop()
        obj = bpy.data.objects.get(object_name)
        modifier = obj.modifiers.get(modifier_name) if obj is not None else None
        if modifier is not None:
            set_modifier_input(modifier, name, value)
            obj.update_tag()


HANDLERS = (
    (bpy.app.handlers.render_pre, _before_render),
    (bpy.app.handlers.render_post, _after_render),
    (bpy.app.handlers.render_cancel, _after_render),
)


def register() -> None:
    for handlers, function in HANDLERS:
        if function not in handlers:
            handlers.append(function)


def unregister() -> None:
    _restore()
    for handlers, function in HANDLERS:
        while function in handlers:
            handlers.remove(function)
