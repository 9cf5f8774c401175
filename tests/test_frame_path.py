"""A frame's path is checked once per hop, at the edge where bytes become arrays.

A probe wraps the check functions (the sensor-id rule on text and on header bytes, the
bit-depth rule, the binary header and length checks, the sample range check) in every
module that holds them, then one simulated frame goes the path the nodes take, in this
process: the driver's frame -> raw wire bytes -> quantizer (decode, quantize, encode) ->
quantized wire bytes -> localizer (decode, localize) -> targets JSON. Each hop's calls
are counted apart and compared with docs/design.md's list ("A frame's path")."""

import sys
from collections import Counter

import numpy as np
import pytest

import pipeline.nodes.frame_codec as frame_codec
import pipeline.wire.frames as wire_frames
import radar_driver.limits as limits
from pipeline.dsp.decode import DecoderConfig, decode_batch
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames, sensor_dither_seeds
from pipeline.wire import (FrameHeaders, decode_quantized_batch, decode_raw_batch, decode_targets,
                           encode_quantized_batch, encode_raw_batch, encode_targets_batch)
from radar_driver.scene import resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource

#: the checks the probe counts, by the name the test reports
CHECKS = {"sensor_id": (limits, "sensor_id_problem"), "sensor_id_bytes": (limits, "sensor_id_fields_bad"),
          "bits": (limits, "bits_problem"), "bits_vectorized": (limits, "bits_bad"), "header_and_length": (wire_frames, "_faults"),
          "sample_range": (frame_codec, "bad_samples")}


@pytest.fixture
def probe(monkeypatch):
    """Counts calls of each check, wherever a module bound it (module globals only)."""
    calls = Counter()
    for name, (module, attr) in CHECKS.items():
        original = getattr(module, attr)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(*args, **kwargs)

        for mod in list(sys.modules.values()):
            if getattr(mod, "__name__", "").split(".")[0] in ("radar_driver", "pipeline", "replay", "qradar") \
                    and getattr(mod, attr, None) is original:
                monkeypatch.setattr(mod, attr, counted)
    return calls


def test_each_check_once_per_hop_at_the_edge(probe):
    scene = resolve_scene("chamber")
    config = QuantizerConfig(bits=1, alpha=1.0)  # built (and checked) when the node starts
    decoder = DecoderConfig()
    with SimulatedSource(SimSourceConfig(scene, sensors=1, rate_hz=0.0, frames=1)) as source:
        (frame,) = list(source.frames(1))
    hops = {}

    def hop(name):
        hops[name] = dict(probe)
        probe.clear()

    probe.clear()
    # the sensor node: the driver's frame (its id checked by the driver's config) -> raw bytes
    headers = FrameHeaders([frame.sensor_id], [frame.seq], [frame.timestamp_ns], [frame.config_id])
    raw = encode_raw_batch(headers, frame.data[None])
    hop("sensor")
    # the quantizer node: raw bytes -> a typed raw batch -> codes -> quantized bytes
    (group,), errors = decode_raw_batch(raw, ["radar/sim0/raw"])
    assert not errors and group.data.dtype == np.complex64
    assert not frame_codec.bad_samples(group.data).any()
    q = quantize_frames(group.data, config, group.headers.seq,
                        dither_seed=sensor_dither_seeds(config.dither_seed, group.headers.sensor_id))
    quantized = encode_quantized_batch(group.headers, q)
    hop("quantizer")
    # the localizer node: quantized bytes -> typed QuantizedFrames -> targets JSON
    (qgroup,), errors = decode_quantized_batch(quantized, ["radar/sim0/quantized"])
    assert not errors
    det = decode_batch(qgroup.frames, scene.radar, 2, decoder)
    (targets,) = encode_targets_batch(qgroup.headers, det, "pbp", 2, "quantized", 0)
    hop("localizer")
    msg = decode_targets(targets, "radar/sim0/targets")
    hop("consumer")

    assert msg.sensor_id == frame.sensor_id and msg.seq == frame.seq and len(msg.targets) == 2
    print(hops)
    assert hops == {"sensor": {"sensor_id": 1},
                    "quantizer": {"sensor_id_bytes": 1, "header_and_length": 1, "sample_range": 1, "bits": 1},
                    "localizer": {"sensor_id_bytes": 1, "header_and_length": 1, "bits_vectorized": 1},
                    "consumer": {"sensor_id": 1}}


def test_the_probe_sees_a_check_that_fails(probe):
    """The counted checks are the ones that refuse bad input (the probe is not blind)."""
    from pipeline.wire import WireError
    with pytest.raises(WireError, match="sensor_id='bad id'"):
        FrameHeaders(["bad id"], [0], [0], [0])
    bad = encode_raw_batch(FrameHeaders(["ok"], [0], [0], [0]), np.zeros((1, 4, 2), np.complex64))[0][:-1]
    _, errors = decode_raw_batch([bad], ["radar/ok/raw"])
    assert "111 bytes, expected 112 for M=4" in str(errors[0][1])
    assert probe == {"sensor_id": 2, "sensor_id_bytes": 1, "header_and_length": 1}
