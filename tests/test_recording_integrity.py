"""A recording loses nothing and lies about nothing: real recorders on real zenoh sessions,
real MCAP files, real damage.

- every kind of bad message (time, size, shape, topic) between good ones is refused before
  any byte of it is written, counted by kind and sensor, and every good one reads back;
- what the recorder says it wrote is what the file holds (each flush reads back; a disk
  that corrupts a chunk is an error in health and the summary);
- every read checks chunk CRCs: one flipped bit anywhere in a recording never returns a
  wrong message, and a damaged chunk is named with its messages counted lost (the API,
  re-processing, the player, ``recover``, ``record --verify``);
- the recorder's memory stays flat with short-lived sensor ids (mcap's Writer included).
"""

import gc
import json
import random
import struct
import signal
import subprocess
import time
import tracemalloc
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

import qradar
from pipeline.bus.session import BusConfig
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.nodes.budget import IntakeBudget
from pipeline.nodes.counters import NO_SENSOR
from pipeline.wire import (HealthMsg, QuantizedFrameMsg, RawFrameMsg, TargetsMsg, TracksMsg, encode_quantized,
                           encode_raw)
from radar_driver.model import RadarConfig
from replay.admission import MAX_JSON_BYTES, REFUSED_KINDS
from replay.errors import UnwritableMessage
from replay.mcapio import DERIVED, McapFile, McapSink, topic_of
from replay.player import PlayConfig, play
from replay.recorder import RecorderNode
from replay.reprocess import load_raw
from zenoh_helpers import Collector, QRADAR, RUNTIME_DECODER, rss_mb, wait_until

ROOT = Path(__file__).resolve().parents[1]
CHAMBER = ROOT / "recordings" / "chamber.mcap"
CONFIG = RadarConfig().config_id()  # M = 512, as the nodes announce it
RNG = np.random.default_rng(36)


def raw(sid: str, seq: int, ts: int | None = None, config_id: int = CONFIG, m: int = 512, payload_sid=None) -> bytes:
    data = (0.1 * (RNG.standard_normal((m, 2)) + 1j * RNG.standard_normal((m, 2)))).astype(np.complex64)
    return encode_raw(RawFrameMsg(payload_sid or sid, seq, 1_000_000 + seq if ts is None else ts, config_id, data))


def quantized(sid: str, seq: int) -> bytes:
    data = 0.1 * (RNG.standard_normal((1, 512, 2)) + 1j * RNG.standard_normal((1, 512, 2)))
    q = quantize_frames(data, QuantizerConfig(), np.array([seq]))
    return encode_quantized(QuantizedFrameMsg(sid, seq, 1_000_000 + seq, CONFIG, 1, float(q.alpha),
                                              float(q.delta[0]), 7, q.codes[0]))


def targets(sid: str, seq: int) -> bytes:
    return TargetsMsg(sid, seq, 1_000_000 + seq, CONFIG, "cml", 1, "quantized",
                      [{"range_m": 4.8, "angle_deg": 10.0, "x_m": 4.7, "y_m": 0.8, "amplitude": 0.2}],
                      2_000_000 + seq).to_json()


def bad_messages(sid: str) -> list[tuple[str, str, bytes]]:
    """(kind, key, payload) of each kind of bad message, on ``sid``'s keys and others'."""
    good_health = json.loads(HealthMsg("viewer", sid, 5).to_json())
    nan_frame = np.zeros((512, 2), np.complex64)
    nan_frame[3, 1] = np.nan
    huge = RawFrameMsg(sid, 9, 9, CONFIG, np.zeros((1 << 20, 2), np.complex64))  # M = 2**20: 16 MB
    bad_magic = bytearray(quantized(sid, 3))
    bad_magic[:4] = b"XXXX"
    return [
        ("refused_time", f"radar/{sid}/health", HealthMsg("viewer", sid, -1).to_json()),
        ("refused_time", f"radar/{sid}/health", json.dumps({**good_health, "timestamp_ns": 10**30}).encode()),
        ("refused_time", f"radar/{sid}/health", json.dumps({**good_health, "timestamp_ns": 2**64}).encode()),
        ("refused_time", f"radar/{sid}/targets", targets(sid, 1).replace(b'"timestamp_ns":1000001',
                                                                         b'"timestamp_ns":-1')),
        ("refused_time", f"radar/{sid}/targets", targets(sid, 2).replace(b'"published_ns":2000002',
                                                                         b'"published_ns":1e30')),
        ("refused_time", f"radar/{sid}/raw", raw(sid, 3, ts=-5)),
        ("refused_time", f"radar/{sid}/tracks", TracksMsg(sid, 4, 4, [], -9).to_json()),
        ("refused_size", f"radar/{sid}/raw", raw(sid, 4, m=300)),
        ("refused_size", f"radar/{sid}/raw", encode_raw(huge)),
        ("refused_size", f"radar/{sid}/health",
         HealthMsg("viewer", sid, 5, extra={"pad": "x" * MAX_JSON_BYTES}).to_json()),
        ("refused_shape", f"radar/{sid}/raw", raw(sid, 5, config_id=7)),
        ("refused_shape", f"radar/{sid}/raw", raw(sid, 6, payload_sid="other")),
        ("refused_shape", f"radar/{sid}/raw", encode_raw(RawFrameMsg(sid, 7, 7, CONFIG, nan_frame))),
        ("refused_shape", f"radar/{sid}/quantized", bytes(bad_magic)),
        ("refused_shape", f"radar/{sid}/targets", b"not json"),
        ("refused_shape", f"radar/{sid}/health", json.dumps({k: good_health[k] for k in
                                                             ("version", "type", "node", "sensor_id",
                                                              "timestamp_ns")}).encode()),
        ("refused_shape", f"radar/{sid}/health", HealthMsg("viewer", "other", 5).to_json()),
        ("refused_shape", f"radar/{sid}/tracks", b'{"version":1,"type":"tracks","tracks":' + b"[" * 100_000),
        ("refused_topic", f"radar/{sid}/pointcloud", b"{}"),
        ("refused_topic", f"radar/{sid}/foo", b"anything"),
        ("refused_topic", "radar/a.b/raw", raw(sid, 8)),
        ("refused_topic", f"radar/{sid}/x/raw", raw(sid, 8)),
    ]


def test_each_kind_of_bad_message_between_good_ones_is_refused_and_every_good_one_reads_back(
        tmp_path, bus, zenoh_session):
    path = tmp_path / "r.mcap"
    rec = RecorderNode(bus, path, session=zenoh_session, health_period_s=60).start()
    col = Collector(zenoh_session, "radar/**")
    good = [("radar/s0/raw", raw("s0", 0))]
    try:
        zenoh_session.put(*good[0])  # s0 is a live sensor: its refusals are its own
        wait_until(lambda: "s0" in rec.stats, 10, "the sensor's state")
        bad = bad_messages("s0")
        seq = 1
        for kind, key, payload in bad:  # each between good ones, on the same keys
            for gkey, gpayload in ((f"radar/s0/raw", raw("s0", seq)), ("radar/s0/quantized", quantized("s0", seq)),
                                   ("radar/s0/targets", targets("s0", seq)),
                                   ("radar/s0/tracks", TracksMsg("s0", seq, 1_000 + seq, [], 2_000 + seq).to_json()),
                                   ("radar/s0/health", HealthMsg("viewer", "s0", 1_000 + seq).to_json())):
                zenoh_session.put(gkey, gpayload)
                good.append((gkey, gpayload))
            zenoh_session.put(key, payload)
            seq += 1
        want = {kind: sum(k == kind for k, _, _ in bad) for kind in REFUSED_KINDS}
        wait_until(lambda: rec.refused() == want and rec.written == len(good), 20,
                   f"{len(good)} messages written and {len(bad)} refused")
        summary = rec.summary()
        totals = rec.totals()
    finally:
        rec.stop()
        col.sub.undeclare()
    # counted by kind, by sensor (the keys of no valid sensor: the unknown senders), and in the node's counters
    assert {k: summary[k] for k in REFUSED_KINDS} == want
    not_a_sensors = want["refused_topic"]  # keys of no sensor (or no qradar topic): the unknown senders'
    assert summary["refused_by_sensor"]["s0"] == {**want, "refused_topic": 0}
    assert summary["refused_by_sensor"]["_unknown"] == {**dict.fromkeys(REFUSED_KINDS, 0), "refused_topic": not_a_sensors}
    assert totals["decode_errors"] + totals["invalid_frames"] == len(bad)
    assert summary["lost"] == summary["verify_errors"] == summary["pending"] == 0 and summary["error"] is None
    # every good message reads back, bytes and order per key; nothing else
    f = McapFile(path)
    got: dict[str, list[bytes]] = {}
    for ch, m in f.messages():
        got.setdefault(ch.topic, []).append(bytes(m.data))
    assert f.intact, f.damage_lines()
    want_by_key: dict[str, list[bytes]] = {}
    for key, payload in good:
        want_by_key.setdefault(key, []).append(payload)
    derived = {key: got.pop(key) for key in list(got) if topic_of(key) in DERIVED}  # written beside (replay.derived)
    assert got == want_by_key
    assert len(derived["radar/s0/pointcloud"]) == len(want_by_key["radar/s0/targets"])
    # a profile of the quantized frames, a scene of the tracks
    assert set(derived) == {"radar/s0/pointcloud", "radar/s0/profile", "radar/s0/scene"}
    pointclouds = [m for msgs in derived.values() for m in msgs]
    # the summary's statistics, mcap's own reader with CRCs checked and the recorder agree
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        stats = reader.get_summary().statistics
        assert sum(1 for _ in reader.iter_messages()) == stats.message_count == f.read
    assert summary["written"] == f.read - len(pointclouds)
    counters = f.metadata_dict()["qradar.recorder_counters"]
    assert {k: int(counters[k]) for k in REFUSED_KINDS} == want


def test_a_message_mcap_cannot_hold_is_refused_before_a_byte_of_it_is_written(tmp_path):
    """The minimal case: 20 good writes and one with a negative publish time (mcap's Writer
    counted it and packed half of it: statistics 21, 11 readable)."""
    sink = McapSink(tmp_path / "m.mcap")
    for i in range(20):
        sink.write("radar/m0/health", HealthMsg("x", "m0", i).to_json(), 10 + i, 10 + i, i)
        if i == 10:
            for log_ns, pub_ns in ((10 + i, -1), (10 + i, 2**64), (-3, 5), (1.5, 5), (True, 5)):
                with pytest.raises(UnwritableMessage, match="is not a time a recording holds"):
                    sink.write("radar/m0/health", b"{}", log_ns, pub_ns, i)
    sink.close()
    assert sink.problems == [] and sink.readable == 20
    with open(tmp_path / "m.mcap", "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        assert reader.get_summary().statistics.message_count == sum(1 for _ in reader.iter_messages()) == 20


def test_a_disk_that_corrupts_a_chunk_is_a_verify_error_in_health_and_the_summary(tmp_path, bus, zenoh_session):
    """What each flush wrote is read back: a chunk that went to the file corrupted (a bit
    flipped between the writer and the disk) is found at once; its messages are lost, not
    written, and the recorder says so."""
    col = Collector(zenoh_session, "radar/v0/health")
    rec = RecorderNode(bus, tmp_path / "v.mcap", session=zenoh_session, topics="radar/*/raw",
                       health_period_s=0.2).start()
    try:
        for seq in range(5):
            zenoh_session.put("radar/v0/raw", raw("v0", seq))
        wait_until(lambda: rec.written == 5, 10, "the first frames read back")
        fh = rec._sink._fh
        clean_write = fh.write

        def flipping_write(data):  # the next chunk record reaches the disk with one bit flipped
            view = bytes(memoryview(data).cast("B"))
            if view[:1] == b"\x06" and len(view) > 1000:
                fh.write = clean_write
                view = view[:600] + bytes([view[600] ^ 0x10]) + view[601:]
            return clean_write(view)

        fh.write = flipping_write
        for seq in range(5, 10):
            zenoh_session.put("radar/v0/raw", raw("v0", seq))
        wait_until(lambda: rec.verify_errors == 1, 10, "the read-back to find the corrupted chunk")
        for seq in range(10, 15):
            zenoh_session.put("radar/v0/raw", raw("v0", seq))
        wait_until(lambda: rec.written == 10, 10, "the frames after it")
        summary = rec.summary()
        wait_until(lambda: any(json.loads(p)["extra"]["recorder"]["verify_errors"] == 1 for p in col.of("/health")
                               if json.loads(p)["node"] == "record"), 10, "health saying so")
    finally:
        rec.stop()
        col.sub.undeclare()
    assert summary["lost_by_topic"] == {"raw": 5} and summary["written"] == 10
    assert "CRC mismatch" in summary["error"] and "v.mcap" in summary["error"]
    f = McapFile(tmp_path / "v.mcap")
    seqs = [m.sequence for ch, m in f.messages() if ch.topic == "radar/v0/raw"]
    assert seqs == [*range(5), *range(10, 15)]
    assert len(f.damaged) == 1 and f.lost_by_topic == {"radar/v0/raw": 5}


# -- damage found on every read ---------------------------------------------------------------
def flipped_copy(src: Path, dst: Path, pos: int, bit: int = 0) -> Path:
    data = bytearray(src.read_bytes())
    data[pos] ^= 1 << bit
    dst.write_bytes(data)
    return dst


def chunk_indexes(path: Path):
    with open(path, "rb") as fh:
        return sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda ci: ci.chunk_start_offset)


def test_one_flipped_bit_anywhere_never_returns_a_wrong_message(tmp_path):
    """60 single-bit flips over the committed recording, complete and cut short (without its
    summary): every message read is one of the original's, byte for byte; when the flip is
    in a chunk, the messages read plus those counted lost are all of them."""
    original = {(ch.topic, m.log_time, bytes(m.data)) for ch, m in McapFile(CHAMBER).messages()}
    total = len(original)
    index = chunk_indexes(CHAMBER)
    data = CHAMBER.read_bytes()
    last = index[-1]
    mi_end = max(last.message_index_offsets.values())
    mi_end += 9 + struct.unpack_from("<Q", data, mi_end + 1)[0]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:mi_end])  # every chunk and its indexes, no summary: read record by record
    rng = random.Random(36)
    in_chunks = 0
    for trial in range(60):
        src = CHAMBER if trial % 2 else cut
        ci = rng.choice(index)
        pos = (rng.randrange(ci.chunk_start_offset, ci.chunk_start_offset + 48) if trial % 3 == 0 else
               rng.randrange(ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length) if trial % 3 == 1 else
               rng.randrange(0, src.stat().st_size))
        f = McapFile(flipped_copy(src, tmp_path / f"f{trial}.mcap", pos, rng.randrange(8)))
        got = [(ch.topic, m.log_time, bytes(m.data)) for ch, m in f.messages()]
        assert set(got) <= original, f"flip at byte {pos} of {src.name}: a message read is not the original's"
        inside = any(c.chunk_start_offset <= pos < c.chunk_start_offset + c.chunk_length for c in index)
        if inside and len(got) < total:
            in_chunks += 1
            assert len(got) + f.lost == total, (pos, src.name, f.damage_lines())
            assert f.damaged and not f.intact
    assert in_chunks >= 20


def test_a_damaged_chunk_is_named_and_its_frames_are_never_returned_by_the_api_reprocess_player(
        tmp_path, bus, zenoh_session):
    index = chunk_indexes(CHAMBER)
    ci = index[2]
    bad = flipped_copy(CHAMBER, tmp_path / "bad.mcap", ci.chunk_start_offset + ci.chunk_length // 2, 3)
    clean = qradar.open_recording(CHAMBER).raw()
    # the API: the intact chunks' frames, each equal to the original's; the damaged chunk named
    rec = qradar.open_recording(bad)
    frames = rec.raw()
    assert 0 < len(frames) < len(clean) and rec.lost["radar/kmd2-0/raw"] == len(clean) - len(frames)
    keep = np.isin(clean.seq, frames.seq)
    assert np.array_equal(clean.data[keep], frames.data) and np.array_equal(clean.seq[keep], frames.seq)
    assert len(rec.damaged) == 1 and f"chunk at byte {ci.chunk_start_offset}" in rec.damaged[0]
    assert "radar/kmd2-0/raw" in rec.damaged[0] and "log time" in rec.damaged[0]
    # re-processing reads the same frames and says what it lost
    loaded = load_raw(bad)
    assert np.array_equal(loaded.seq, frames.seq) and loaded.lost == sum(rec.lost.values()) and loaded.damaged
    # the player publishes none of the damaged chunk's messages and counts them
    col = Collector(zenoh_session, "badplay/**")
    result = play(bad, bus, PlayConfig(fast=True, prefix="badplay"), session=zenoh_session)
    whole = play(CHAMBER, bus, PlayConfig(fast=True, prefix="cleanplay"), session=zenoh_session)
    assert result.damaged == 1 and result.lost > 0 and result.published < whole.published
    wait_until(lambda: len(col.items) >= result.published, 10, "the played messages")
    played_raw = [p for k, p in col.items if k.endswith("/raw")]
    assert sorted(struct.unpack_from("<Q", p, 8)[0] for p in played_raw) == sorted(frames.seq.tolist())
    col.sub.undeclare()


def test_recover_leaves_damaged_chunks_out_and_verify_exits_non_zero_on_damage(tmp_path):
    ci = chunk_indexes(CHAMBER)[1]
    bad = flipped_copy(CHAMBER, tmp_path / "bad.mcap", ci.chunk_start_offset + 5000, 1)
    out = tmp_path / "recovered.mcap"
    proc = subprocess.run([*QRADAR, "recover", str(bad), "-o", str(out)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert "1 damaged chunk(s) left out" in proc.stderr and f"{r['lost']} messages lost" in proc.stderr
    assert len(r["damaged_chunks"]) == 1 and r["damaged_chunks"][0]["offset"] == ci.chunk_start_offset
    n_all = McapFile(CHAMBER).scan()
    g = McapFile(out)
    assert g.scan() == r["messages"] == n_all - r["lost"] and g.intact  # a complete file of what reads
    recovery = g.metadata_dict()["qradar.recovery"]
    assert int(recovery["lost"]) == r["lost"] and f"byte {ci.chunk_start_offset}" in recovery["damage"]
    # --verify: the damaged copy exits 1 naming the chunk; the original and the recovered file exit 0
    proc = subprocess.run([*QRADAR, "record", "--verify", str(bad), str(CHAMBER), str(out)], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 1, proc.stderr
    reports = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [rep["intact"] for rep in reports] == [False, True, True]
    assert reports[0]["lost"] == r["lost"] and f"chunk at byte {ci.chunk_start_offset}" in proc.stderr
    proc = subprocess.run([*QRADAR, "record", "--verify", str(CHAMBER)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and json.loads(proc.stdout)["messages"] == n_all


def test_a_killed_recording_with_its_first_chunk_damaged_loses_that_chunk_only(tmp_path):
    """Every chunk defines the channels of its messages again: a file without a summary (a
    recorder killed) whose first chunk is damaged still reads every later message."""
    sink = McapSink(tmp_path / "k.mcap", chunk_size=4000)
    for i in range(300):
        sink.write(f"radar/k{i % 3}/health", HealthMsg("x", f"k{i % 3}", i).to_json(), 10 + i, 10 + i, i)
        if i % 50 == 49:
            sink.flush()
    data = (tmp_path / "k.mcap").read_bytes()  # no footer, no summary: as SIGKILL leaves it
    sink.close()
    pos = 8
    while data[pos] != 0x06:  # the first chunk
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    f = McapFile(flipped_copy(tmp_path / "k.mcap", tmp_path / "cut.mcap", pos + 200, 2))
    f.path.write_bytes(bytearray(f.path.read_bytes())[:len(data)])
    n = f.scan()
    assert f.truncated and len(f.damaged) == 1 and 0 < f.lost < 50 and n + f.lost == 300
    assert set(f.lost_by_topic) <= {"radar/k0/health", "radar/k1/health", "radar/k2/health"}


# -- memory -------------------------------------------------------------------------------------
@pytest.mark.measure
def test_the_recorders_memory_is_flat_with_short_lived_ids(tmp_path, bus, zenoh_session):
    """1500 short-lived sensor ids a round (more than the recorder's max_dead_channels, 1000
    here), one quantized frame each: every id's state goes when it expires, and mcap's
    Writer's (its channels, statistics and chunk indexes) when the file holds max_dead_channels
    channels of expired ids and the next file starts. After a first round (zenoh's and the
    decoders' caches), the Python heap (traced) after each of three more rounds stays within
    3 MB (0.7 MB apart at most in three runs): the ids of a round cost 10-13 MB at the peak,
    5 KB an id once in, so ids that each left a fifth of their state behind would show.
    (tracemalloc makes a round 4-5 times slower: 6000 ids a round and the default
    DEAD_CHANNELS_MAX took 47 s alone, 90-160 s in the suite; this takes 12-17 s.)"""
    import bench_expiry

    def settled_heap() -> int:
        """The traced heap the recorder settles at: the least of 5 readings 0.2 s apart (not
        what a batch in flight or a health tick holds a moment)."""
        readings = []
        for _ in range(5):
            gc.collect()
            readings.append(tracemalloc.get_traced_memory()[0])
            time.sleep(0.2)
        return min(readings)

    rec = RecorderNode(bus, tmp_path / "ids.mcap", session=zenoh_session, health_period_s=0.5, sensor_expiry_s=0.3,
                       topics="radar/*/quantized", intake=IntakeBudget.unlimited(), max_dead_channels=1000).start()
    n_ids, rounds = 1_500, 4
    msgs = [bench_expiry.frames([f"r{r}i{i}" for i in range(n_ids)]) for r in range(rounds)]
    heaps, rss, sent = [], [], 0
    started = time.monotonic()
    try:
        for r in range(rounds):
            if r == 1:
                tracemalloc.start()
            for key, payload in msgs[r]:
                zenoh_session.put(key, payload)
            sent += n_ids
            msgs[r] = None
            # (bounded by the work, not a pace: under tracemalloc on a host loaded by two busy loops and
            # two other workers, a round of 10 000 frames took over 60 s)
            wait_until(lambda: rec.written == sent, 240, f"round {r}: {sent} frames read back")
            wait_until(lambda: not (set(rec.stats) - {NO_SENSOR}) and rec.summary()["channels"] < rec.max_dead_channels,
                       30, f"round {r}: the ids to expire and their channels to go with a new file")
            rss.append(round(rss_mb(), 1))
            if r:
                heaps.append(settled_heap())
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        rec.stop()
    mb = [round((h - heaps[0]) / 2**20, 2) for h in heaps]
    print(f"{rounds} rounds of {n_ids} ids: Python heap after rounds 1-{rounds - 1}: {mb} MB (from the first), peak "
          f"+{(peak - heaps[0]) / 2**20:.1f} MB; RSS after each round {rss} MB; {len(rec.paths)} files")
    assert peak - heaps[0] > 5 * 2**20, "the ids' state was never there at once: the test measures nothing"
    assert len(rec.paths) >= rounds - 1  # the files rolled over as expired ids' channels piled up
    assert max(heaps) - min(heaps) < 3 * 2**20, mb
    by_topic = Counter(ch.topic.rsplit("/", 1)[-1] for p in rec.paths for ch, _ in McapFile(p).messages())
    assert by_topic["quantized"] == sent and rec.summary()["lost"] == 0
    # a range profile of an id's first frame while the recorder's budget of them allows (replay.derived), no more:
    # at most the bucket's one second plus its rate over the run (on a loaded host the rounds last longer and the
    # budget lets more through: 3022 of 6000 once, so no fixed share)
    budget = rec.derivations.config.profile_budget_hz
    assert set(by_topic) == {"quantized", "profile"}
    assert 0 < by_topic["profile"] <= budget * (time.monotonic() - started + 1), (by_topic, budget)
    assert by_topic["profile"] + rec.derivations.profiles_skipped == sent


# -- the measured scenarios, end to end ----------------------------------------------------------
def forged_health(sensor: str, i: int) -> bytes:
    """A health message whose timestamp no recording can hold (-1, 1e30, 2**64), as any
    identity that may publish health can send it."""
    obj = json.loads(HealthMsg("viewer", sensor, 0).to_json())
    obj["timestamp_ns"] = (-1, 10**30, 2**64)[i % 3]
    return json.dumps(obj).encode()


def check_run_recording(summary: dict, path: Path, frames: int, forged: int) -> None:
    """The run's own recording holds every frame it made, says what it refused, and its
    statistics, mcap's reader (CRCs checked) and the recorder's ``written`` agree."""
    rec = summary["recording"]
    assert rec["lost"] == rec["verify_errors"] == 0 and rec["error"] is None, rec
    assert rec["refused_time"] == forged and rec["refused_by_sensor"]["kmd2-0"]["refused_time"] == forged, rec
    f = McapFile(path)
    by_topic: dict[str, list[int]] = {}
    for ch, m in f.messages():
        by_topic.setdefault(ch.topic.rsplit("/", 1)[-1], []).append(m.sequence)
    assert f.intact, f.damage_lines()
    for topic in ("raw", "quantized", "targets"):  # every frame of the run, in the file
        assert sorted(by_topic[topic]) == list(range(frames)), topic
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        assert sum(1 for _ in reader.iter_messages()) == reader.get_summary().statistics.message_count == f.read
    assert rec["written"] == f.read - sum(len(by_topic.get(t, [])) for t in DERIVED)


def recorder_refused_time(payloads: list[bytes]) -> int:
    """The most health messages of kmd2-0 the run's recorder says (its own health) it refused for their time."""
    counts = [0]
    for p in payloads:
        recorder = json.loads(p).get("extra", {}).get("recorder")
        if recorder:
            counts.append(recorder["sensor_refused"]["refused_time"])
    return max(counts)


def run_with_forged_health(tmp_path: Path, run_args: list[str], connect, n: int, pause_s: float) -> dict:
    """``qradar run RUN_ARGS --record rec.mcap`` and ``n`` forged health messages put on
    kmd2-0's health key from the session ``connect()`` opens, once frames flow; the run ends
    (SIGINT, its normal end) once its recorder's health counts the ``n`` refused: not after a
    number of frames, which a slow connect on a loaded host can outlast. Returns the run's
    JSON summary after checking its recording (every frame the run made)."""
    path = tmp_path / "rec.mcap"
    run = subprocess.Popen([*QRADAR, "run", *RUNTIME_DECODER, *run_args, "--record", str(path), "--duration",
                            "120", "--scene", "single", "--K", "1", "--json"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        session = connect()
        col = Collector(session, "radar/kmd2-0/raw")
        health = Collector(session, "radar/kmd2-0/health")
        wait_until(lambda: len(col.items) >= 5 or run.poll() is not None, 60, "the run's first frames")
        for i in range(n):  # while frames flow
            session.put("radar/kmd2-0/health", forged_health("kmd2-0", i))
            time.sleep(pause_s)
        wait_until(lambda: recorder_refused_time(health.of("kmd2-0/health")) >= n or run.poll() is not None, 60,
                   lambda: f"the recorder's health to count {n} refused (it says "
                           f"{recorder_refused_time(health.of('kmd2-0/health'))})")
        assert run.poll() is None, run.communicate(timeout=20)[1][-3000:]
        run.send_signal(signal.SIGINT)
        out, err = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate(timeout=20)
    assert run.returncode == 0, err
    summary = json.loads(out)
    assert summary["interrupted"] is True and summary["frames_raw"] >= 5, summary
    check_run_recording(summary, path, summary["frames_raw"], n)
    return summary


def test_bad_timestamps_from_a_peer_lose_nothing_of_a_run_recording(tmp_path, free_port, connect_when_ready):
    """`qradar run --listen EP --record rec.mcap` and a peer sending health with timestamps
    no recording holds (which broke the recorder's open chunk: frames missing, "lost": 0):
    three each of -1, 1e30 and 2**64."""
    ep = f"tcp/127.0.0.1:{free_port}"
    run_with_forged_health(tmp_path, ["--listen", ep], lambda: connect_when_ready(ep, timeout_s=30), 9, 0.1)


@pytest.mark.skipif(subprocess.run(["which", "openssl"], capture_output=True).returncode != 0,
                    reason="makes certificates with openssl")
def test_the_viewer_identity_cannot_harm_a_secure_run_recording(tmp_path, free_port, connect_when_ready):
    """`qradar run --secure` and the viewer identity, which may publish only health, sending
    20 health messages with timestamps no recording holds: the recording keeps every frame
    and counts the 20 refused (it lost 135 of ~200 frames and said "lost 0")."""
    from pipeline.bus.security import SecureConfig

    lab = tmp_path / "lab"
    proc = subprocess.run([*QRADAR, "security", "init", str(lab)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    ep = f"tls/127.0.0.1:{free_port}"
    run_with_forged_health(tmp_path, ["--secure", str(lab), "--listen", ep],
                           lambda: connect_when_ready(ep, timeout_s=30, mode="client", secure=SecureConfig(lab, "viewer")),
                           20, 0.05)
