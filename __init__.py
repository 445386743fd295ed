# SPDX-License-Identifier: GPL-3.0-or-later
"""Stylize Gaussians: a Blender extension that stylizes 3D Gaussian Splatting scenes (DReSG).

Registration only. The engine lives in ``dresg_addon`` (no bpy); ``operators`` and ``ui`` are the
thin Blender layer. Heavy modules (torch, the optimizer) are imported when an operator runs.
"""

# The Blender layer is imported on register, not here: pytest imports this file from a checkout without
# bpy and, in a folder whose name is not a Python identifier, without a parent package.


def _modules():
    from . import operators, ui

    return operators, ui


def register() -> None:
    for module in _modules():
        module.register()


def unregister() -> None:
    for module in reversed(_modules()):
        module.unregister()
