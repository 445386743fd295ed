"""Menus, so that F3 finds every operator: File > Import / Export, and Object > Gaussian Splats.

The status bar shows the progress of a running stylization or view selection.
"""

import bpy

from ..operators.job import StylizeJob
from ..operators.views import SelectionJob

OPERATORS = (
    ("dresg.import_splats", "IMPORT"),
    ("dresg.export_splats", "EXPORT"),
    (None, None),
    ("dresg.stylize", "BRUSH_DATA"),
    ("dresg.cancel_stylize", "CANCEL"),
    ("dresg.restore_colors", "LOOP_BACK"),
    ("dresg.open_view_images", "IMAGE_DATA"),
    (None, None),
    ("dresg.select_views", "VIEWZOOM"),
    ("dresg.cancel_select_views", "CANCEL"),
    ("dresg.add_orbit_cameras", "CAMERA_DATA"),
    ("dresg.import_cameras", "OUTLINER_OB_CAMERA"),
)


class VIEW3D_MT_dresg_splats(bpy.types.Menu):
    bl_idname = "VIEW3D_MT_dresg_splats"
    bl_label = "Gaussian Splats"

    def draw(self, context):
        for idname, icon in OPERATORS:
            if idname is None:
                self.layout.separator()
            else:
                self.layout.operator(idname, icon=icon)


def draw_import(self, context):
    self.layout.operator("dresg.import_splats", text="Gaussian Splats (.ply, .splat)")


def draw_export(self, context):
    self.layout.operator("dresg.export_splats", text="Gaussian Splats (.ply)")


def draw_object_menu(self, context):
    self.layout.separator()
    self.layout.menu(VIEW3D_MT_dresg_splats.bl_idname)


def draw_status(self, context):
    current = StylizeJob.active()
    if current is not None:
        self.layout.progress(factor=current.fraction, type="BAR", text=f"Stylize Gaussians: {current.text}")
    selecting = SelectionJob.active()
    if selecting is not None:
        self.layout.progress(factor=selecting.fraction, type="BAR", text=f"Select Views: {selecting.text}")


classes = (VIEW3D_MT_dresg_splats,)

HOOKS = (
    (bpy.types.TOPBAR_MT_file_import, draw_import),
    (bpy.types.TOPBAR_MT_file_export, draw_export),
    (bpy.types.VIEW3D_MT_object, draw_object_menu),
    (bpy.types.STATUSBAR_HT_header, draw_status),
)


def attach() -> None:
    for menu, draw in HOOKS:
        menu.append(draw)


def detach() -> None:
    for menu, draw in reversed(HOOKS):
        menu.remove(draw)
