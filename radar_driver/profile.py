"""Sensor profiles: what the K-MD2's public documents do not say, in one validated TOML
file per guess.

A profile holds the ``RADC`` layout (receivers, which two are the azimuth pair, chirps
per ``RADC``, samples per chirp, sample order, word format, ADC bits and offset), the
``INIT`` baud codes, the ``GNFD`` frame bits and the plausible payload lengths of the
frames the driver passes on uninterpreted. Two ship in ``radar_driver/profiles/``:

- ``kmd2-blocks`` (the default): one ramp per ``RADC``; for each azimuth receiver 256 I
  words then 256 Q words (2 048 bytes); a frame's ramps 25 ms apart (``chirp_interval_s``);
- ``kmd2-cube256``: one range-Doppler cube per ``RADC``, 3 receivers x 256 chirps x 256
  samples, I and Q interleaved (786 432 bytes), as a public C reader of the K-MD2 reads;
  chirps 1/5120 s apart (256 a measurement, 20 measurements a second).

The codec (:mod:`.protocol`), the session and the simulator take a profile; nothing
else in the package knows a byte offset. ``qradar inspect`` tries every shipped profile
on a capture of an unknown sensor.

Words are held in one canonical shape, ``(receivers, chirps, samples, 2)`` (I, Q last),
whatever the byte order on the wire. Complex samples are in units of full scale:
``((I - offset) + i (Q - offset)) / 2^(adc_bits - 1)``.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError, ProtocolError
from .limits import ADC_WORD_BITS
from .model import DEFAULT_RAMP_INTERVAL_S, RadarConfig

#: word format name -> numpy dtype of one word on the wire
WORD_DTYPES: dict[str, str] = {"uint16le": "<u2", "uint16be": ">u2", "int16le": "<i2"}
ORDERS = ("blocks", "interleaved")
#: how a frame of R ramps takes R of a RADC's chirps: the first R, or every (chirps // R)-th
CHIRP_SELECT = ("first", "stride")
#: the frames the codec knows (a 4-character header each); the host sends the first four
HEADERS = (b"INIT", b"GNFD", b"GBYE", b"RESP", b"DONE", b"RADC")
MAX_OTHER_LENGTH = 1 << 20


@dataclass(frozen=True)
class RadcLayout:
    r"""The ``RADC`` payload: ``receivers`` x ``chirps`` x ``samples`` complex samples as
    pairs of words (I, Q). ``order``: ``blocks`` (per receiver and chirp, ``samples`` I
    words then ``samples`` Q words) or ``interleaved`` (I, Q per sample). ``azimuth``:
    the receivers that are antenna 1 and antenna 2 of the model (their order sets the
    angle's sign). ``word``: one of :data:`WORD_DTYPES`; ``adc_bits``-bit codes, 0 V at
    ``offset``. ``chirp_interval_s``: the time from one chirp's start to the next one's,
    s: in a layout of one chirp a ``RADC``, between the chirps of consecutive ``RADC``\ s
    of a frame (the sensor measuring a frame's ``RADC``\ s back to back); in one of many,
    between consecutive chirps of a ``RADC``. A frame's ramp spacing follows from it
    (:meth:`ramp_interval_s`), and with it the radial velocities the decoder gives
    (docs/sensor.md)."""

    receivers: int = 2
    azimuth: tuple[int, int] = (0, 1)
    chirps: int = 1
    samples: int = 256
    order: str = "blocks"
    word: str = "uint16le"
    adc_bits: int = 12
    offset: int = 2048
    chirp_interval_s: float = DEFAULT_RAMP_INTERVAL_S

    def __post_init__(self) -> None:
        object.__setattr__(self, "azimuth", tuple(self.azimuth))
        for name in ("receivers", "chirps", "samples", "adc_bits"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"radc.{name}={v!r} must be an integer >= 1")
        if self.receivers < 2:
            raise ConfigError(f"radc.receivers={self.receivers} must be >= 2 (an azimuth pair)")
        a = self.azimuth
        if not (len(a) == 2 and all(isinstance(i, int) and 0 <= i < self.receivers for i in a) and a[0] != a[1]):
            raise ConfigError(f"radc.azimuth={list(a)!r} must be two different receiver indices in [0, {self.receivers})")
        if self.order not in ORDERS:
            raise ConfigError(f"radc.order={self.order!r} must be one of {list(ORDERS)}")
        if self.word not in WORD_DTYPES:
            raise ConfigError(f"radc.word={self.word!r} must be one of {list(WORD_DTYPES)}")
        if self.adc_bits > ADC_WORD_BITS:
            raise ConfigError(f"radc.adc_bits={self.adc_bits} must be <= {ADC_WORD_BITS} ({ADC_WORD_BITS}-bit words)")
        if isinstance(self.offset, bool) or not isinstance(self.offset, int) or not self.min_word <= self.offset <= self.max_word:
            raise ConfigError(f"radc.offset={self.offset!r} must be an integer code in [{self.min_word}, {self.max_word}]")
        if self.payload_len > 64 << 20:
            raise ConfigError(f"radc: {self.payload_len} bytes per RADC is beyond 64 MiB")
        t = self.chirp_interval_s
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or not 0 < t <= 10.0:
            raise ConfigError(f"radc.chirp_interval_s={t!r} must be a number of seconds in (0, 10]")

    # -- sizes and ranges --------------------------------------------------------------------
    @property
    def payload_len(self) -> int:
        """Bytes of a RADC payload."""
        return self.receivers * self.chirps * self.samples * 2 * np.dtype(self.dtype).itemsize

    @property
    def dtype(self) -> str:
        return WORD_DTYPES[self.word]

    @property
    def signed(self) -> bool:
        return self.word.startswith("int")

    @property
    def min_word(self) -> int:
        return -(1 << (self.adc_bits - 1)) if self.signed else 0

    @property
    def max_word(self) -> int:
        return (1 << (self.adc_bits - 1)) - 1 if self.signed else (1 << self.adc_bits) - 1

    @property
    def full_scale(self) -> float:
        """ADC codes per unit of full scale: 2^(adc_bits - 1)."""
        return float(1 << (self.adc_bits - 1))

    @property
    def words_shape(self) -> tuple[int, int, int, int]:
        """Canonical shape of a RADC's words: (receivers, chirps, samples, 2 (I, Q))."""
        return (self.receivers, self.chirps, self.samples, 2)

    # -- bytes <-> words ---------------------------------------------------------------------
    def words_from_payload(self, payload: bytes) -> np.ndarray:
        """Words (receivers, chirps, samples, 2) of a payload (at least payload_len bytes): a
        view in the wire's dtype; ProtocolError naming the first word out of the ADC range."""
        raw = np.frombuffer(payload, dtype=self.dtype, count=self.payload_len // np.dtype(self.dtype).itemsize)
        lo, hi = int(raw.min(initial=self.min_word)), int(raw.max(initial=self.max_word))
        if lo < self.min_word or hi > self.max_word:
            bad = int(np.argmax((raw < self.min_word) | (raw > self.max_word)))
            raise ProtocolError(f"RADC word {bad} is {int(raw[bad])}, beyond the {self.adc_bits}-bit ADC range "
                                f"[{self.min_word}, {self.max_word}] of this profile")
        r, c, s = self.receivers, self.chirps, self.samples
        if self.order == "blocks":
            words = raw.reshape(r, c, 2, s).transpose(0, 1, 3, 2)
        else:
            words = raw.reshape(r, c, s, 2)
        return words

    def payload_from_words(self, words: np.ndarray) -> bytes:
        """Bytes of words (receivers, chirps, samples, 2); ProtocolError if the shape or a
        value does not fit."""
        w = np.asarray(words)
        if w.shape != self.words_shape:
            raise ProtocolError(f"RADC words must have shape {self.words_shape}, got {w.shape}")
        if w.size and (w.min() < self.min_word or w.max() > self.max_word):
            raise ProtocolError(f"RADC words must lie in [{self.min_word}, {self.max_word}]")
        if self.order == "blocks":
            w = w.transpose(0, 1, 3, 2)
        return np.ascontiguousarray(w).astype(self.dtype).tobytes()

    # -- words <-> complex -------------------------------------------------------------------
    def to_complex(self, words: np.ndarray, dtype=np.complex128, receivers=None, out=None) -> np.ndarray:
        """Words (..., receivers, chirps, samples, 2) -> complex (..., chirps, samples,
        receivers) of ``dtype`` (complex128 or complex64), full-scale units: (word - offset)
        / full_scale in float64, each of I and Q, rounded once to ``dtype``. ``receivers``:
        the receivers taken, in order (None: all); ``out``: a C-ordered array of the result's
        shape and dtype to write into (None: a new one).

        Written in place into the one output array: each receiver's I or Q goes through a
        float64 scratch of one part of one receiver (for complex64), so no full-size
        temporary is made, and the words are read where they are (no copy of a selection)."""
        w = np.asarray(words)
        rx = range(w.shape[-4]) if receivers is None else list(receivers)
        shape = w.shape[:-4] + w.shape[-3:-1] + (len(rx),)
        out = np.empty(shape, dtype=dtype) if out is None else out
        if out.shape != shape or not out.flags.c_contiguous or out.dtype not in (np.complex64, np.complex128):
            raise ConfigError(f"to_complex: out must be a C-ordered complex array of shape {shape}")
        parts = out.view(np.float64 if out.dtype == np.complex128 else np.float32).reshape(shape + (2,))
        scratch = None if out.dtype == np.complex128 else np.empty(shape[:-1], dtype=np.float64)
        for i, r in enumerate(rx):
            for p in range(2):
                dst = parts[..., i, p] if scratch is None else scratch
                np.subtract(w[..., r, :, :, p], self.offset, out=dst, dtype=np.float64)
                dst /= self.full_scale
                if scratch is not None:
                    parts[..., i, p] = scratch
        return out

    def from_complex(self, samples: np.ndarray) -> np.ndarray:
        """Complex (..., chirps, samples, receivers), full-scale units -> words (...,
        receivers, chirps, samples, 2): rounded to the nearest code and clipped to the ADC."""
        s = np.moveaxis(np.asarray(samples), -1, -3)
        iq = np.stack([s.real, s.imag], axis=-1) * self.full_scale + self.offset
        return np.clip(np.rint(iq), self.min_word, self.max_word).astype(np.int32)

    def round_trip(self, samples: np.ndarray) -> np.ndarray:
        """What complex samples (any shape) become through this ADC and back: each of I and
        Q rounded to the nearest code and clipped, full-scale units, same shape."""
        s = np.asarray(samples)
        return self.round_trip_parts(s.real.astype(np.float64)) + 1j * self.round_trip_parts(
            s.imag.astype(np.float64))

    def round_trip_parts(self, x: np.ndarray) -> np.ndarray:
        """:meth:`round_trip` of real I or Q values, float64 of any shape, in place (and returned)."""
        x *= self.full_scale
        x += self.offset
        np.rint(x, out=x)
        np.clip(x, self.min_word, self.max_word, out=x)
        x -= self.offset
        x /= self.full_scale
        return x

    def chirp_indices(self, ramps_per_frame: int, select: str = "first") -> np.ndarray:
        """Which chirps of one RADC make a frame of ``ramps_per_frame`` ramps (R,), for a
        layout of several chirps per RADC: the first R, or every (chirps // R)-th."""
        if select not in CHIRP_SELECT:
            raise ConfigError(f"chirp_select={select!r} must be one of {list(CHIRP_SELECT)}")
        if ramps_per_frame > self.chirps:
            raise ConfigError(f"a frame of {ramps_per_frame} ramps needs {ramps_per_frame} chirps; "
                              f"a RADC of this profile has {self.chirps}")
        step = self.chirps // ramps_per_frame if select == "stride" else 1
        return np.arange(ramps_per_frame) * step

    def ramp_interval_s(self, ramps_per_frame: int, select: str = "first") -> float:
        """The spacing of the ramps of a frame of ``ramps_per_frame`` ramps, s: the chirp
        interval, times the chirps between the ones a frame takes (``select``,
        :meth:`chirp_indices`) in a layout of several chirps a RADC."""
        if self.chirps == 1:
            return float(self.chirp_interval_s)
        idx = self.chirp_indices(ramps_per_frame, select)
        step = int(idx[1] - idx[0]) if idx.size > 1 else 1
        return float(self.chirp_interval_s * step)


@dataclass(frozen=True)
class SensorProfile:
    """A sensor's wire conventions (see the module docstring). ``baud_codes``: INIT code ->
    line speed; ``startup_baud``: the speed after power-up and after GBYE; ``gnfd_bits``:
    frame name -> GNFD mask bit; ``lengths``: frame name -> (min, max) payload bytes of
    the frames passed on uninterpreted."""

    name: str
    radc: RadcLayout = field(default_factory=RadcLayout)
    description: str = ""
    startup_baud: int = 115_200
    baud_codes: dict[int, int] = field(default_factory=lambda: {0: 115_200, 1: 460_800, 2: 921_600,
                                                                  3: 2_000_000, 4: 3_000_000})
    gnfd_bits: dict[str, int] = field(default_factory=lambda: {"RADC": 0x01, "RMRD": 0x02, "PDAT": 0x04, "TDAT": 0x08})
    lengths: dict[str, tuple[int, int]] = field(default_factory=lambda: {"RMRD": (4, 16384), "PDAT": (0, 4096),
                                                                         "TDAT": (0, 4096)})
    source: str = "<builtin>"

    def __post_init__(self) -> None:
        where = f"profile {self.source}"
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError(f"{where}: name={self.name!r} must be a non-empty string")
        codes = self.baud_codes
        if not codes or not all(isinstance(k, int) and k >= 0 and isinstance(v, int) and v > 0 for k, v in codes.items()):
            raise ConfigError(f"{where}: baud_codes must map integer codes >= 0 to speeds > 0, got {codes!r}")
        if len(set(codes.values())) != len(codes):
            raise ConfigError(f"{where}: baud_codes gives one speed two codes: {codes!r}")
        if self.startup_baud not in codes.values():
            raise ConfigError(f"{where}: startup_baud={self.startup_baud!r} must be one of the baud codes' speeds")
        bits = self.gnfd_bits
        if "RADC" not in bits:
            raise ConfigError(f"{where}: gnfd_bits must name RADC")
        for name, bit in bits.items():
            if not (isinstance(bit, int) and bit > 0 and bit & (bit - 1) == 0 and bit < 1 << 32):
                raise ConfigError(f"{where}: gnfd_bits.{name}={bit!r} must be one bit of a uint32")
        if len(set(bits.values())) != len(bits):
            raise ConfigError(f"{where}: two frames share a GNFD bit: {bits!r}")
        for name in list(bits) + list(self.lengths):
            if not (len(name) == 4 and name.isascii() and name.isalnum()):
                raise ConfigError(f"{where}: frame name {name!r} must be 4 ASCII letters or digits")
        for name, lh in self.lengths.items():
            if name.encode() in HEADERS:
                raise ConfigError(f"{where}: lengths.{name}: the length of {name} is fixed by the protocol")
            if not (len(lh) == 2 and all(isinstance(v, int) for v in lh) and 0 <= lh[0] <= lh[1] <= MAX_OTHER_LENGTH):
                raise ConfigError(f"{where}: lengths.{name}={list(lh)!r} must be [min, max] with "
                                  f"0 <= min <= max <= {MAX_OTHER_LENGTH}")
        object.__setattr__(self, "lengths", {k: tuple(v) for k, v in self.lengths.items()})
        n = self.radc.payload_len
        plausible = {b"INIT": (4, 4), b"GNFD": (4, 4), b"GBYE": (0, 4), b"RESP": (1, 4), b"DONE": (4, 4),
                     b"RADC": (n, n + 3)}
        plausible.update({name.encode(): lh for name, lh in self.lengths.items()})
        object.__setattr__(self, "_plausible", plausible)

    def baud_code(self, baud: int) -> int:
        """The INIT code of a line speed; ConfigError if the profile has none."""
        for code, b in self.baud_codes.items():
            if b == baud:
                return code
        raise ConfigError(f"baud={baud!r} must be one of {sorted(self.baud_codes.values())} (profile {self.name})")

    @property
    def frame_mask(self) -> int:
        """All GNFD bits this profile knows."""
        return sum(self.gnfd_bits.values())

    def plausible_length(self) -> dict[bytes, tuple[int, int]]:
        """Header -> inclusive (min, max) payload bytes; lengths may include up to 3
        padding bytes. A header with another length is taken for garbage. Computed once
        (the codec asks per message); do not modify."""
        return self._plausible

    def radar(self, ramps_per_frame: int, select: str = "first") -> RadarConfig:
        """The radar configuration of this sensor's frames of ``ramps_per_frame`` ramps
        (chirps taken by ``select``): its samples a ramp and ramp spacing, the rest the
        K-MD2's (:class:`~radar_driver.model.RadarConfig`'s defaults). The driver's frames
        carry its id; the simulated device measures on the same spacing."""
        return RadarConfig(samples_per_ramp=self.radc.samples, ramps_per_frame=ramps_per_frame,
                           ramp_interval_s=self.radc.ramp_interval_s(ramps_per_frame, select))

    def to_dict(self) -> dict[str, Any]:
        r = self.radc
        return {"name": self.name, "description": self.description, "startup_baud": self.startup_baud,
                "radc": {"receivers": r.receivers, "azimuth": list(r.azimuth), "chirps": r.chirps,
                         "samples": r.samples, "order": r.order, "word": r.word, "adc_bits": r.adc_bits,
                         "offset": r.offset, "chirp_interval_s": r.chirp_interval_s, "payload_len": r.payload_len},
                "baud_codes": {str(k): v for k, v in self.baud_codes.items()},
                "gnfd_bits": dict(self.gnfd_bits), "lengths": {k: list(v) for k, v in self.lengths.items()}}


PROFILES_DIR = Path(__file__).with_name("profiles")
DEFAULT_PROFILE_NAME = "kmd2-blocks"
_TOP_KEYS = {"name", "description", "startup_baud", "radc", "baud_codes", "gnfd_bits", "lengths"}


def profile_from_dict(data: dict[str, Any], source: str = "<dict>") -> SensorProfile:
    """A validated profile from the dict of a TOML file; ConfigError names the key."""
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise ConfigError(f"profile {source}: unknown keys {sorted(unknown)}; known: {sorted(_TOP_KEYS)}")
    radc = data.get("radc", {})
    known = set(RadcLayout.__dataclass_fields__)
    if not isinstance(radc, dict) or set(radc) - known:
        raise ConfigError(f"profile {source}: [radc] has unknown keys {sorted(set(radc) - known)}; known: {sorted(known)}")
    try:
        codes = {int(k): v for k, v in data.get("baud_codes", {}).items()}
    except ValueError:
        raise ConfigError(f"profile {source}: baud_codes keys must be integers") from None
    kw = {k: data[k] for k in ("description", "startup_baud", "gnfd_bits", "lengths") if k in data}
    if codes:
        kw["baud_codes"] = codes
    if "name" not in data:
        raise ConfigError(f"profile {source}: missing name")
    try:
        layout = RadcLayout(**radc)
    except ConfigError as exc:
        raise ConfigError(f"profile {source}: {exc}") from None
    return SensorProfile(name=data["name"], radc=layout, source=source, **kw)


def load_profile(path: str | Path) -> SensorProfile:
    """Load and validate a TOML profile file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read profile {path}: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"profile {path}: not valid TOML: {exc}") from None
    return profile_from_dict(data, str(path))


def packaged_profiles() -> list[str]:
    """Names of the profiles shipped in radar_driver/profiles/."""
    return sorted(p.stem for p in PROFILES_DIR.glob("*.toml"))


def resolve_profile(name_or_path: str | Path | SensorProfile | None) -> SensorProfile:
    """A profile: itself, the default (None), a packaged one by name, or a TOML file."""
    if isinstance(name_or_path, SensorProfile):
        return name_or_path
    if name_or_path is None:
        return DEFAULT_PROFILE
    path = Path(name_or_path)
    if not path.exists() and path.suffix == "" and len(path.parts) == 1:
        packaged = PROFILES_DIR / f"{path.name}.toml"
        if not packaged.exists():
            raise ConfigError(f"no profile file {str(path)!r} and no packaged profile of that name; "
                              f"packaged: {packaged_profiles()}")
        path = packaged
    return load_profile(path)


DEFAULT_PROFILE = load_profile(PROFILES_DIR / f"{DEFAULT_PROFILE_NAME}.toml")
