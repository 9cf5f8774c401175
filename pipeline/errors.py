"""Exceptions of the ``pipeline`` package, all in this module: every error raised here
is a :class:`PipelineError`. Errors about bad arguments are also ``ValueError``s."""


class PipelineError(Exception):
    """Root of all pipeline errors."""


class ParameterError(PipelineError, ValueError):
    """A processing parameter (bits, alpha, delta, K, ...) or an array shape is invalid."""


class WireError(PipelineError, ValueError):
    """A payload is not a valid message of the expected format."""


class DitherUnavailable(ParameterError):
    """A dither-aware decoder was given a frame whose dither is unknown or absent."""


class BusError(PipelineError):
    """A zenoh session could not be opened or connected, or its config file is unusable."""


class CalibrationError(ParameterError):
    """A calibration file or estimate that cannot be used; the message names the file and the entry."""


class RunSetupError(PipelineError):
    """A run that cannot give a result as set up: frames arrive, but none is decoded (every
    one refused); the message says how many, where and why."""
