"""Import Gaussian Splats (.ply, .splat, compressed .ply) and Export Gaussian Splats (graphdeco .ply)."""

import os
import time

import bpy
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..dresg_addon.util.errors import DresgError
from .splat_object import create_splat_object, is_splat_object, scene_from_object

# F12 calls the render set-up's handlers on the render thread: they change the splat objects only with the
# interface locked (render_setup.py), so the import turns the lock on, says so, and Unlock Interface undoes it.
LOCKED_BY_IMPORT = "dresg_locked_interface"  # scene property: the import turned Lock Interface on (it was off)
LOCKED_NOTE = "turned on Render > Lock Interface, which F12 renders of splats need"


def lock_interface(scene) -> bool:
    """Turn on the scene's Render > Lock Interface; True when it was off (the scene remembers that)."""
    if scene.render.use_lock_interface:
        return False
    scene.render.use_lock_interface = True
    scene[LOCKED_BY_IMPORT] = True
    return True


def locked_by_import(scene) -> bool:
    """Whether the lock is on because an import turned it on (the panel then offers Unlock Interface)."""
    return scene is not None and bool(scene.get(LOCKED_BY_IMPORT)) and scene.render.use_lock_interface


class DRESG_OT_import_splats(bpy.types.Operator, ImportHelper):
    """Import a 3D Gaussian Splatting scene as one mesh object with a vertex per splat"""

    bl_idname = "dresg.import_splats"
    bl_label = "Import Gaussian Splats"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filter_glob: bpy.props.StringProperty(default="*.ply;*.splat", options={"HIDDEN"})
    axis_conversion: bpy.props.EnumProperty(
        name="Axes",
        description="Which way is up in the file; choose another if the scene stands on its head or side "
        "(it only sets the object's rotation: the Up Axis in the object panel changes it later)",
        items=(
            (
                "AUTO",
                "Automatic",
                "From the capture's cameras beside the file (cameras.json, COLMAP, LLFF), else from the splats "
                "(a floor, table or base, and the wider end at the bottom) when they are clear, else OpenCV",
            ),
            (
                "OPENCV_TO_BLENDER",
                "OpenCV / COLMAP (y down)",
                "Captures trained with COLMAP cameras (most 3DGS scenes)",
            ),
            ("Y_UP_TO_BLENDER", "Y Up", "y up, z towards the viewer (OpenGL, glTF, many exported models)"),
            ("NONE", "Z Up (as Blender)", "The file's coordinates unchanged"),
        ),
        default="AUTO",
    )
    shape: bpy.props.EnumProperty(
        name="Splat Shape",
        description="Shape drawn for each splat in the viewport",
        items=(
            ("ICO", "Ellipsoid", "A low-poly ico sphere scaled to each Gaussian"),
            ("DISK", "Disk", "A disk across each Gaussian's two largest axes"),
        ),
        default="ICO",
    )
    scale_factor: bpy.props.FloatProperty(
        name="Size (sigma)",
        description="Drawn size of each splat in standard deviations",
        min=0.0,
        soft_max=4.0,
        default=1.5,
    )
    min_opacity: bpy.props.FloatProperty(
        name="Min Opacity", description="Hide splats below this opacity (display only)", min=0.0, max=1.0, default=0.02
    )
    max_splats: bpy.props.IntProperty(
        name="Max Shown",
        description="Draw at most this many splats, a random subset (display only)",
        min=0,
        default=2_000_000,
    )
    solid_colors: bpy.props.BoolProperty(
        name="Colours in Solid Mode",
        description="Realize the preview so Solid mode can show the colours (heavier for millions of splats)",
        default=True,
    )
    soft_render: bpy.props.BoolProperty(
        name="Soft Splats in Renders",
        description="Renders (EEVEE) draw each splat with its opacity and Gaussian falloff, as the stylizer sees it",
        default=True,
    )
    set_viewport_shading: bpy.props.BoolProperty(
        name="Show Splat Colours",
        description="Set the 3D views' Solid mode and Workbench renders to the splat colours, and the view "
        "transform to Standard so colours show as captured",
        default=True,
    )
    drop_invalid: bpy.props.BoolProperty(
        name="Drop Invalid Splats", description="Drop splats with NaN or infinite values instead of failing"
    )

    def execute(self, context):
        from ..dresg_addon.blender.splat_mesh import AXIS_CONVERSION_UP
        from ..dresg_addon.scene.camera_io import detect_up_axis
        from ..dresg_addon.scene.io import clamped_note, read_scene_detailed

        start = time.perf_counter()
        try:
            result = read_scene_detailed(self.filepath, drop_invalid=self.drop_invalid)
            if self.axis_conversion == "AUTO":
                up_axis, axes_reason = detect_up_axis(self.filepath, result.scene)
            else:
                up_axis, axes_reason = AXIS_CONVERSION_UP[self.axis_conversion], ""
            obj = create_splat_object(
                context,
                result.scene,
                bpy.path.display_name_from_filepath(self.filepath),
                source_path=self.filepath,
                source_format=result.format.value,
                up_axis=up_axis,
                shape=self.shape,
                scale_factor=self.scale_factor,
                min_opacity=self.min_opacity,
                max_splats=self.max_splats,
                solid_colors=self.solid_colors,
                soft_render=self.soft_render,
            )
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        locked = lock_interface(context.scene)
        if self.set_viewport_shading:
            for area in context.screen.areas if context.screen else ():
                if area.type == "VIEW_3D":
                    area.spaces.active.shading.color_type = "VERTEX"
            shading = context.scene.display.shading  # Workbench renders (F12)
            shading.light, shading.color_type = "FLAT", "VERTEX"
            context.scene.view_settings.view_transform = "Standard"
        seconds = time.perf_counter() - start
        message = f"Imported {len(result.scene)} splats ({result.format.value}) as '{obj.name}' in {seconds:.2f} s"
        if axes_reason:
            message += f"; Axes: Automatic: {axes_reason}"
        if locked:
            message += f"; {LOCKED_NOTE} (Unlock Interface in the Stylize Gaussians panel undoes it)"
        notes = [f"dropped {result.dropped} invalid splats"] if result.dropped else []
        notes += [clamped_note(result.clamped)] if result.clamped else []
        self.report({"WARNING"} if notes else {"INFO"}, "; ".join([message, *notes]))
        return {"FINISHED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        for name in ("axis_conversion", "shape", "scale_factor", "min_opacity", "max_splats"):
            layout.prop(self, name)
        for name in ("solid_colors", "soft_render", "set_viewport_shading", "drop_invalid"):
            layout.prop(self, name)


class DRESG_OT_export_splats(bpy.types.Operator, ExportHelper):
    """Export the active splat object, stylized colours and optimised geometry included, as a graphdeco PLY"""

    bl_idname = "dresg.export_splats"
    bl_label = "Export Gaussian Splats"
    bl_options = {"REGISTER", "PRESET"}

    filename_ext = ".ply"
    filter_glob: bpy.props.StringProperty(default="*.ply", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        if not is_splat_object(context.active_object):
            cls.poll_message_set("Select an object imported with Import Gaussian Splats")
            return False
        return True

    def invoke(self, context, event):
        if not self.filepath:
            source = context.active_object.get("dresg_source_path", "")
            folder = os.path.dirname(source) if source else ""
            self.filepath = os.path.join(folder, f"{bpy.path.clean_name(context.active_object.name)}_stylized.ply")
        return super().invoke(context, event)

    def execute(self, context):
        from ..dresg_addon.scene.io import write_scene

        obj = context.active_object
        try:
            scene = scene_from_object(obj)
            write_scene(scene, self.filepath)
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Exported {len(scene)} splats to {self.filepath}")
        return {"FINISHED"}


class DRESG_OT_unlock_interface(bpy.types.Operator):
    """Turn Render > Lock Interface off again, as it was before the import turned it on (F12 renders of splat
    objects then show them as the viewport does)"""

    bl_idname = "dresg.unlock_interface"
    bl_label = "Unlock Interface"
    bl_options = {"REGISTER", "UNDO"}

    keep: bpy.props.BoolProperty(name="Keep Locked", description="Keep the lock on and hide the note")

    @classmethod
    def poll(cls, context):
        return locked_by_import(context.scene)

    @classmethod
    def description(cls, context, properties):
        return (
            "Keep Render > Lock Interface on and hide this note" if properties.keep else " ".join(cls.__doc__.split())
        )

    def execute(self, context):
        scene = context.scene
        del scene[LOCKED_BY_IMPORT]
        if not self.keep:
            scene.render.use_lock_interface = False
            self.report({"INFO"}, "Render > Lock Interface is off again")
        return {"FINISHED"}


classes = (DRESG_OT_import_splats, DRESG_OT_export_splats, DRESG_OT_unlock_interface)
