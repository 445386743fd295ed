"""Stylize Gaussians, its cancel, Restore Original Colours and the per-view images of the last stage."""

import os

import bpy
import numpy as np

from ..dresg_addon.blender import splat_mesh
from ..dresg_addon.util.errors import DresgError, ImageError
from . import ADDON_PACKAGE, job
from .splat_object import (
    is_splat_object,
    object_mode,
    restore_original,
    run_selection,
    selection_mask,
    stylized_scene,
)
from .tasks import CancelJobOperator, JobOperator, JobState, tag_redraw
from .views import fitting_cameras, view_plan

IMAGE_KINDS = ("render", "proposal", "marks", "target", "residual")  # marks: the painting as the splats carry it
# What a run from one view leaves out, said before it starts (the Views panel and the operator).
SINGLE_VIEW = "One view paints only the side it sees: the splats it does not see keep their colours"


def addon_preferences(context):
    """The add-on preferences, or None when it runs unregistered as an add-on (scripts, tests)."""
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


def style_image(settings) -> tuple[np.ndarray, str]:
    """The style picture as [H, W, 3] float32 in [0, 1], and a name for it."""
    if settings.style_source == "IMAGE":
        image = settings.style_image
        if image is None:
            raise ImageError("no style image chosen")
        width, height = image.size
        channels = image.channels
        if width * height == 0 or channels == 0:
            return _unloaded_style_image(image), image.name
        pixels = np.empty(width * height * channels, dtype=np.float32)
        image.pixels.foreach_get(pixels)
        if image.is_float:  # float buffers are scene-linear; the method works on display values
            pixels = splat_mesh.linear_to_srgb(pixels)
        return splat_mesh.image_from_pixels(pixels, width, height, channels), image.name
    from ..dresg_addon.util.imageio import STYLE_MAX_SIDE, read_rgb

    if not settings.style_path:
        raise ImageError("no style image chosen")
    path = bpy.path.abspath(settings.style_path)
    return read_rgb(path, max_side=STYLE_MAX_SIDE), os.path.basename(path)


def _unloaded_style_image(image) -> np.ndarray:
    """The pixels of a Blender image that has none loaded, read from its file by the engine's reader; or an
    ImageError saying why not: the file missing, or the reader's reason (as the command line says it)."""
    from ..dresg_addon.util.imageio import STYLE_MAX_SIDE, read_rgb

    if image.packed_file is not None or image.source != "FILE" or not image.filepath:
        raise ImageError(f"style image '{image.name}' has no pixels: Blender could not load it")
    path = bpy.path.abspath(image.filepath, library=image.library)
    if not os.path.exists(path):
        raise ImageError(f"style image '{image.name}': its file {path} is missing")
    try:  # Blender could not decode it: the reader's reason tells why (or it reads after all)
        return read_rgb(path, max_side=STYLE_MAX_SIDE)
    except ImageError as error:
        raise ImageError(f"style image '{image.name}': the file could not be read: {error}") from None


def prepare_job(context, *, model_path: str = "", dino_path: str = "") -> tuple[job.StylizeJob, str]:
    """A job for the active splat object from the panel's settings (not started), and a note for the user.

    Views: those :func:`~.views.view_plan` names, as the Views panel says them (when there are more than Max
    Views, the engine picks that many of them by coverage). Splats: the Stylize setting as
    :func:`~.splat_object.run_selection` reads it. Model paths default to the add-on preferences.
    """
    from ..dresg_addon.method.medium import check_painting

    obj, scene = context.active_object, context.scene
    settings = scene.dresg
    prefs = addon_preferences(context)
    model_path = model_path or (prefs.sd15_path if prefs is not None else "")
    dino_path = dino_path or (prefs.dino_path if prefs is not None else "")
    config = settings.config(model_path=bpy.path.abspath(model_path) if model_path else "")
    dino_path = bpy.path.abspath(dino_path) if dino_path else ""
    style, style_name = style_image(settings)
    check_painting(style, style_name)  # before the run: a painting too small turns the scene one colour
    selection = run_selection(obj, settings.selection)  # read in Edit Mode, before leaving it
    with object_mode(obj):  # one exit from Edit Mode (and back) for both reads
        mask = selection_mask(obj, selection, settings.selection_group)
        splats = stylized_scene(obj)  # earlier runs' colours stay on the splats this one does not select
    plan = view_plan(scene)
    views = list(range(len(plan.camera_objects))) if plan.ticked else None
    if views is not None and 0 < config.max_views < len(views):
        views = None  # the engine picks Max Views of the ticked cameras by coverage
    if plan.orbit:
        from ..dresg_addon.method.views import scaled_cameras
        from ..dresg_addon.scene.orbit import orbit_cameras

        up = splat_mesh.local_up(np.array(obj.matrix_world))
        ring = orbit_cameras(splats, settings.orbit_count, elevation_deg=settings.orbit_elevation, up=up)
        cameras = scaled_cameras(ring, settings.render_scale)
    else:
        cameras = fitting_cameras(scene, obj, plan.camera_objects)
    run = job.StylizeJob(
        obj,
        splats,
        cameras,
        style,
        config,
        views=views,
        style_name=style_name,
        mask=mask,
        dino_path=dino_path,
        views_key=plan.key(),
    )
    note = f"Views: {plan.line}"
    if mask is not None:
        note += f"; stylizing {int(mask.sum()):,} of {len(mask):,} splats (the selection)"
    return run, note


class DRESG_OT_stylize(JobOperator, bpy.types.Operator):
    """Give the selected splats the look of the style image, from the ticked cameras; runs in the background, Esc cancels"""

    bl_idname = "dresg.stylize"
    bl_label = "Stylize Gaussians"
    bl_options = {"REGISTER", "UNDO"}

    model_path: bpy.props.StringProperty(
        name="SD1.5 Model", description="Overrides the add-on preferences (scripts)", options={"HIDDEN", "SKIP_SAVE"}
    )
    dino_path: bpy.props.StringProperty(
        name="DINOv2 Weights", description="Overrides the add-on preferences (scripts)", options={"HIDDEN", "SKIP_SAVE"}
    )

    @classmethod
    def poll(cls, context):
        from .dependencies import torch_available

        if not is_splat_object(context.active_object):
            cls.poll_message_set("Select an object imported with Import Gaussian Splats")
            return False
        if job.StylizeJob.active() is not None:
            cls.poll_message_set("A stylization is already running")
            return False
        if not torch_available():
            cls.poll_message_set("PyTorch is not installed: use Install Dependencies in the add-on preferences")
            return False
        settings = context.scene.dresg
        if (settings.style_path if settings.style_source == "FILE" else settings.style_image) in ("", None):
            cls.poll_message_set("Choose a style image first (Style panel)")
            return False
        return True

    def _prepare(self, context) -> job.StylizeJob:
        from ..dresg_addon.method.backends import slow_note

        run, note = prepare_job(context, model_path=self.model_path, dino_path=self.dino_path)
        if view_plan(context.scene).single:  # before the run, not after it
            self.report({"WARNING"}, f"{note}. {SINGLE_VIEW}")
        else:
            self.report({"INFO"}, note)
        slow = slow_note(run.config)
        if slow:
            self.report({"WARNING"}, slow)
        return run

    def execute(self, context):
        try:
            run = self._prepare(context)
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        return self.run_here(context, run)

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        try:
            run = self._prepare(context)
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        return self.run_modal(context, run)

    def _finish(self, context, run: job.StylizeJob):
        if run.state is JobState.ERROR:
            self.report({"ERROR"}, f"Stylize Gaussians failed: {run.error}")
            return {"CANCELLED"}
        for line in run.notes():  # the Info editor keeps them; the panel shows them until the next run
            self.report({"INFO"}, line)
        if run.state is JobState.CANCELLED:
            self.report({"WARNING"}, f"{run.text}; Restore Original Colours brings back the imported ones")
            return {"FINISHED"}  # the applied stages stay, as one undo step
        self.report({"INFO"}, run.summary())
        return {"FINISHED"}


class DRESG_OT_cancel_stylize(CancelJobOperator, bpy.types.Operator):
    """Stop the running stylization after the current optimizer step; the last finished stage stays"""

    bl_idname = "dresg.cancel_stylize"
    bl_label = "Cancel Stylization"
    _job_class = job.StylizeJob


class DRESG_OT_restore_colors(bpy.types.Operator):
    """Bring back the colours and geometry the splats had when imported (splats a run split are whole again)"""

    bl_idname = "dresg.restore_colors"
    bl_label = "Restore Original Colours"
    bl_options = {"REGISTER", "UNDO"}

    selection_only: bpy.props.BoolProperty(
        name="Selection Only",
        description="Only the splats the Stylize setting selects; the others keep their stylized colours",
        default=False,
    )

    @classmethod
    def poll(cls, context):
        if not is_splat_object(context.active_object):
            cls.poll_message_set("Select an object imported with Import Gaussian Splats")
            return False
        return True

    def execute(self, context):
        obj = context.active_object
        if job.StylizeJob.running_on(obj):  # the run must not write over the restored colours
            job.StylizeJob.active().cancel()
        settings = context.scene.dresg
        selection = run_selection(obj, settings.selection)
        try:
            with object_mode(obj):  # one exit from Edit Mode (and back) for the selection and the write
                mask = None
                if self.selection_only:
                    mask = selection_mask(obj, selection, settings.selection_group)
                count = len(obj.data.vertices) if mask is None else int(mask.sum())
                removed = restore_original(obj, mask)
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        tag_redraw()
        if removed:
            kept = len(obj.data.vertices)
            self.report({"INFO"}, f"Restored the {kept:,} imported splats: the {removed:,} split from them are gone")
        else:
            self.report({"INFO"}, f"Restored the original colours of {count:,} splats")
        return {"FINISHED"}


class DRESG_OT_open_view_images(bpy.types.Operator):
    """Open the render, proposal, target and residual of each view of the last stage as Blender images"""

    bl_idname = "dresg.open_view_images"
    bl_label = "Open View Images"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        current = job.StylizeJob.current()
        if current is None or not current.images:
            cls.poll_message_set("No stage has finished yet")
            return False
        return True

    def execute(self, context):
        images = []
        for view, kinds in job.StylizeJob.current().images.items():
            for kind in IMAGE_KINDS:
                if kinds.get(kind) is not None:
                    images.append(_store_image(f"DReSG {view} {kind}", kinds[kind]))
        for area in context.screen.areas if context.screen else ():
            if area.type == "IMAGE_EDITOR" and images:
                area.spaces.active.image = images[0]
        self.report({"INFO"}, f"{len(images)} images ready in the Image Editor (DReSG ...)")
        return {"FINISHED"}


def _store_image(name: str, array: np.ndarray):
    """Create or refill a byte (sRGB) image named ``name`` from a top-down [H, W, 3] array in [0, 1]."""
    height, width = array.shape[:2]
    image = bpy.data.images.get(name)
    if image is None or tuple(image.size) != (width, height):
        if image is not None:
            bpy.data.images.remove(image)
        image = bpy.data.images.new(name, width, height, alpha=False)
    image.pixels.foreach_set(splat_mesh.pixels_from_image(array))
    image.update()
    return image


class DRESG_OT_reset_preset(bpy.types.Operator):
    """Set every control the preset names back to the preset's value"""

    bl_idname = "dresg.reset_preset"
    bl_label = "Reset to Preset"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        from .properties import apply_preset

        settings = context.scene.dresg
        changed = settings.preset_changes()
        apply_preset(settings)
        if changed:
            self.report({"INFO"}, f"Reset to the preset's values: {', '.join(changed)}")
        return {"FINISHED"}


class DRESG_OT_dismiss(bpy.types.Operator):
    """Clear the outcome of the last stylization from the panel"""

    bl_idname = "dresg.dismiss"
    bl_label = "Dismiss"
    bl_options = {"INTERNAL"}

    def execute(self, context):
        current = job.StylizeJob.current()
        if current is not None and not current.running:
            job.StylizeJob.forget()
        return {"FINISHED"}


classes = (
    DRESG_OT_stylize,
    DRESG_OT_cancel_stylize,
    DRESG_OT_restore_colors,
    DRESG_OT_open_view_images,
    DRESG_OT_reset_preset,
    DRESG_OT_dismiss,
)
