"""A frame's path is checked once per hop, at the edge where bytes become arrays.

A probe wraps the check functions (the sensor-id rule on text and on header bytes, the
bit-depth rule, the binary header and length checks, the sample range check) in every
module that holds them, then one simulated frame goes the path the nodes take, in this
process: the driver's frame -> raw wire bytes -> quantizer (decode, quantize, encode) ->
quantized wire bytes -> localizer (decode, localize) -> targets JSON. Each hop's calls
are counted apart and compared with docs/design.md's list ("A frame's path"). Then the same
along the real node path (the nodes on the in-memory transport), with the JSON parses and
the payload copies counted too, and the driver's memory while it builds a frame."""

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
from zenoh_helpers import wait_until

#: the checks the probe counts, by the name the test reports
CHECKS = {"sensor_id": (limits, "sensor_id_problem"), "sensor_id_bytes": (limits, "sensor_id_fields_bad"),
          "bits": (limits, "bits_problem"), "bits_vectorized": (limits, "bits_bad"), "header_and_length": (wire_frames, "_faults"),
          "sample_range": (frame_codec, "bad_samples")}


class Probe(Counter):
    """Calls of each check, and ``frames``: the frames they checked (a vectorized check's
    batch, one for a check of one value). A node that takes frames in batches (a busy host's
    queue holds several) checks a batch with one call: per frame, the frames count."""

    def __init__(self):
        super().__init__()
        self.frames = Counter()

    def clear(self) -> None:
        super().clear()
        self.frames.clear()

    def checked(self, name: str, first) -> None:
        self[name] += 1
        if name == "header_and_length":  # _faults(fields, ...): (n,) arrays by field
            first = next(iter(first.values()))
        self.frames[name] += len(first) if isinstance(first, np.ndarray) and first.ndim >= 1 else 1


@pytest.fixture
def probe(monkeypatch):
    """Counts calls of each check, wherever a module bound it (module globals only)."""
    calls = Probe()
    for name, (module, attr) in CHECKS.items():
        original = getattr(module, attr)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls.checked(_name, args[0])
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


# -- along the real node path: the nodes of `qradar run` on the in-memory transport -----------------
FRAMES = 12


def test_the_nodes_check_each_frame_once_and_parse_each_message_once(probe, tmp_path, monkeypatch):
    """``qradar run``'s nodes in one process on the in-memory transport (pipeline.nodes.transport):
    simulated sensor -> source node -> quantizer -> localizer (with tracks) -> recorder,
    monitor and Foxglove view, which share the process's one parse of each JSON message
    (pipeline.wire.shared). Per frame: each check once per node that takes the frame in, at
    its edge (the decoders' vectorized header pass, the sample range where raw frames become
    arrays); each targets and tracks message parsed once in the process, not once per reader;
    each payload copied once per node it reaches (zenoh's copy into the node's queue)."""
    from pipeline.bus.session import BusConfig
    from pipeline.dsp.track import TrackerConfig
    from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode
    from pipeline.nodes.transport import MemoryPayload, MemoryTransport
    import pipeline.wire.messages as messages
    from pipeline.wire.shared import DecodedOnce
    from qradar.monitor import Monitor
    from qradar.view import FoxgloveView, ViewConfig
    from replay.recorder import RecorderNode

    parses, copies = Counter(), Counter()
    load_json = messages.load_json

    def counted_load(payload, what, *a, **kw):
        parses[what.split(" ", 1)[0]] += 1  # "targets from radar/..." -> "targets"
        return load_json(payload, what, *a, **kw)

    monkeypatch.setattr(messages, "load_json", counted_load)
    to_bytes = MemoryPayload.to_bytes
    monkeypatch.setattr(MemoryPayload, "to_bytes", lambda self: (copies.update([len(self)]), to_bytes(self))[1])
    bus, mem, shared = BusConfig(), MemoryTransport(), DecodedOnce()
    source = SourceNode(bus, SimulatedSource(SimSourceConfig(resolve_scene("chamber"), sensors=1, rate_hz=50.0,
                                                             frames=FRAMES)), session=mem, health_period_s=60)
    nodes = [RecorderNode(bus, tmp_path / "run.mcap", session=mem, decoded=shared, health_period_s=60),
             LocalizeNode(bus, LocalizerConfig(k=2, algo="pbp"), session=mem, tracking=TrackerConfig(),
                          health_period_s=60),
             QuantizeNode(bus, QuantizerConfig(bits=1, alpha=1.0), session=mem, health_period_s=60)]
    monitor = Monitor(bus, mem, None, 0, live=None, decoded=shared).start()
    view = FoxgloveView(bus, ViewConfig(port=0, profile_rate_hz=0), session=mem, health_period_s=60,
                        decoded=shared).start()
    try:
        for n in nodes:
            n.start()
        probe.clear()
        source.start()
        wait_until(lambda: nodes[0].totals()["frames_out"] >= 4 * FRAMES and view.totals()["frames_out"] >= 3 * FRAMES,
                   30, f"{FRAMES} frames' raw, quantized, targets and tracks recorded and shown")
    finally:
        for n in [source, *nodes[::-1], view]:
            n.stop()
        monitor.stop()
        mem.close()
    counts = {k: v / FRAMES for k, v in probe.frames.items()}  # frames checked, a frame
    print(counts, dict(probe), dict(parses), shared.parses, shared.hits, copies)
    # each check once a frame per node taking the frame in: the quantizer and the recorder take raw frames
    # (header and length, the id's 16 bytes, the samples), the localizer and the recorder quantized ones (and
    # their bits); each node checks the id of the sensor it publishes for once a batch (FrameHeaders: source,
    # quantizer, localizer's targets and tracks)
    assert counts["header_and_length"] == 4 and counts["sensor_id_bytes"] == 4
    assert counts["sample_range"] == 2 and counts["bits_vectorized"] == 2
    # the id's text: once a frame where a message is made of it (the source's headers, the tracks message) or read
    # (the targets and tracks JSON, once in the process), plus once per key and node (the intake's look at a key,
    # the key a node puts on, the source's config, the view's first sight of the sensor): none per put or reader
    keys = 5 + 1 + 1 + 3 + 5 + 4 + 2  # the recorder's, localizer's, quantizer's, view's keys; the keys put on; 2
    assert 4 * FRAMES <= probe["sensor_id"] <= 4 * FRAMES + keys, probe["sensor_id"]
    assert 0 < probe["bits"] <= FRAMES  # the quantized writer's, once a batch it writes (docs/design.md's list)
    # the JSON messages: each parsed once for the three readers (the recorder, the monitor, the view)
    assert parses["targets"] == parses["tracks"] == FRAMES
    assert shared.parses >= 2 * FRAMES and shared.hits >= 2 * 2 * FRAMES
    # a payload copied once per node it reaches: raw frames (8 240 B) by the quantizer, the recorder and the
    # monitor; quantized ones (320 B) by the localizer, the recorder and the monitor
    assert copies[8240] == 3 * FRAMES and copies[320] == 3 * FRAMES


@pytest.mark.measure
def test_the_driver_builds_a_frame_with_no_full_size_temporary():
    """FrameAssembler.frame(): the words of a frame's RADCs -> its complex64 (M, 2) array,
    written in place (RadcLayout.to_complex): at its peak the call holds the frame and less
    than one more frame's bytes (a float64 scratch of one receiver's I or Q), bit for bit
    what (words - offset) / full_scale in float64, rounded to complex64, gives."""
    import tracemalloc

    from radar_driver.assembly import FrameAssembler
    from radar_driver.profile import DEFAULT_PROFILE
    from radar_driver.protocol import Done, Radc

    lay = DEFAULT_PROFILE.radc
    ramps = 16  # a large frame (M = 4 096), so that the arrays, not Python's objects, set the peak
    asm = FrameAssembler(DEFAULT_PROFILE, ramps_per_frame=ramps, sensor_id="s")
    rng = np.random.default_rng(5)
    words = [rng.integers(lay.min_word, lay.max_word + 1, lay.words_shape).astype(lay.dtype) for _ in range(ramps)]
    for i, w in enumerate(words):
        asm.take(Radc(w, lay))
        asm.take(Done(i))
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        frame = asm.frame()
        peak = tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()
    size = frame.data.nbytes  # 4 096 x 2 complex64: 64 KiB
    print(f"frame {size} B, peak {peak} B ({peak / size:.2f} frames)")
    assert frame.data.dtype == np.complex64 and frame.data.flags.c_contiguous and frame.data.shape == (ramps * 256, 2)
    assert peak < 2 * size, f"building a frame of {size} B peaked at {peak} B"
    ref = (np.stack([w[list(lay.azimuth), 0] for w in words]).astype(np.float64) - lay.offset)  # (R, 2, N, 2)
    ref = ((ref[..., 0] + 1j * ref[..., 1]) / lay.full_scale).transpose(0, 2, 1).reshape(-1, 2)
    assert np.array_equal(frame.data, ref.astype(np.complex64))
