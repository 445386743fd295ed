"""Scene data and file formats: what a stylization reads and writes, with no rendering and no method.

The one scene type (``gaussians.GaussianScene``) and the one camera type (``camera.Camera``, OpenCV
axes); scene files (``io``: graphdeco PLY, antimatter15 ``.splat``, PlayCanvas compressed PLY); camera
files (``camera_io``: cameras.json, COLMAP, LLFF, and which way is up); which way is up from the splats
alone (``up_axis``); reprojection of an image between cameras by depth (``warp``); orbits of cameras around a scene (``orbit``);
and the built-in demo scene, cameras and painting (``demo``). Blender's math (no bpy) is ``dresg_addon.blender``, above this.
May import ``util`` only.
"""
