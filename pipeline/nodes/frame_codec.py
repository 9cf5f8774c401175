"""One codec per kind of frame a node takes in (``raw``, ``quantized``), chosen once by
the node's input topic: how a batch of payloads decodes, how many measurements M a
decoded group has, how a group or its frames are subset, what the decoder is given, and
how frames of that kind encode.
"""

from __future__ import annotations

from dataclasses import replace
from typing import ClassVar, Protocol, Sequence

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.errors import ParameterError, WireError
from pipeline.dsp.quantize import MAX_BITS, QuantizedFrames, packed_size
from pipeline.wire import (
    HEADER_LEN,
    QUANT_HEADER_LEN,
    FrameHeaders,
    QuantizedGroup,
    RawGroup,
    decode_quantized_batch,
    decode_raw_batch,
    encode_quantized_batch,
    encode_raw_batch,
)

#: the largest |Re| or |Im| of a raw sample a node accepts, full-scale units (the ADC's
#: full scale is 1; beyond this a frame is refused as invalid, not quantized)
MAX_SAMPLE = 1e4


def bad_samples(frames: np.ndarray) -> np.ndarray:
    """(B,) True where a frame (B, M, 2) has a sample that is not finite or beyond MAX_SAMPLE."""
    parts = frames.view(np.float32 if frames.dtype == np.complex64 else np.float64)
    return ~(np.abs(parts) <= MAX_SAMPLE).reshape(frames.shape[0], -1).all(axis=1)  # NaN fails <=


class FrameCodec(Protocol):
    """The frames of one input topic."""

    topic: ClassVar[str]

    def decode(self, payloads: Sequence[bytes], keys: Sequence[str]) -> tuple[list, list[tuple[int, WireError]]]:
        """Groups of frames of one M (with ``index``: their positions in ``payloads``) and
        the (position, error) of the payloads that do not decode."""

    def lengths(self, ms: set[int]) -> frozenset[int]:
        """Every payload length a frame of M in ``ms`` can have, bytes."""

    def n_measurements(self, group) -> int:
        """M of a decoded group."""

    def take(self, group, keep: np.ndarray):
        """The group's frames at positions ``keep``."""

    def frames(self, group) -> tuple[object, np.ndarray, np.ndarray | None]:
        """What the decoder takes of a group: (frames, dithered (B,) bool, bad (B,) bool
        where a raw sample is not finite or beyond MAX_SAMPLE, or None)."""

    def select(self, frames, idx: np.ndarray):
        """Frames ``idx`` of what :meth:`frames` gave."""

    def encode(self, headers: FrameHeaders, frames) -> list[bytes]:
        """One payload per frame."""


class RawCodec:
    """Raw frames: ``data`` (B, M, 2) complex64, 16 bytes a measurement."""

    topic: ClassVar[str] = "raw"

    def decode(self, payloads: Sequence[bytes], keys: Sequence[str]) -> tuple[list[RawGroup], list]:
        return decode_raw_batch(payloads, keys)

    def lengths(self, ms: set[int]) -> frozenset[int]:
        return frozenset(HEADER_LEN + 16 * m for m in ms)

    def n_measurements(self, group: RawGroup) -> int:
        return group.data.shape[1]

    def take(self, group: RawGroup, keep: np.ndarray) -> RawGroup:
        return replace(group, headers=group.headers.take(keep), index=group.index[keep], data=group.data[keep])

    def frames(self, group: RawGroup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return group.data.astype(np.complex128), np.zeros(len(group.headers), dtype=bool), bad_samples(group.data)

    def select(self, frames: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return frames[idx]

    def encode(self, headers: FrameHeaders, frames: np.ndarray) -> list[bytes]:
        return encode_raw_batch(headers, frames)


class QuantizedCodec:
    """Quantized frames: :class:`~pipeline.dsp.quantize.QuantizedFrames` of 1..MAX_BITS bits."""

    topic: ClassVar[str] = "quantized"

    def decode(self, payloads: Sequence[bytes], keys: Sequence[str]) -> tuple[list[QuantizedGroup], list]:
        return decode_quantized_batch(payloads, keys)

    def lengths(self, ms: set[int]) -> frozenset[int]:
        return frozenset(QUANT_HEADER_LEN + packed_size(4 * m, b) for m in ms for b in range(1, MAX_BITS + 1))

    def n_measurements(self, group: QuantizedGroup) -> int:
        return group.frames.codes.shape[1]

    def take(self, group: QuantizedGroup, keep: np.ndarray) -> QuantizedGroup:
        return replace(group, headers=group.headers.take(keep), index=group.index[keep],
                       frames=group.frames.take(keep))

    def frames(self, group: QuantizedGroup) -> tuple[QuantizedFrames, np.ndarray, None]:
        dithered = np.asarray(group.frames.alpha) > 0  # one alpha for the batch, or one per frame
        if dithered.ndim == 0:
            dithered = np.full(len(group.headers), bool(dithered))
        return group.frames, dithered, None

    def select(self, frames: QuantizedFrames, idx: np.ndarray) -> QuantizedFrames:
        return frames.take(idx)

    def encode(self, headers: FrameHeaders, frames: QuantizedFrames) -> list[bytes]:
        return encode_quantized_batch(headers, frames)


#: the codec of each input topic
CODECS: dict[str, FrameCodec] = {c.topic: c for c in (RawCodec(), QuantizedCodec())}


def codec_for(topic: str) -> FrameCodec:
    """The codec of frames on ``topic``."""
    codec = CODECS.get(topic)
    if codec is None:
        raise ParameterError(f"input topic {topic!r} has no frame codec (one of {', '.join(CODECS)})")
    return codec


def radar_configs(radar: RadarConfig, max_ramps: int) -> dict[int, RadarConfig]:
    """The announced configurations: ``radar`` with 1..max_ramps ramps per frame, by config id."""
    if not (isinstance(max_ramps, int) and max_ramps >= 1):
        raise ParameterError(f"max_ramps={max_ramps!r} must be an integer >= 1")
    return {c.config_id(): c for c in (replace(radar, ramps_per_frame=r) for r in range(1, max_ramps + 1))}


def check_frames(codec: FrameCodec, configs: dict[int, RadarConfig], payloads: Sequence[bytes],
                 keys: Sequence[str], key_sensors: Sequence[str]) -> tuple[list, list[tuple[int, str, str]]]:
    """Decode payloads with ``codec``, in one vectorized call per length, and keep the frames
    whose sensor id is their key's (``key_sensors``), whose config id is one of ``configs``
    (the announced configurations) and whose M is that configuration's. Returns the groups
    of the good frames and, for each payload refused, (position, counter kind
    (``decode_errors`` or ``invalid_frames``), one-line reason naming the key): the checks
    every node and the recorder apply to a frame."""
    groups, errors = codec.decode(payloads, keys)
    refused: list[tuple[int, str, str]] = [(i, "decode_errors", str(exc)) for i, exc in errors]
    out = []
    for g in groups:
        h = g.headers
        m = codec.n_measurements(g)
        ok = np.ones(len(h), dtype=bool)
        for j, (i, sid) in enumerate(zip(g.index.tolist(), h.sensor_id)):
            if sid != key_sensors[i]:
                ok[j] = False
                refused.append((i, "decode_errors", f"frame from {keys[i]}: sensor id {sid!r} does not match the key"))
        cids = h.config_id
        for cid in ([int(cids[0])] if (cids == cids[0]).all() else np.unique(cids).tolist()):
            radar = configs.get(cid)
            if radar is not None and radar.n_measurements == m:
                continue
            why = (f"unknown radar config id {cid:#010x}" if radar is None else
                   f"M={m} but its radar config has M={radar.n_measurements}")
            for j in np.flatnonzero(ok & (h.config_id == cid)).tolist():
                ok[j] = False
                i = int(g.index[j])
                refused.append((i, "invalid_frames", f"frame {int(h.seq[j])} from {keys[i]}: {why}"))
        if ok.all():
            out.append(g)
        elif ok.any():
            out.append(codec.take(g, np.flatnonzero(ok)))
    return out, refused
