"""Error hierarchy. Every error a user can cause is a ``PipelineError``; the CLI maps it to exit code 2."""


class PipelineError(Exception):
    """Base class of the errors this library raises on bad input or assets."""


class ShapeError(PipelineError, ValueError):
    """A tensor or array has the wrong shape, dtype or values (NaN, out of range)."""


class ConfigError(PipelineError, ValueError):
    """A setting, option or file content is invalid; the message lists the valid choices."""


class AssetError(PipelineError, FileNotFoundError):
    """A file the user named (image, mask, camera, URDF, mesh, model) is missing or unreadable."""
