"""DReSG engine: reference-guided stylization of 3D Gaussian Splatting scenes.

Imports nothing heavy at package import time and never imports ``bpy``: the Blender operators in
``operators/`` and the command line (``python -m dresg_addon``) are thin layers over this package.
Importing it changes nothing in the process: the thread policy (:mod:`dresg_addon.util.threads`) is the
business of the code that owns the process, the CLI's ``main`` here and the host application elsewhere.

Packages, bottom to top; each imports only its own and those below it (tests/test_package.py checks):

==========  =====================================================================================
util        errors, atomic writes, image files, machine facts, torch threads, local image encoders
scene       the scene and camera types, scene and camera files, Blender camera math, orbits, demo
raster      the differentiable rasterizer and its float64 reference
method      the paper: views, schedule, proposals, targets, fit loss, PCGrad, optimiser, the loop
evaluation  metrics, CLIP-S / DINO-C, the report and its plots, stability cases
commands    the sub-commands of the CLI (``cli`` builds the parser, ``__main__`` runs it)
==========  =====================================================================================
"""

__version__ = "0.1.0"
