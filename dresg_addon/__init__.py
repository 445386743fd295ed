"""DReSG engine: reference-guided stylization of 3D Gaussian Splatting scenes.

Imports nothing heavy at package import time and never imports ``bpy``: the Blender operators in
``operators/`` and the command line (``python -m dresg_addon``) are thin layers over this package.
Importing it sets how torch's CPU threads wait (:mod:`dresg_addon.threads`), before torch loads.
"""

from .threads import apply_thread_policy

__version__ = "0.1.0"
THREAD_POLICY = apply_thread_policy()
