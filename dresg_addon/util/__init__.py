"""Plumbing that every layer may use, and that imports nothing else of the engine.

The error family written for users (``errors``), atomic writes (``fileutil``), image files through
OpenImageIO (``imageio``), facts about the machine (``machine``), how torch's CPU threads wait and how
many run (``threads``), and image encoders loaded from local weights (``feature_models``: CLIP and DINO).
"""
