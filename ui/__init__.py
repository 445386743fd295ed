"""User interface: the sidebar panels, the menus (File, Object, status bar) and the add-on preferences."""

import bpy

from . import menus, panels, preferences

classes = (*preferences.classes, *panels.classes, *menus.classes)


def register() -> None:
    for cls in classes:
        bpy.utils.register_class(cls)
    menus.attach()


def unregister() -> None:
    menus.detach()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
