"""Exception root of the ``pipeline`` package: every error raised here is a
:class:`PipelineError`. Errors about bad arguments are also ``ValueError``s."""


class PipelineError(Exception):
    """Root of all pipeline errors."""


class ParameterError(PipelineError, ValueError):
    """A processing parameter (bits, alpha, delta, K, ...) or an array shape is invalid."""
