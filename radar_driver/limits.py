"""The limits every layer shares: the widest quantizer (bits per real value) and the rule
of a sensor id. The driver checks its own configuration with them; pipeline (quantizer,
wire formats, nodes, security), replay and the qradar command import them from here, so
each rule is written once.

A sensor id is 1-16 ASCII characters of ``[A-Za-z0-9_-]``: it is a zenoh key chunk and
fills the 16-byte, NUL-padded ``sensor_id`` field of a binary frame header.
"""

from __future__ import annotations

import re

import numpy as np

from .errors import ConfigError

#: the most bits per real value (I or Q) a quantizer, a decoder and the wire format take
MAX_BITS = 16
#: the widest ADC word the driver reads, bits
ADC_WORD_BITS = 16
#: the longest sensor id, characters (the width of the binary header's field, bytes)
SENSOR_ID_MAX = 16
#: the characters a sensor id may hold
SENSOR_ID_CHARS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-"
SENSOR_ID_RULE = f"1-{SENSOR_ID_MAX} characters of [A-Za-z0-9_-]"
SENSOR_ID_PATTERN = re.compile(f"[A-Za-z0-9_-]{{1,{SENSOR_ID_MAX}}}")
#: a valid NUL-padded sensor id field of a binary header, as bytes
SENSOR_ID_FIELD = re.compile(rb"[A-Za-z0-9_-]{1,%d}\0*" % SENSOR_ID_MAX)
#: (256,) bool: the bytes a sensor id may hold
SENSOR_ID_BYTES = np.zeros(256, dtype=bool)
SENSOR_ID_BYTES[list(SENSOR_ID_CHARS.encode())] = True
#: (256,) uint8: the class of each byte of a sensor id field: 1 = a byte an id may hold,
#: 0 = NUL (padding), 2 = any other; a valid field's classes never rise and start with 1
_ID_FIELD_CLASS = np.where(SENSOR_ID_BYTES, 1, 2).astype(np.uint8)
_ID_FIELD_CLASS[0] = 0

def sensor_id_problem(sensor_id: object) -> str | None:
    """What is wrong with a sensor id (None when it is valid): one line naming the value.
    A pure function (~0.5 us): no cache of ids seen, so nothing here grows with the sensors
    or needs forgetting when a node forgets one."""
    if not (isinstance(sensor_id, str) and SENSOR_ID_PATTERN.fullmatch(sensor_id)):
        return f"sensor_id={sensor_id!r} must be {SENSOR_ID_RULE}"
    return None


def check_sensor_id(sensor_id: object, error: type[Exception] = ConfigError) -> str:
    """``sensor_id`` when it is valid, else raise ``error`` (a ConfigError unless the
    caller names its own package's error) with the one-line reason."""
    problem = sensor_id_problem(sensor_id)
    if problem is not None:
        raise error(problem)
    return sensor_id  # type: ignore[return-value]


def sensor_id_fields_bad(fields: bytes | np.ndarray) -> bool | np.ndarray:
    """Whether NUL-padded 16-byte sensor id fields are not valid ids: bytes -> bool, or
    (n, 16) uint8 -> (n,) bool (valid: 1-16 bytes of [A-Za-z0-9_-], then NULs only)."""
    if isinstance(fields, bytes):
        return SENSOR_ID_FIELD.fullmatch(fields) is None
    cls = _ID_FIELD_CLASS.take(fields)  # (n, 16): 1...1 then 0...0 when valid
    return ~(cls[:, :-1] >= cls[:, 1:]).all(axis=1) | (cls[:, 0] != 1)


def bits_problem(bits: object) -> str | None:
    """What is wrong with a bit depth (None when it is an integer in [1, MAX_BITS])."""
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or not 1 <= bits <= MAX_BITS:
        return f"bits={bits!r} must be an integer in [1, {MAX_BITS}]"
    return None


def bits_bad(bits: np.ndarray) -> np.ndarray:
    """(n,) bool: where integer bit depths (n,) are outside [1, MAX_BITS] (vectorized
    :func:`bits_problem`, for headers read from bytes)."""
    return (bits < 1) | (bits > MAX_BITS)


def check_bits(bits: object, error: type[Exception] = ConfigError) -> int:
    """``bits`` as an int when it is an integer in [1, MAX_BITS], else raise ``error``."""
    problem = bits_problem(bits)
    if problem is not None:
        raise error(problem)
    return int(bits)  # type: ignore[arg-type]
