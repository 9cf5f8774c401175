"""Counters no one can poison: every reader of sequence numbers (a node's intake, the
quantize and localize nodes, the recorder, the Foxglove view, the run's monitor, the
Python API, a recording as a source) judges them with one function,
:func:`pipeline.nodes.counters.judge_seq`: a gap the elapsed time allows is missing, a
restarted count is a reset, and a number out of line (2^63, 2^64 - 1, one back, one
10^6 ahead) is implausible, never frames missing."""

from __future__ import annotations

import random

from pipeline.bus.session import BusConfig
from pipeline.dsp.quantize import QuantizerConfig
from pipeline.nodes.counters import (DEFAULT_SEQ_RATE_HZ, SEQ_AHEAD_S, SEQ_RATE_SLACK, SensorStats, judge_seq,
                                     seq_allowance)
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode
from qradar.api import open_recording
from qradar.monitor import Monitor
from qradar.view import FoxgloveView, ViewConfig
from replay.recorder import RecorderNode
from replay.source import RecordingSource
from test_hardening import mem, raw  # noqa: F401  (mem: the in-memory transport fixture)
from zenoh_helpers import wait_until

#: honest 0..9, then 2^63, 2^64 - 1, one back (3) and one 10^6 ahead, each between honest
#: frames; a real gap (17 -> 20: 18 and 19 lost) and a real restart of the count (0, 1, 2)
FORGED = [*range(10), 2**63, 10, 11, 2**64 - 1, 12, 13, 3, 14, 15, 10**6 + 15, 16, 17, 20, 21, 0, 1, 2]
#: what every reader counts of it: (frames_missing, seq_resets, implausible_seq)
EXPECTED = (2, 1, 4)


def judged(seqs, dt_s=0.001, rate_hz=DEFAULT_SEQ_RATE_HZ, t0_s=0.0):
    track, out, t = None, [0, 0, 0], t0_s
    for s in seqs:
        t += dt_s
        track, v = judge_seq(track, s, t, rate_hz)
        out[0] += v.missing
        out[1] += v.resets
        out[2] += v.implausible
    return tuple(out)


def test_the_judge_on_its_own():
    assert judged(FORGED) == EXPECTED
    assert judged(range(100)) == (0, 0, 0)
    assert judged([0, 1, 2, 2**63, 2**64 - 1, 3, 4]) == (0, 0, 2)  # two out of line in a row
    assert judged([5, 5, 6]) == (0, 0, 1)  # a repeat
    assert judged([0, 1, 10**6, 10**6 + 1, 10**6 + 2]) == (0, 1, 0)  # a sender that restarted far ahead
    # a long real outage: 60 s without a frame at 20 frames/s, then the count goes on (1 199 lost)
    track, _ = judge_seq(None, 0, 0.0, 20.0)
    track, _ = judge_seq(track, 1, 0.05, 20.0)
    track, v = judge_seq(track, 1201, 60.05, 20.0)
    assert (v.missing, v.resets, v.implausible) == (1199, 0, 0)
    # the most a gap may count at once: SEQ_AHEAD_S of frames at the rate, and the time since
    track, _ = judge_seq(None, 0, 10.0, 20.0)
    assert seq_allowance(track, 10.0, 20.0) == int(20.0 * SEQ_AHEAD_S) - 1


def test_a_forger_can_never_count_more_missing_than_the_time_allows():
    """An honest 20 frames/s sender and a forger who puts a number of its choosing between
    every two of its frames (ahead within reach, back, far ahead, following the honest
    count): over 10 s, what is counted missing stays within what the time allows at the
    rate, and nothing the honest sender does counts as missing."""
    rng = random.Random(7)
    rate, track, missing, t, honest = 20.0, None, 0, 0.0, 0
    for i in range(200):
        t += 1 / rate
        track, v = judge_seq(track, honest, t, rate)
        missing += v.missing
        honest += 1
        forged = rng.choice([honest + rng.randrange(1, 40), honest - rng.randrange(1, 1000), honest + 10**6,
                             honest, 2**63])
        track, v = judge_seq(track, forged, t + 0.01, rate)
        missing += v.missing
    assert missing <= rate * (SEQ_RATE_SLACK * t + SEQ_AHEAD_S), missing
    assert judged(range(0, 400, 2), dt_s=0.1, rate_hz=20.0)[0] == 199  # every second frame lost: all counted


def test_skipped_frames_are_in_the_sequence_not_missing():
    st = SensorStats()
    st.note_seq("raw", 0, 0.0)
    st.skipped["raw"] = 5  # 1..5 dropped over budget here
    st.note_seq("raw", 2**63, 0.01)  # out of line: the skipped frames are still ahead of the line
    st.note_seq("raw", 6, 0.02)
    assert (st.frames_missing, st.seq_resets, st.implausible_seq) == (0, 0, 1)


def counts(d):
    return d["frames_missing"], d["seq_resets"], d["implausible_seq"]


def stat_counts(node, sensor):
    with node._lock:
        st = node.stats[sensor]
        return st.frames_missing, st.seq_resets, st.implausible_seq


def test_every_reader_judges_the_same_forged_numbers_alike(mem, tmp_path):
    """The same frames through quantize, localize, the recorder, the view and the run's
    monitor, then the recording through the Python API and as a source: every counter
    the same, and nothing counted missing but the two frames really lost."""
    bus = BusConfig()
    nodes = [QuantizeNode(bus, QuantizerConfig(alpha=1.0, dither_seed=3), session=mem, health_period_s=0.2),
             LocalizeNode(bus, LocalizerConfig(k=1), session=mem, health_period_s=0.2),
             RecorderNode(bus, tmp_path / "forged.mcap", session=mem, health_period_s=0.2),
             FoxgloveView(bus, ViewConfig(port=0, profile_rate_hz=5.0), session=mem, health_period_s=0.2)]
    q, loc, rec, view = nodes
    monitor = Monitor(bus, mem, None, 0, live=None).start()
    try:
        for node in nodes:
            node.start()
        for s in FORGED:
            mem.put("radar/f0/raw", raw("f0", s))
        wait_until(lambda: loc.totals()["frames_out"] == len(FORGED) and monitor.count["targets"] == len(FORGED),
                   20, "the targets of every frame")
        wait_until(lambda: view.totals()["frames_in"] >= 2 * len(FORGED) and rec.written >= 4 * len(FORGED), 20,
                   "the view and the recorder to have every message")
    finally:
        monitor.stop()
        for node in reversed(nodes):
            node.stop()
    assert counts(q.totals()) == EXPECTED
    assert counts(loc.totals()) == EXPECTED
    assert stat_counts(view, "f0") == EXPECTED  # the quantized frames' numbers
    assert stat_counts(rec, "f0") == tuple(2 * x for x in EXPECTED)  # raw and quantized, each judged on its own
    assert (monitor.targets_missing, monitor.targets_seq_resets, monitor.targets_implausible_seq) == EXPECTED
    recording = open_recording(rec.paths[0])
    for topic in ("raw", "quantized", "targets"):
        got = recording.losses(topic, "f0")
        assert got["messages"] == len(FORGED) and counts(got) == EXPECTED, (topic, got)
    source = RecordingSource(rec.paths[0])
    with source:
        assert len(list(source.frames())) == len(FORGED)
    st = source.stats()["f0"]
    assert (st["dropped"], st["seq_resets"], st["implausible_seq"]) == EXPECTED
