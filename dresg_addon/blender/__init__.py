"""Blender's side of the engine, as plain numpy math: no bpy here (the add-on's ``operators/`` call bpy).

``splat_mesh``: a Gaussian scene as the per-point attribute arrays of a Blender mesh and back, the
preview's constants, the import's axes and Up Axis rotations, image pixels to and from Blender's layout;
``camera``: Blender camera settings (lens, sensor fit, shift, pixel aspect, object transform) to and
from :class:`~dresg_addon.scene.camera.Camera`. The add-on imports these without torch.
May import ``util`` and ``scene`` only; nothing else in the engine imports it.
"""
