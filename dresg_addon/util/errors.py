"""One family of errors whose messages are written for users.

The CLI prints ``str(error)`` on one line and exits non-zero; Blender operators turn it into
``self.report({'ERROR'}, str(error))``. Messages name the file (when there is one) and the problem.
"""

from __future__ import annotations


class DresgError(Exception):
    """Base class of every error the engine raises on purpose."""


class SceneFormatError(DresgError):
    """A scene file cannot be read or written (truncated, bad header, missing properties...)."""


class CameraError(DresgError):
    """Cameras are missing, malformed, or see nothing of the scene."""


class ImageError(DresgError):
    """An image cannot be read or written."""


class ConfigError(DresgError):
    """A setting or a command-line option has a value that cannot work."""


class NumericalError(DresgError):
    """A non-finite value appeared where the method needs finite numbers."""


class ModelError(DresgError):
    """Model weights (SD1.5, DINO, CLIP) are missing or do not match the expected layout."""


class WriteError(DresgError):
    """A file cannot be written (disk full, file too large, no permission); the file that was there is kept."""


class CancelledError(DresgError):
    """The user cancelled a run."""


def with_path(path, message: str) -> str:
    """Prefix a message with the file it concerns: ``'scene.ply: truncated data'``."""
    return f"{path}: {message}"
