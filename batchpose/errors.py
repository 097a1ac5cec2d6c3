"""Exception hierarchy. Every user-facing error names the file, topic or field and what was expected.

The CLI prints ``str(error)`` on one line and exits with code 2 for any :class:`BatchposeError`.
"""


class BatchposeError(Exception):
    """Base class for errors caused by the user's input or configuration."""


class ConfigError(BatchposeError):
    """A pipeline config or data manifest is malformed (unknown key, bad value, missing file)."""


class MeshError(BatchposeError):
    """A mesh file is missing, unreadable, empty, untextured or in the wrong units."""


class CameraError(BatchposeError):
    """Camera intrinsics are missing or invalid (NaN, non-positive focal length, bad shape)."""


class ImageError(BatchposeError):
    """An image is empty, undecodable, all one colour or in an unsupported encoding."""


class DataError(BatchposeError):
    """A data set (folder or log) is missing, malformed or truncated."""


class RenderError(BatchposeError):
    """Headless rendering is unavailable (missing system GL packages)."""
