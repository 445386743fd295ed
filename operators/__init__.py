"""Operators and properties: thin adapters between Blender and the engine in ``dresg_addon``.

Each operator reads properties, calls one engine function and writes the result back; engine errors
(:class:`~dresg_addon.util.errors.DresgError`) become reports. torch and the optimizer are imported inside
the operators, so enabling the extension stays instant and works without torch.
"""

import sys

import bpy

ADDON_PACKAGE = __package__.rpartition(".")[0]  # the extension's root package (bl_ext.REPO.ID when installed)

from . import dependencies, io_ops, job, properties, render_setup, stylize, tasks, views  # noqa: E402 (they import ADDON_PACKAGE)

classes = (
    *properties.classes,
    *dependencies.classes,
    *io_ops.classes,
    *views.classes,
    *stylize.classes,
)

__all__ = [
    "ADDON_PACKAGE",
    "classes",
    "dependencies",
    "io_ops",
    "job",
    "properties",
    "render_setup",
    "stylize",
    "tasks",
    "views",
]


def register() -> None:
    for cls in classes:
        bpy.utils.register_class(cls)
    properties.attach()
    render_setup.register()
    dependencies.add_site_packages()


def unregister() -> None:
    tasks.stop_jobs()
    # the rasterizer's threads, if a run started them (importing the engine here would load torch)
    workers = sys.modules.get(f"{ADDON_PACKAGE}.dresg_addon.raster.workers")
    if workers is not None:
        workers.shutdown()
    render_setup.unregister()
    properties.detach()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
