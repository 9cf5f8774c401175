"""Exception root of the ``radar_driver`` package: every error raised here is a
:class:`RadarError`. Errors about bad arguments are also ``ValueError``s."""


class RadarError(Exception):
    """Root of all radar_driver errors."""


class ConfigError(RadarError, ValueError):
    """A configuration value is out of range or of the wrong type."""


class InputError(RadarError, ValueError):
    """An array argument has the wrong shape, dtype or values."""
