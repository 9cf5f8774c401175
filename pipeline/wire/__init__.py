"""Wire formats of the zenoh stream (byte layouts in docs/wire-formats.md): the names
callers import, from the modules of each format.

Raw and quantized frames are compact binary, little-endian, behind one 48-byte common
header (:mod:`pipeline.wire.frames`); targets, tracks and health are UTF-8 JSON objects
(:mod:`pipeline.wire.messages`). Every message carries the format version, the sensor id, the
sequence number, the sensor timestamp (ns) and the radar configuration id. One writer and
one reader per format, all for batches (a single frame is a batch of one); decoders check
everything where bytes become arrays and raise :class:`WireError` naming what is wrong
and where (the ``source``, e.g. the zenoh key).
"""

from __future__ import annotations

from radar_driver.limits import SENSOR_ID_MAX

from pipeline.errors import WireError
from pipeline.keys import TOPICS
from pipeline.wire.frames import (COMMON, COMMON_DTYPE, COMMON_FIELDS, FLAG_DITHERED, GENERATOR_VERSIONS, HEADER_LEN,
                          KIND_QUANTIZED, KIND_RAW, MAGIC, MAX_BITS, MAX_M, QUANT_DTYPE, QUANT_EXT, QUANT_EXT_FIELDS,
                          QUANT_HEADER_LEN, RAW_VERSION, VERSIONS, FrameHeaders, QuantizedFrameMsg,
                          QuantizedGroup, RawFrameMsg, RawGroup, check_sensor_id, decode_quantized,
                          decode_quantized_batch, decode_raw, decode_raw_batch, encode_quantized,
                          encode_quantized_batch, encode_raw, encode_raw_batch, frame_size, peek_seq,
                          quantized_batch)
from pipeline.wire.messages import (HEALTH_LOSS_FIELDS, JSON_VERSION, MAX_JSON_BYTES, MAX_JSON_DEPTH,
                        OPTIONAL_TARGET_FIELDS, TARGET_DIGITS, TARGET_FIELDS, TRACK_FIELDS, HealthMsg, TargetColumns,
                        TargetsMsg, TracksMsg, decode_health, decode_targets, decode_tracks, encode_targets_batch,
                        load_json)

__all__ = ["COMMON", "COMMON_DTYPE", "COMMON_FIELDS", "FLAG_DITHERED", "GENERATOR_VERSIONS", "HEADER_LEN",
           "HEALTH_LOSS_FIELDS", "JSON_VERSION", "KIND_QUANTIZED", "KIND_RAW", "MAGIC", "MAX_BITS", "MAX_JSON_BYTES",
           "MAX_JSON_DEPTH", "MAX_M",
           "OPTIONAL_TARGET_FIELDS", "QUANT_DTYPE", "QUANT_EXT", "QUANT_EXT_FIELDS", "QUANT_HEADER_LEN",
           "RAW_VERSION", "SENSOR_ID_MAX", "TARGET_DIGITS", "TARGET_FIELDS", "TOPICS", "TRACK_FIELDS", "VERSIONS",
           "FrameHeaders", "HealthMsg", "QuantizedFrameMsg", "QuantizedGroup", "RawFrameMsg", "RawGroup",
           "TargetColumns", "TargetsMsg", "TracksMsg", "WireError", "check_sensor_id", "decode_health",
           "decode_quantized", "decode_quantized_batch", "decode_raw", "decode_raw_batch", "decode_targets",
           "decode_tracks", "encode_quantized", "encode_quantized_batch", "encode_raw", "encode_raw_batch",
           "encode_targets_batch", "frame_size", "load_json", "peek_seq", "quantized_batch"]
