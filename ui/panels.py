"""The "Stylize Gaussians" sidebar tab of the 3D view: the Stylize Gaussians panel and its sub-panels."""

import textwrap

import bpy

from ..dresg_addon.method.config import preset_label
from ..dresg_addon.method.medium import allows_geometry, holds_scene_light, sets_its_own_stages
from ..operators import dependencies, io_ops, job
from ..operators.splat_nodes import (
    INPUT_MAX_SPLATS,
    INPUT_MIN_OPACITY,
    INPUT_SCALE,
    INPUT_SHAPE,
    INPUT_SOFT,
    INPUT_SOLID,
)
from ..operators.splat_object import has_stylized_colors, is_splat_object, run_selection, splat_modifier
from ..operators.stylize import SINGLE_VIEW, addon_preferences
from ..operators.tasks import JobState
from ..operators.views import SEEN_ENOUGH, SelectionJob, fit_size, scene_cameras, seen_share, view_plan

CATEGORY = "Stylize Gaussians"


def _wrapped(layout, text: str, width: int = 48, icon: str = "NONE") -> None:
    column = layout.column(align=True)
    for index, line in enumerate(textwrap.wrap(text, width) or [""]):
        column.label(text=line, icon=icon if index == 0 else "BLANK1")


def _draw_lock_note(layout, scene) -> None:
    """The import turned Render > Lock Interface on: say so, with the one-click undo."""
    if not io_ops.locked_by_import(scene):
        return
    box = layout.box()
    _wrapped(box, f"The import {io_ops.LOCKED_NOTE}", icon="LOCKED")
    row = box.row(align=True)
    row.operator("dresg.unlock_interface", icon="UNLOCKED")
    row.operator("dresg.unlock_interface", text="Keep", icon="CHECKMARK").keep = True


class SplatPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = CATEGORY


class ChildPanel(SplatPanel):
    bl_parent_id = "DRESG_PT_main"

    @classmethod
    def poll(cls, context):
        return is_splat_object(context.active_object)


class DRESG_UL_cameras(bpy.types.UIList):
    """The scene's cameras with a tick each, and the coverage the selection computed."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_property, index=0, flt_flag=0):
        view = item.dresg_view
        row = layout.row(align=True)
        row.prop(view, "use", text="")
        row.label(text=item.name, icon="CAMERA_DATA")
        if view.coverage >= 0.0:
            row.label(text=f"{100.0 * view.coverage:.1f}%" + (f"  #{view.pick}" if view.pick else ""))

    def filter_items(self, context, data, property_name):
        objects = getattr(data, property_name)
        flags = [self.bitflag_filter_item if obj.type == "CAMERA" else 0 for obj in objects]
        if self.filter_name:
            by_name = bpy.types.UI_UL_list.filter_items_by_name(
                self.filter_name, self.bitflag_filter_item, objects, "name", reverse=False
            )
            flags = [a & b for a, b in zip(flags, by_name)]
        return flags, bpy.types.UI_UL_list.sort_items_by_name(objects, "name")


class DRESG_PT_main(SplatPanel, bpy.types.Panel):
    bl_idname = "DRESG_PT_main"
    bl_label = "Stylize Gaussians"

    def draw(self, context):
        layout = self.layout
        obj = context.active_object
        if not is_splat_object(obj):
            layout.label(text="Select a splat object, or import one:")
            layout.operator("dresg.import_splats", icon="IMPORT")
            _draw_lock_note(layout, context.scene)
            return
        mesh = obj.data
        box = layout.box()
        box.label(text=f"{obj.name}: {len(mesh.vertices):,} splats", icon="OUTLINER_OB_POINTCLOUD")
        box.label(text=obj.get("dresg_source_format", "?"))
        row = box.row(align=True)
        row.prop(obj, "dresg_up_axis")
        row.prop(obj, "dresg_up_flip", toggle=True)
        if "dresg_stylize_settings" in obj:
            box.label(text=_stylized_label(obj), icon="BRUSH_DATA")
        _draw_lock_note(layout, context.scene)

        if not dependencies.torch_available():
            from .preferences import draw_dependencies

            prefs = addon_preferences(context)
            draw_dependencies(layout, prefs.index_url if prefs is not None else "")

        current = job.StylizeJob.current()
        mine = current is not None and current.concerns(obj)
        if current is not None and current.running:
            if not mine:
                layout.label(text=f"Stylizing '{current.object_name}'", icon="SORTTIME")
            layout.progress(factor=current.fraction, type="BAR", text=current.text)
            layout.operator("dresg.cancel_stylize", icon="CANCEL")
        else:
            settings = context.scene.dresg
            if view_plan(context.scene).single:  # before the run, not after it
                alert = layout.row()
                alert.alert = True
                _wrapped(alert, f"{SINGLE_VIEW} (Views panel)", icon="ERROR")
            row = layout.row()
            row.scale_y = 1.5
            row.operator("dresg.stylize", text=stylize_label(obj, settings), icon="BRUSH_DATA")
        if mine and current.state in (JobState.DONE, JobState.CANCELLED):  # the last run's notes, until the next
            notes = layout.box()
            summary = [current.summary()] if current.n_changed is not None else []  # once colours were written
            for line in [*summary, *current.notes()]:
                _wrapped(notes, line[0].upper() + line[1:], icon="INFO")
        if mine and current.state is JobState.ERROR:
            box = layout.box()
            box.alert = True
            _wrapped(box, f"Stylize Gaussians failed: {current.error}", icon="ERROR")
            box.operator("dresg.dismiss", icon="X")
        elif mine and not current.running:
            row = layout.row()
            row.label(text=current.text, icon="INFO" if current.state is JobState.DONE else "CANCEL")
            row.operator("dresg.dismiss", text="", icon="X")
        if mine and current.images:
            layout.operator("dresg.open_view_images", icon="IMAGE_DATA")
        if has_stylized_colors(obj):
            layout.prop(obj, "dresg_strength", slider=True)
        row = layout.row(align=True)
        row.operator("dresg.restore_colors", icon="LOOP_BACK")
        if run_selection(obj, context.scene.dresg.selection) != "ALL":
            row.operator("dresg.restore_colors", text="Selection", icon="LOOP_BACK").selection_only = True
        row.operator("dresg.export_splats", text="Export", icon="EXPORT")


def stylize_label(obj, settings) -> str:
    """The Stylize button's text: which splats it changes when that is not all of them, and when an Edit Mode
    selection is left out (Stylize set to All Splats)."""
    selection = run_selection(obj, settings.selection)
    selected = obj.mode == "EDIT" and obj.data.total_vert_sel
    if selection == "ALL" and selected:
        return "Stylize All (selection ignored)"
    if selection == "SELECTED" and obj.mode == "EDIT":
        return f"Stylize {obj.data.total_vert_sel:,} Selected Splats"
    return "Stylize Gaussians"


def _stylized_label(obj) -> str:
    import json

    try:
        settings = json.loads(obj["dresg_stylize_settings"])
    except (TypeError, ValueError):
        return "Stylized"
    for how in ("cancelled", "failed"):
        if f"{how}_after_stage" in settings:
            return f"Stylized ({how} after stage {settings[f'{how}_after_stage']})"
    return "Stylized"


def _draw_backend_notes(layout, context, settings) -> None:
    """Why the chosen proposal backend cannot run here, and what it costs without a GPU (the registry's words)."""
    from ..dresg_addon.method.backends import BACKENDS, duration, proposal_seconds
    from ..dresg_addon.util.errors import DresgError

    entry = BACKENDS[settings.proposal]
    prefs = addon_preferences(context)
    model_path = prefs.sd15_path if prefs is not None else ""
    reason = entry.unavailable(bpy.path.abspath(model_path) if model_path else "")  # as Stylize resolves it
    if reason:
        _wrapped(layout, reason, icon="ERROR")
    if entry.uses_gpu:
        try:
            seconds = proposal_seconds(settings.config())
        except DresgError:  # settings that cannot run say so when Stylize is pressed
            return
        layout.label(text=f"Without a GPU: about {duration(seconds)} (estimate)", icon="INFO")


class DRESG_PT_style(ChildPanel, bpy.types.Panel):
    bl_label = "Style"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        settings = context.scene.dresg
        layout.prop(settings, "style_source", expand=True)
        if settings.style_source == "FILE":
            layout.prop(settings, "style_path")
        else:
            layout.template_ID(settings, "style_image", open="image.open")
        # The preset above the controls it sets (Blender's preset menus apply every value they name); the
        # controls changed since are named, with a way back.
        row = layout.row(align=True)
        row.prop(settings, "preset")
        changed = settings.preset_changes()
        if changed:
            row.operator("dresg.reset_preset", text="", icon="LOOP_BACK")
            _wrapped(
                layout, f"{preset_label(settings.preset)} (modified): {', '.join(changed)}", icon="DECORATE_OVERRIDE"
            )
        layout.prop(settings, "stroke_size")
        layout.prop(settings, "scene_weight", slider=True)
        light = layout.row()
        light.active = holds_scene_light(settings.medium)
        light.prop(settings, "scene_light", slider=True)
        layout.prop(settings, "medium")
        layout.prop(settings, "selection")
        if settings.selection == "GROUP":
            layout.prop_search(settings, "selection_group", context.active_object, "vertex_groups")
        layout.prop(settings, "proposal")
        _draw_backend_notes(layout, context, settings)


class DRESG_PT_style_advanced(ChildPanel, bpy.types.Panel):
    bl_label = "Advanced"
    bl_parent_id = "DRESG_PT_style"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        from ..dresg_addon.method.backends import BACKENDS

        layout = self.layout
        layout.use_property_split = True
        settings = context.scene.dresg
        stages = layout.row()
        stages.active = not sets_its_own_stages(settings.medium, BACKENDS[settings.proposal])
        stages.prop(settings, "stages")
        layout.prop(settings, "max_views")
        column = layout.column(align=True)
        column.prop(settings, "proposal_width")
        column.prop(settings, "proposal_height", text="Y")
        for name in ("fit_resolution", "render_scale"):
            layout.prop(settings, name)
        width, height = fit_size(context.scene)
        width, height = max(1, round(width * settings.render_scale)), max(1, round(height * settings.render_scale))
        layout.label(text=f"Fitting at {width} x {height} px ({width * height / 1e6:.2f} MP a view)", icon="INFO")
        geometry = layout.row()
        geometry.active = allows_geometry(settings.medium)
        geometry.prop(settings, "optimize_geometry")
        for name in ("sh_rest", "seed"):
            layout.prop(settings, name)


class DRESG_PT_views(ChildPanel, bpy.types.Panel):
    bl_label = "Views"

    def draw(self, context):
        layout = self.layout
        scene = context.scene
        settings = scene.dresg
        cameras = scene_cameras(scene)
        layout.row().prop(settings, "view_source", expand=True)
        plan = view_plan(scene)
        _wrapped(layout, plan.line, icon="ERROR" if plan.single else "INFO")
        seen = seen_share(context.active_object, plan)
        if plan.single or (seen is not None and seen < SEEN_ENOUGH):
            box = layout.box()
            if seen is not None and seen < SEEN_ENOUGH:
                _wrapped(box, f"The cameras saw {seen:.0%} of the splats: the other {1 - seen:.0%} keep their colours")
            else:
                _wrapped(box, SINGLE_VIEW)
            box.prop_enum(settings, "view_source", "ORBIT", text="Use an Orbit Ring", icon="CON_FOLLOWPATH")
        if cameras and settings.view_source == "CAMERAS":
            layout.template_list("DRESG_UL_cameras", "", scene, "objects", settings, "camera_index", rows=4)
            row = layout.row(align=True)
            row.operator("dresg.tick_views", text="All").use = True
            row.operator("dresg.tick_views", text="None").use = False
            selecting = SelectionJob.active()
            if selecting is not None:
                layout.progress(factor=selecting.fraction, type="BAR", text=f"{selecting.text} (Esc cancels)")
                layout.operator("dresg.cancel_select_views", icon="CANCEL")
            else:
                layout.operator("dresg.select_views", icon="VIEWZOOM")
        column = layout.column(align=True)
        row = column.row(align=True)
        row.prop(settings, "orbit_count")
        row.prop(settings, "orbit_elevation")
        column.prop(settings, "orbit_fov")
        column.operator("dresg.add_orbit_cameras", icon="CAMERA_DATA")
        layout.operator("dresg.import_cameras", icon="OUTLINER_OB_CAMERA")


class DRESG_PT_display(ChildPanel, bpy.types.Panel):
    bl_label = "Display"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        modifier = splat_modifier(context.active_object)
        if modifier is None:
            layout.label(text="The splat preview modifier was removed", icon="ERROR")
            return
        items = modifier.node_group.interface.items_tree
        for name in (INPUT_SHAPE, INPUT_SCALE, INPUT_MIN_OPACITY, INPUT_MAX_SPLATS, INPUT_SOLID, INPUT_SOFT):
            if name in items:
                layout.prop(modifier, f'["{items[name].identifier}"]', text=name)
        soft = INPUT_SOFT in items and modifier[items[INPUT_SOFT].identifier]
        if soft and context.scene.render.engine == "BLENDER_WORKBENCH":
            _wrapped(layout, "Workbench renders soft splats without colour: render with EEVEE", icon="INFO")
        shading = context.space_data.shading if context.space_data and context.space_data.type == "VIEW_3D" else None
        if shading is not None and shading.type == "SOLID":
            layout.prop(shading, "color_type", text="Solid Colour")


classes = (
    DRESG_UL_cameras,
    DRESG_PT_main,
    DRESG_PT_style,
    DRESG_PT_style_advanced,
    DRESG_PT_views,
    DRESG_PT_display,
)
