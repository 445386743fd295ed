# SPDX-License-Identifier: GPL-3.0-or-later
"""Stylize Gaussians: a Blender extension that stylizes 3D Gaussian Splatting scenes (DReSG).

Registration only. The engine lives in ``dresg_addon`` (no bpy); ``operators`` and ``ui`` are the
thin Blender layer. Heavy modules (torch, the optimizer) are imported when an operator runs.
"""

from . import operators, ui

_modules = (operators, ui)


def register() -> None:
    for module in _modules:
        module.register()


def unregister() -> None:
    for module in reversed(_modules):
        module.unregister()
