"""MCAP recording, replay and re-processing on real files and real zenoh sessions."""

import base64
import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import Writer

from pipeline.bus.session import BusConfig
from pipeline.dsp.quantize import (DITHER_COUNTER, DITHER_SEEDSEQ, QuantizerConfig, quantize, quantize_frames,
                               sensor_dither_seed)
from pipeline.wire import (HealthMsg, RawFrameMsg, TargetsMsg, decode_quantized, decode_quantized_batch, decode_raw,
                           encode_raw)
from radar_driver.model import RadarConfig
from replay.errors import NoQradarChannelsError, NotMcapError, ReplayError
from replay.mcapio import McapFile
from replay.player import PlayConfig, play
from replay.recorder import RecorderNode
from replay.reprocess import load_raw, parse_alphas, radar_for, sweep, truth_scene
from zenoh_helpers import QRADAR, RUNTIME_DECODER, Collector, qradar, stop_when, wait_until

ROOT = Path(__file__).resolve().parents[1]
CHAMBER = ROOT / "recordings" / "chamber.mcap"
#: the config ids of the default K-MD2 with 2 ramps a frame (M = 512) and with one (M = 256):
#: the recorder records only frames of an announced configuration, as the nodes take
CONFIG_512 = RadarConfig().config_id()
CONFIG_256 = RadarConfig(ramps_per_frame=1).config_id()


def traffic(n=30, sensors=("a0", "b1")):
    """(key, payload) of raw, targets and health messages for a few sensors."""
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        for s in sensors:
            data = (rng.standard_normal((512, 2)) + 1j * rng.standard_normal((512, 2))).astype(np.complex64)
            out.append((f"radar/{s}/raw", encode_raw(RawFrameMsg(s, i, 1_000 + i, CONFIG_512, data))))
            t = TargetsMsg(s, i, 1_000 + i, CONFIG_512, "pbp", 1, "quantized",
                           [{"range_m": 4.8, "angle_deg": -20.0, "x_m": 4.5, "y_m": -1.6, "amplitude": 0.1}], 2_000 + i)
            out.append((f"radar/{s}/targets", t.to_json()))
    return out


def per_topic(pairs):
    d = {}
    for k, p in pairs:
        d.setdefault(k, []).append(p)
    return d


def test_record_then_replay_round_trip(tmp_path, bus, zenoh_session):
    session = zenoh_session
    path = tmp_path / "rt.mcap"
    rec = RecorderNode(bus, path, session=session, topics="radar/*/raw", health_period_s=60).start()
    rec2 = RecorderNode(bus, tmp_path / "all.mcap", session=session, health_period_s=60).start()
    sent = traffic()
    for key, payload in sent:
        session.put(key, payload)
    wait_until(lambda: rec2.written >= len(sent), 10, "recorder to write everything")
    # rec2 (every topic) first: rec's last health as it stops would reach rec2 as rec2 stops, be
    # counted in its drops (received, not processed), and fail the check below on a loaded host
    rec2.stop()
    rec.stop()
    f = McapFile(tmp_path / "all.mcap")
    msgs = list(f.messages())
    assert not f.truncated
    topics = {ch.topic for ch, _ in msgs}
    assert {"radar/a0/raw", "radar/a0/targets", "radar/a0/pointcloud", "radar/b1/targets"} <= topics
    assert {ch.topic for ch, _ in McapFile(path).messages()} == {"radar/a0/raw", "radar/b1/raw"}  # --topics
    raw = [(ch, m) for ch, m in msgs if ch.topic == "radar/a0/raw"]
    assert [m.sequence for _, m in raw] == list(range(30))  # the frames' seq
    assert [m.publish_time for _, m in raw] == [1_000 + i for i in range(30)]  # the sensor timestamps
    assert all(m.log_time > 1e18 for _, m in raw)  # arrival at the recorder, ns since the epoch
    counters = f.metadata_dict()["qradar.recorder_counters"]
    assert int(counters["dropped"]) == 0 and int(counters["written"]) == int(counters["received"])

    col = Collector(session, "replay/**")
    result = play(tmp_path / "all.mcap", bus, PlayConfig(fast=True, prefix="replay", topics="radar/*/raw"),
                  session=session)
    wait_until(lambda: len(col.items) == 60, 10, "replayed raw frames")
    got = per_topic((k.replace("replay/", "radar/", 1), p) for k, p in col.items)
    want = per_topic((k, p) for k, p in sent if k.endswith("/raw"))
    assert got == want  # same messages, bytes and order per topic
    assert result.published == 60 and not result.truncated
    col.sub.undeclare()


def test_player_keeps_the_original_timing_scaled(tmp_path, bus, zenoh_session):
    session = zenoh_session
    rec = RecorderNode(bus, tmp_path / "t.mcap", session=session, health_period_s=60).start()
    for i in range(6):
        session.put("radar/tm/health", HealthMsg("x", "tm", i).to_json())
        time.sleep(0.1)
    wait_until(lambda: rec.written == 6, 10)
    rec.stop()
    t0 = time.monotonic()
    r = play(tmp_path / "t.mcap", bus, PlayConfig(rate=2.0), session=session)
    elapsed = time.monotonic() - t0
    # 0.5 s of traffic at twice the speed: never faster than that (a busy host may make it slower, so no
    # upper bound)
    assert r.published == 6 and elapsed >= 0.2
    r = play(tmp_path / "t.mcap", bus, PlayConfig(fast=True, start_s=0.25), session=session)
    assert 2 <= r.published <= 4
    # looped: stopped once a third pass has begun (its messages seen), not after a time a busy host stretches
    col = Collector(session, "loop/**")
    stop = threading.Event()
    threading.Thread(target=stop_when, args=(lambda: len(col.items) >= 13, stop, 60), daemon=True).start()
    r = play(tmp_path / "t.mcap", bus, PlayConfig(rate=4.0, loop=True, prefix="loop"), session=session, stop=stop)
    assert r.loops >= 2 and r.published >= 12


def test_split_by_duration(tmp_path, bus, zenoh_session):
    session = zenoh_session
    rec = RecorderNode(bus, tmp_path / "s.mcap", session=session, split_duration_s=0.3, health_period_s=60).start()
    for i in range(10):
        session.put("radar/sp/raw", encode_raw(RawFrameMsg("sp", i, i, CONFIG_256, np.zeros((256, 2), np.complex64))))
        time.sleep(0.1)
    wait_until(lambda: rec.written == 10, 10)
    parts = len(rec.paths)
    time.sleep(1.0)  # time itself is tested: over three split periods with nothing arriving
    assert len(rec.paths) == parts  # a file is started only with a message to put in it
    rec.stop()
    assert len(rec.paths) >= 2
    counts = [McapFile(p).scan() for p in rec.paths]
    assert sum(counts) == 10 and min(counts) >= 1, counts  # no file of the set holds its metadata alone


def test_sigkill_loses_at_most_the_last_second_and_recover_gets_the_rest(tmp_path, free_port, connect_when_ready):
    ep = f"tcp/127.0.0.1:{free_port}"
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([*QRADAR, "record", "-o", str(path), "--listen", ep],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    session = None
    try:
        session = connect_when_ready(ep, timeout_s=30)
        wait_until(lambda: any(r.ok is not None for r in session.liveliness().get("radar/alive/record/**",
                                                                                  timeout=1.0)), 20, "recorder alive")
        sent_at = []
        pub = session.declare_publisher("radar/k1/raw")
        for i in range(40):
            pub.put(encode_raw(RawFrameMsg("k1", i, i, CONFIG_256, np.zeros((256, 2), np.complex64))))
            sent_at.append(time.monotonic())
            time.sleep(0.05)
        time.sleep(1.6)  # more than one flush period after the last message
        kill_at = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if session is not None:
            session.close()
        if proc.poll() is None:
            proc.kill()
    f = McapFile(path)
    seqs = [m.sequence for ch, m in f.messages() if ch.topic == "radar/k1/raw"]
    flushed_before = [i for i, t in enumerate(sent_at) if kill_at - t > 1.5]
    assert set(flushed_before) <= set(seqs)  # the player's reader gets everything flushed
    out = tmp_path / "recovered.mcap"
    r = subprocess.run([*QRADAR, "recover", str(path), "-o", str(out)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    g = McapFile(out)
    assert [m.sequence for ch, m in g.messages() if ch.topic == "radar/k1/raw"] == seqs
    assert not g.truncated and "qradar.versions" in g.metadata_dict()
    with open(out, "rb") as fh:  # complete and indexed: the seeking reader uses the summary
        summary = make_reader(fh).get_summary()
        assert summary is not None and summary.statistics.message_count >= len(seqs)


def test_truncated_file_plays_up_to_its_last_complete_chunk(tmp_path, bus, zenoh_session):
    data = CHAMBER.read_bytes()
    cut_at = int(len(data) * 0.6)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:cut_at])
    # what "its last complete chunk" means, from the complete file's own chunk index
    with open(CHAMBER, "rb") as fh:
        index = sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda ci: ci.chunk_start_offset)
    with open(CHAMBER, "rb") as fh:
        chunks = [r for r in StreamReader(fh, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) == len(index)
    complete = sum(ci.chunk_start_offset + ci.chunk_length <= cut_at for ci in index)
    assert 0 < complete < len(index)  # the cut falls inside a later chunk
    in_complete_chunks = sum(isinstance(r, Message) for c in chunks[:complete] for r in breakup_chunk(c))

    full = list(McapFile(CHAMBER).messages())
    f = McapFile(cut)
    got = list(f.messages())
    assert f.truncated and f.truncation_reason
    # every message of the complete chunks, none of the cut one, in the file's order
    assert len(got) == in_complete_chunks < len(full)
    assert [(ch.topic, m.log_time, m.data) for ch, m in got] == \
        [(ch.topic, m.log_time, m.data) for ch, m in full[:in_complete_chunks]]

    # the player publishes exactly those (its qradar channels: not the pointclouds) and says it was cut
    want = [(ch.topic, m.data) for ch, m in got if ch.topic.rsplit("/", 1)[-1] in ("raw", "quantized", "targets",
                                                                                   "health")]
    col = Collector(zenoh_session, "cutplay/**")
    r = play(cut, bus, PlayConfig(fast=True, prefix="cutplay"), session=zenoh_session)
    assert r.truncated and r.published == len(want) > 0
    wait_until(lambda: len(col.items) >= len(want), 10, "the cut file's messages")
    assert per_topic((k.replace("cutplay/", "radar/", 1), p) for k, p in col.items) == per_topic(want)
    col.sub.undeclare()


def test_bad_files_give_clear_errors(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not mcap at all")
    with pytest.raises(NotMcapError, match="is not an MCAP file"):
        McapFile(junk).scan()
    other = tmp_path / "other.mcap"
    with open(other, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("foo", "jsonschema", b"{}")
        cid = w.register_channel("/camera/image", "json", sid)
        w.add_message(cid, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    with pytest.raises(NoQradarChannelsError, match="no qradar channels.*camera/image"):
        play(other, BusConfig(), PlayConfig(fast=True))
    with pytest.raises(NoQradarChannelsError, match="no raw frames"):
        load_raw(other)
    with pytest.raises(ReplayError, match="cannot open"):
        McapFile(tmp_path / "missing.mcap").scan()
    proc = subprocess.run([*QRADAR, "replay", str(junk), "--fast"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "is not an MCAP file" in proc.stderr
    for bad in ("2:1", "0:1:0", "-0.5", "a,b"):
        with pytest.raises(ReplayError, match="--alpha"):
            parse_alphas(bad)


def test_a_replay_that_selects_nothing_says_why_and_fails(tmp_path, bus, zenoh_session):
    """``--topics`` matching none of a recording's channels, or a window past its end: one line
    naming them and status 2, not "published 0" with status 0 (with ``--loop``, a loop over
    nothing until Ctrl-C); so does a recording of no message."""
    with pytest.raises(ReplayError, match=r"--topics 'radar/\*\*/nothing' matches none of the channels of "
                                          r".*chamber\.mcap: radar/kmd2-0/health, radar/kmd2-0/quantized"):
        play(CHAMBER, bus, PlayConfig(fast=True, topics="radar/**/nothing"), session=zenoh_session)
    with pytest.raises(ReplayError, match=r"chamber\.mcap has no message within --start 9999 \(s from its first"):
        play(CHAMBER, bus, PlayConfig(fast=True, loop=True, start_s=9999), session=zenoh_session)
    with pytest.raises(ReplayError, match=r"no message of --topics 'radar/\*/health' within --start 1 --end 1\.01"):
        play(CHAMBER, bus, PlayConfig(fast=True, topics="radar/*/health", start_s=1, end_s=1.01), session=zenoh_session)
    assert play(CHAMBER, bus, PlayConfig(fast=True, topics="radar/*/targets", end_s=0.5),
                session=zenoh_session).published > 0
    empty = tmp_path / "empty.mcap"  # a recording stopped before its first message
    with open(empty, "wb") as fh:
        w = Writer(fh)
        w.start()
        w.register_channel("radar/s0/health", "json", w.register_schema("qradar.health", "jsonschema", b"{}"))
        w.finish()
    with pytest.raises(ReplayError, match=r"empty\.mcap holds no message on its qradar channels \(radar/s0/health\)$"):
        play(empty, bus, PlayConfig(fast=True), session=zenoh_session)
    proc = subprocess.run([*QRADAR, "replay", str(CHAMBER), "--fast", "--topics", "radar/*/tracks"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stdout == "", proc
    assert proc.stderr.strip().splitlines() == [
        f"qradar replay: error: --topics 'radar/*/tracks' matches none of the channels of {CHAMBER}: "
        "radar/kmd2-0/health, radar/kmd2-0/quantized, radar/kmd2-0/raw, radar/kmd2-0/targets"]


def test_committed_recording_and_foxglove_channel():
    assert CHAMBER.stat().st_size <= 5 * 1024 * 1024
    f = McapFile(CHAMBER)
    msgs = list(f.messages())
    by_topic = per_topic((ch.topic, m) for ch, m in msgs)
    assert len(by_topic["radar/kmd2-0/raw"]) == 106
    assert {"radar/kmd2-0/quantized", "radar/kmd2-0/targets", "radar/kmd2-0/pointcloud"} <= set(by_topic)
    md = f.metadata_dict()
    assert {"qradar.radar", "qradar.quantizer", "qradar.scene", "qradar.versions"} <= set(md)
    ch = next(c for c in f.channels.values() if c.topic.endswith("/pointcloud"))
    schema = f.schemas[ch.schema_id]
    assert schema.name == "foxglove.PointCloud" and schema.encoding == "jsonschema"
    js = json.loads(schema.data)
    assert {"timestamp", "frame_id", "pose", "point_stride", "fields", "data"} <= set(js["properties"])
    pc = json.loads(by_topic["radar/kmd2-0/pointcloud"][0].data)
    assert [fl["name"] for fl in pc["fields"]] == ["x", "y", "amplitude"] and pc["point_stride"] == 12
    assert len(base64.b64decode(pc["data"])) == 12 * 2  # two targets, three float32 each


def test_old_recording_decodes_with_its_seedseq_dither():
    """chamber.mcap predates the counter generator: its quantized frames are format version
    1, decode as generator "seedseq", and re-quantizing its raw frames with that generator
    and the recording's quantizer (metadata) and per-sensor seed reproduces every code; the
    frames' own dither regenerates them too, in one batch and frame by frame."""
    f = McapFile(CHAMBER)
    payloads = per_topic((ch.topic, m.data) for ch, m in f.messages())
    quant = payloads["radar/kmd2-0/quantized"]
    assert {p[4] for p in quant} == {1}
    groups, errors = decode_quantized_batch(quant, ["radar/kmd2-0/quantized"] * len(quant))
    assert not errors and len(groups) == 1
    q = groups[0]
    assert set(np.atleast_1d(q.frames.generator).tolist()) == {DITHER_SEEDSEQ}  # one name for the group, or one a frame
    raws = {m.seq: m for m in map(decode_raw, payloads["radar/kmd2-0/raw"])}
    seqs = q.headers.seq
    assert len(seqs) == 106 and set(seqs.tolist()) == set(raws)
    frames = np.stack([raws[s].data for s in seqs.tolist()]).astype(complex)
    md = f.metadata_dict()["qradar.quantizer"]
    cfg = QuantizerConfig(bits=int(md["bits"]), alpha=float(md["alpha"]))
    seed = sensor_dither_seed(int(md["dither_seed"]), "kmd2-0")
    assert set(q.frames.dither_seed.tolist()) == {seed}
    again = quantize_frames(frames, cfg, seqs, dither_seed=seed, generator=DITHER_SEEDSEQ)
    np.testing.assert_array_equal(again.codes, q.frames.codes)
    np.testing.assert_array_equal(again.delta, q.frames.delta)
    np.testing.assert_array_equal(quantize(frames, q.frames.delta, q.frames.bits, q.frames.dither()), q.frames.codes)
    one = decode_quantized(quant[0])
    assert one.generator == DITHER_SEEDSEQ
    np.testing.assert_array_equal(quantize(frames[:1], one.delta, 1, one.dither()[None]), one.codes[None])
    # the counter generator draws another dither: new output is not the recording's
    new = quantize_frames(frames, cfg, seqs, dither_seed=seed)
    assert new.generator == DITHER_COUNTER and np.mean(new.codes != q.frames.codes) > 0.1


def test_reprocess_is_deterministic_and_dither_helps_cml_on_the_off_grid_recording():
    rec = load_raw(CHAMBER)
    scene = truth_scene(rec, None)
    assert sorted(t["range_m"] for t in scene.truth()) == [4.87, 9.23]  # off the range grid
    radar = radar_for(rec, scene.radar)
    alphas = parse_alphas("0:1:0.05")
    assert alphas.size == 21 and alphas[-1] == 1.0
    a = sweep(rec, radar, scene, alphas, seed=3, bar=False, algo="pbp")
    b = sweep(rec, radar, scene, alphas, seed=3, bar=False, algo="pbp")
    c = sweep(rec, radar, scene, alphas, seed=4, bar=False, algo="pbp")
    assert a.summary() == b.summary()
    assert a.summary()["mean_error_all_m"] != c.summary()["mean_error_all_m"]
    # PBP: the strong reflector off the grid fills two range bins, which bury the weak one at every alpha
    assert min(a.mean_error_m[:, 0]) > 3.0
    s = sweep(rec, radar, scene, parse_alphas("0:1:0.1"), seed=3, bar=False, algo="cml").summary()
    assert s["error_at_best_m"] < 0.4 and s["error_at_best_m"] < a.summary()["error_at_best_m"] / 5
    assert s["error_at_alpha0_m"] > 1.3 * s["error_at_best_m"]  # dither helps ...
    assert 0 < s["best_alpha"] < 1  # ... but with sensor noise full dither is not the optimum (paper Fig. 5a)


def test_cli_reprocess_writes_plots_results_and_mcap(tmp_path):
    out = tmp_path / "rp"
    proc = subprocess.run([*QRADAR, "reprocess", str(CHAMBER), "--alpha", "0:1:0.25",
                           "--algos", "pbp", "cml", "--out", str(out), "--mcap", str(tmp_path / "re.mcap")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "reprocess [" in proc.stderr  # progress bar
    res = json.loads((out / "results.json").read_text())
    assert res["alphas"] == [0.0, 0.25, 0.5, 0.75, 1.0] and res["frames"] == 106
    assert res["algo"] == "pbp" and set(res["by_algo"]) == {"pbp", "cml"}  # one sweep, one curve, per decoder
    assert res["by_algo"]["cml"]["error_at_best_m"] < res["by_algo"]["pbp"]["error_at_best_m"]
    assert "cml   best alpha" in proc.stdout
    for png in ("alpha_sweep.png", "reconstructions.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"
    assert McapFile(tmp_path / "re.mcap").scan() == 2 * 106  # the best decoder's targets: cml, with statistics
    targets = [json.loads(m.data)["targets"] for ch, m in McapFile(tmp_path / "re.mcap").messages()
               if ch.topic.endswith("/targets")]
    assert len(targets) == 106 and all("statistic_db" in t for frame in targets for t in frame)
    truthless = subprocess.run([*QRADAR, "reprocess", str(tmp_path / "re.mcap")],
                               capture_output=True, text=True, timeout=60)
    assert truthless.returncode == 2 and "no raw frames" in truthless.stderr


def test_qradar_run_leaves_a_recording_that_replays(tmp_path):
    path = tmp_path / "run.mcap"
    proc = subprocess.run([*QRADAR, "run", *RUNTIME_DECODER, "--frames", "20", "--duration", "120", "--json",
                           "--record", str(path)], capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    s = json.loads(proc.stdout)
    assert s["recording"]["files"] == [str(path)] and s["recording"]["dropped"] == 0
    rp = subprocess.run([*QRADAR, "replay", str(path), "--fast", "--replay-prefix",
                         "replay"], capture_output=True, text=True, timeout=120)
    assert rp.returncode == 0, rp.stderr
    out = json.loads(rp.stdout.strip().splitlines()[-1])
    assert out["published"] >= 3 * s["frames_raw"] and not out["truncated"]


def test_a_recorder_that_records_nothing_says_so_and_fails(tmp_path):
    """A recorder on another prefix than the nodes' (or with no router in common) wrote a file
    of no message and ended with status 0: now one line says nothing came, and status 1 at the
    end of its --duration (stopped by a signal before anything came: the same line, a warning)."""
    path = tmp_path / "nothing.mcap"
    proc = qradar("record", "-o", path, "--prefix", "lab2", "--duration", "1", "--quiet")
    assert proc.returncode == 1 and proc.stderr.strip().splitlines()[-1] == (
        f"qradar record: error: nothing came on lab2/**: {path} holds no message (are the nodes up, on this "
        "--prefix, and joined to the same router as this recorder?)"), proc.stderr
    assert json.loads(proc.stdout)["frames_in"] == 0


def test_a_moving_target_is_scored_where_it_is_in_each_frame(tmp_path):
    """A recording of the walker (3 m at 1.5 m/s beside a static reflector), split in two files,
    re-processed: each frame is scored against where the walker is at its time since
    the sensor's first frame, as the live run scores it, a later file too (its recorder names
    that frame). It was scored against its place at the file's first frame: metres behind."""
    from replay.reprocess import clock_start_ns, truth_positions

    path = tmp_path / "walk.mcap"
    proc = subprocess.run([*QRADAR, "run", "--scene", "walker", "--frames", "60", "--duration", "120",
                           "--split-size", "0.2", "--record", str(path), "--json"], capture_output=True, text=True,
                          timeout=180, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stderr[-2000:]
    live = json.loads(proc.stdout)["score"]
    first, later = load_raw(path), load_raw(tmp_path / "walk_0001.mcap")
    assert clock_start_ns(first) == (first.timestamp_ns[0], False)  # the first file: its own first frame
    assert clock_start_ns(later) == (first.timestamp_ns[0], True)  # a later one: named by its recorder
    for rec in (first, later):
        scene = truth_scene(rec, None)
        ranges, angles = truth_positions(rec, scene)
        t_s = (rec.timestamp_ns - first.timestamp_ns[0]) / 1e9
        np.testing.assert_allclose(ranges[:, 0], 3.0 + 1.5 * t_s)  # the walker, frame by frame
        np.testing.assert_allclose(ranges[:, 1], 20.0)
        np.testing.assert_allclose(angles, [[-10.0, 35.0]] * len(t_s))
        res = sweep(rec, radar_for(rec, scene.radar), scene, np.array([0.45]), bar=False)
        walker = np.nanmedian(res.results[0].errors_m[:, 0])
        # as the live run scored it (its frames quantized alike); scored at the file's first frame it was metres
        assert walker < 0.3 and walker < 3 * live["targets"][0]["median_error_m"] + 0.05, (walker, live)
    assert (later.timestamp_ns[0] - first.timestamp_ns[0]) / 1e9 > 1.0  # the later file starts a second or more on
    # --K auto's detections too, and the labels at the file's first frame (the walker 1.5 m or more on)
    res = sweep(later, radar_for(later, scene.radar), scene, np.array([0.45]), bar=False, auto_k=True, k=4)
    summary = res.summary()
    assert res.truth[0]["range_m"] == pytest.approx(ranges[0, 0]) and ranges[0, 0] > 4.5
    assert min(v[0] for v in summary["detected"].values()) > 0.9, summary["detected"]
    assert summary["false_targets_per_frame"][0] < 0.1, summary
    out = qradar("reprocess", str(tmp_path / "walk_0001.mcap"), "--alpha", "0.45", "--out", str(tmp_path / "rp"),
                 "--quiet")
    assert out.returncode == 0 and "each frame is scored where they are at its time since the sensor's first " \
        "frame\n" in out.stderr, out.stderr
    # the web page's view of each file draws the truth on the same clock (it drew a later file's from its start)
    from qradar.web.node import WebView

    for rec, file in ((first, path), (later, tmp_path / "walk_0001.mcap")):
        view = WebView.of_recording(file)  # not started: no server, no player's thread, an in-memory transport
        assert set(view.player.truth_t0_ns) == {rec.sensor_id}
        t0 = view.player.truth_t0_ns[rec.sensor_id]
        assert t0 == (view.player.first_log_ns if rec is first else first.timestamp_ns[0])
        shown = view._truth_at(rec.sensor_id, int(rec.timestamp_ns[-1]))
        want = 3.0 + 1.5 * (rec.timestamp_ns[-1] - t0) / 1e9  # (the first file's clock: its first log time, a
        assert shown[0]["range_m"] == pytest.approx(want, abs=1e-6), (shown, want)  # frame's latency after)


@pytest.mark.parametrize("named, start", [
    ('{"s": 1000}', (1000, True)), ('{"other": 1000}', (5000, True)),  # a sensor it does not name began here
    ('{"s": 9000}', (5000, False)), ('{"s": -5}', (5000, False)), ('{"s": 1e30}', (5000, False)),
    ('{"s": Infinity}', (5000, False)), ('{"s": true}', (5000, False)), ('[1, 2]', (5000, False)),
    ("[" * 100000, (5000, False)), ("not json", (5000, False)), (None, (5000, False))])
def test_the_truth_clock_of_a_later_file_is_taken_only_when_it_is_a_time_before_its_frames(named, start):
    """``first_raw_ns`` of a crafted file: a time at or before the file's first frame, else the
    file's own first frame, never a traceback (the metadata's CRC guards against damage, not craft)."""
    from replay.reprocess import RawRecording, clock_start_ns

    recorder = {"part": "1"} if named is None else {"part": "1", "first_raw_ns": named}
    rec = RawRecording("s", np.zeros((2, 512, 2), complex), np.arange(2), np.array([5000, 55000]), 0,
                       {"qradar.recorder": recorder}, ["s"], False)
    assert clock_start_ns(rec) == start
