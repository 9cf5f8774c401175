"""Exceptions of the ``radar_driver`` package, all in this module: every error raised
here is a :class:`RadarError`. Errors about bad arguments are also ``ValueError``s."""

from enum import IntEnum


class RadarError(Exception):
    """Root of all radar_driver errors."""


class ConfigError(RadarError, ValueError):
    """A configuration value is out of range or of the wrong type."""


class OptionValueError(ConfigError):
    """An option's value that does not read (radar_driver.options): the message says what
    was expected, and the caller where the value came from."""


class InputError(RadarError, ValueError):
    """An array argument has the wrong shape, dtype or values."""


class ProtocolError(RadarError):
    """A byte string is not a valid message, or a message cannot be encoded."""


class SensorError(RadarError):
    """Root of the errors of a sensor session."""


class SensorTimeout(SensorError):
    """The sensor did not answer in time; the message says what was seen instead."""


class RespCode(IntEnum):
    """Codes of the ``RESP`` answer (K-LD7 datasheet); the codec (protocol.py) uses them, the
    errors name them."""

    OK = 0
    UNKNOWN_COMMAND = 1
    INVALID_PARAMETER = 2
    INVALID_PARAMETER_VERSION = 3
    UART_ERROR = 4
    SENSOR_BUSY = 5
    TIMEOUT = 6


class SensorResponseError(SensorError):
    """The sensor answered a command with a RESP error code."""

    def __init__(self, command: str, code: int):
        name = RespCode(code).name if code in RespCode._value2member_map_ else "UNDEFINED"
        super().__init__(f"sensor answered {command} with RESP {code} ({name})")
        self.command, self.code = command, code


class LinkError(SensorError):
    """The port could not be opened, or failed (unplugged device, closed socket)."""


class WrongDevice(LinkError):
    """A device path that now names another device than the one first opened."""


class PortBusy(LinkError):
    """The port is held by another program (its exclusive lock, or the device says busy)."""


class PortDenied(LinkError):
    """The port may not be opened by this user (permission denied)."""


class DiscoveryError(SensorError):
    """``--sensor auto`` found no K-MD2 on this host's serial ports, or more than one."""


class SetupError(RadarError):
    """A wrong set-up, which retrying does not mend: the sensor answers, but what it sends does
    not go with what it was asked to be (its frame layout is not the sensor profile's); the
    message names the likely cause and the command that shows it. A supervisor does not
    restart a driver that ended with one."""


class LinkDown(RadarError):
    """The simulated link has no peer or was closed."""


class CaptureError(RadarError):
    """A capture file (:mod:`.capture`) cannot be read or written; the message names the file."""
