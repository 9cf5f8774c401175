"""The Python API (qradar.api, docs/api.md) on the committed recording and on a real
``qradar run --track`` recording: arrays, windows and topics read lazily by chunk (compared
with a whole read), damage in a window, tracks, tables and pandas, and the examples that
docs/api.md shows, run as a user runs them."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import qradar
from pipeline.errors import ParameterError
from pipeline.wire import RawFrameMsg, decode_raw, decode_targets, decode_tracks, encode_raw
from replay.errors import ReplayError
from replay.mcapio import McapSink
from replay.mcapread import McapFile
from zenoh_helpers import QRADAR

ROOT = Path(__file__).resolve().parents[1]
CHAMBER = ROOT / "recordings" / "chamber.mcap"


@pytest.fixture(scope="module")
def rec():
    return qradar.open_recording(CHAMBER)


def test_the_recording_as_arrays(rec):
    raw, quantized, targets = rec.raw(), rec.quantized(), rec.targets()
    assert rec.sensors == ["kmd2-0"] and not rec.truncated
    assert raw.data.shape == (len(raw), 512, 2) and raw.data.dtype == np.complex64
    assert (np.diff(raw.seq.astype(np.int64)) > 0).all()  # in sequence order
    assert len(quantized) == len(targets) == len(raw) == 106
    assert targets.range_m.shape == (106, 2) and (targets.count == 2).all() and targets.algo == "pbp"
    assert (targets.published_ns > targets.timestamp_ns).all()
    assert rec.radar.config_id() == raw.config_id == quantized.config_id
    assert len(rec.health()) > 0 and rec.unparsed == {}
    assert len(rec.scene().targets) == 2


def test_quantize_and_decode_reproduce_what_the_stream_published(rec):
    """The recording's raw frames quantized again give its quantized frames bit for bit
    (it was made with the older 'seedseq' dither), and PBP on them its targets exactly."""
    raw, quantized, targets = rec.raw(), rec.quantized(), rec.targets()
    again = qradar.quantize(raw, alpha=float(quantized.frames.alpha[0]), generator="seedseq")
    assert np.array_equal(again.codes, quantized.frames.codes)
    det = qradar.decode(quantized, rec.radar, k=2, algo="pbp")
    for name in ("range_m", "angle_deg", "x_m", "y_m"):  # the JSON carries 9 significant digits
        np.testing.assert_allclose(getattr(det, name), getattr(targets, name), rtol=2e-9, atol=0, err_msg=name)
    # the stream's own generator draws another dither: most codes, not all, agree
    assert not np.array_equal(qradar.quantize(raw, alpha=0.55).codes, quantized.frames.codes)


def test_errors_are_one_line(rec):
    with pytest.raises(ReplayError, match="no raw messages of sensor 'nope'"):
        rec.raw("nope")
    with pytest.raises(ParameterError):
        qradar.quantize(rec.raw(), alpha=2.0)
    with pytest.raises(ReplayError, match="not whole ramps"):
        qradar.decode(np.zeros((1, 300, 2), complex), rec.radar, k=1)
    with pytest.raises(ReplayError, match=r"^radar must be a RadarConfig .*, not NoneType$"):
        qradar.decode(rec.raw().data, None, k=1)  # (was numpy's AttributeError)
    with pytest.raises(ParameterError, match=r"of the same B; got \(2, 1\), \(2, 1\), \(3, 2\), \(3, 2\)$"):
        qradar.position_error_m(np.ones((2, 1)), np.zeros((2, 1)), np.ones((3, 2)), np.zeros((3, 2)))
    with pytest.raises(AttributeError):
        qradar.not_a_name  # noqa: B018


def test_version():
    out = subprocess.run([*QRADAR, "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == f"qradar {qradar.__version__}"
    assert re.fullmatch(r"\d+\.\d+\.\d+.*", qradar.__version__)


def run_example(name: str, *args: str) -> str:
    out = subprocess.run([sys.executable, str(ROOT / "examples" / name), *args], capture_output=True, text=True,
                         timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def figure(text: str, pattern: str) -> float:
    m = re.search(pattern, text)
    assert m, f"{pattern!r} not in:\n{text}"
    return float(m.group(1))


def test_example_recording_arrays():
    out = run_example("recording_arrays.py")
    assert "raw (106, 512, 2) complex64" in out and "targets (106, 2) by pbp" in out
    assert 0 < figure(out, r"median error ([\d.]+) m") < 10


def test_example_decode_again():
    out = run_example("decode_again.py", str(CHAMBER), "0.3")
    pbp = figure(out, r"alpha 0.30 pbp: median error ([\d.]+) m")
    cml = figure(out, r"alpha 0.30 cml: median error ([\d.]+) m")
    full = figure(out, r"unquantized cml: median error ([\d.]+) m")
    assert full < cml < 0.3 < pbp  # the chamber's reflectors are off the grid


@pytest.mark.slow
def test_example_montecarlo_sweep(tmp_path):
    out = run_example("montecarlo_sweep.py", str(tmp_path))
    pbp = figure(out, r"dither_m512: median position error ([\d.]+) m")
    cml = figure(out, r"dither_m512@cml: median position error ([\d.]+) m")
    assert cml < 0.2 < pbp
    assert {p.name for p in tmp_path.iterdir()} >= {"results.json", "alpha_sweep.png", "reconstructions.png"}


# -- reading lazily, by window and topic ---------------------------------------------------------
def recorded(path: Path) -> tuple[list[tuple[str, int, bytes]], int]:
    """Every message of a whole, checked read: (key, log time, data), and the first log time."""
    got = [(ch.topic, m.log_time, bytes(m.data)) for ch, m in McapFile(path).messages()]
    return got, min(t for _, t, _ in got)


def in_window(messages, t0: int, key: str, start, end) -> list[tuple[int, bytes]]:
    lo = -np.inf if start is None else t0 + round(start * 1e9)
    hi = np.inf if end is None else t0 + round(end * 1e9)
    return [(t, d) for k, t, d in messages if k == key and lo <= t < hi]


WINDOWS = [(None, None), (0.0, 1.0), (1.2, 2.7), (2.5, None), (None, 0.6), (4.9, 5.2), (5.3, 9.0), (6.0, 7.0)]


@pytest.mark.parametrize("start, end", WINDOWS)
def test_a_window_reads_exactly_its_messages_and_only_its_chunks(start, end, chunks_opened):
    """open_recording(start, end) returns exactly the messages a whole read logs in
    [start, end) s from the first message, in sequence order, and decompresses only the
    chunks whose log time range meets the window."""
    messages, t0 = recorded(CHAMBER)
    index = McapFile(CHAMBER).read_index().chunk_indexes
    chunks_opened.clear()
    rec = qradar.open_recording(CHAMBER, start=start, end=end)
    assert chunks_opened == [] and rec.start_ns == t0  # opening reads the summary and metadata only
    want_raw = in_window(messages, t0, "radar/kmd2-0/raw", start, end)
    want_targets = in_window(messages, t0, "radar/kmd2-0/targets", start, end)
    if not want_raw:
        with pytest.raises(ReplayError, match="no raw messages of sensor 'kmd2-0' in the window"):
            rec.raw()
        return
    raw, targets, health = rec.raw(), rec.targets(), rec.health()
    expected = sorted((decode_raw(d) for _, d in want_raw), key=lambda m: m.seq)
    assert raw.seq.tolist() == [m.seq for m in expected]
    assert np.array_equal(raw.data, np.stack([m.data for m in expected]))
    assert targets.seq.tolist() == sorted(decode_targets(d).seq for _, d in want_targets)
    assert len(health) == len(in_window(messages, t0, "radar/kmd2-0/health", start, end))
    lo, hi = (start or 0.0), (np.inf if end is None else end)
    assert ((raw.t_s >= lo) & (raw.t_s < hi)).all() and ((targets.t_s >= lo) & (targets.t_s < hi)).all()
    assert np.allclose(np.sort(raw.t_s), sorted((t - t0) / 1e9 for t, _ in want_raw))
    # only the chunks that meet the window, each once per topic read (raw, targets, health)
    lo_ns = None if start is None else t0 + round(start * 1e9)
    hi_ns = None if end is None else t0 + round(end * 1e9)
    meet = [c for c in index if (hi_ns is None or c.message_start_time < hi_ns)
            and (lo_ns is None or c.message_end_time >= lo_ns)]
    assert sorted(chunks_opened) == sorted(c.chunk_length - 9 for c in meet for _ in range(3))  # 9: record head
    assert rec.damaged == [] and rec.lost == {} and rec.unparsed == {}


def test_a_sensor_is_read_from_the_chunks_that_hold_its_channel(tmp_path, chunks_opened):
    """Two sensors recorded one after the other (a chunk a second): a's frames are read from
    a's chunks only, b's from b's, and each equals what was written."""
    radar = qradar.RadarConfig()
    rng = np.random.default_rng(1)
    sink = McapSink(tmp_path / "two.mcap")
    written = {}
    for second, sensor in enumerate(["a", "a", "a", "b", "b"]):
        for i in range(4):
            seq, t = second * 4 + i, 10**18 + second * 10**9 + i * 10**8
            data = (rng.standard_normal((512, 2)) + 1j * rng.standard_normal((512, 2))).astype(np.complex64) * 0.1
            sink.write(f"radar/{sensor}/raw", encode_raw(RawFrameMsg(sensor, seq, t, radar.config_id(), data)),
                       t, t, seq)
            written.setdefault(sensor, []).append(data)
        sink.flush()
    sink.close()
    chunks_opened.clear()
    rec = qradar.open_recording(tmp_path / "two.mcap")
    assert rec.sensors == ["a", "b"] and rec.raw().sensor_id == "a" and len(chunks_opened) == 3
    b = rec.raw("b")
    assert len(chunks_opened) == 5 and np.array_equal(b.data, np.stack(written["b"]))
    assert np.allclose(b.t_s, [3, 3.1, 3.2, 3.3, 4, 4.1, 4.2, 4.3])
    window = qradar.open_recording(tmp_path / "two.mcap", start=2.5, end=3.15).raw("b")
    assert window.seq.tolist() == [12, 13] and len(chunks_opened) == 6


def test_topics_select_what_is_read():
    rec = qradar.open_recording(CHAMBER, topics="targets", start=1.0, end=2.0)
    assert rec.sensors == ["kmd2-0"] and rec.topics == ("targets",)
    assert len(rec.targets()) == 20
    with pytest.raises(ReplayError, match=r"opened with topics=\['targets'\]: open it again with 'raw'"):
        rec.raw()
    with pytest.raises(ReplayError, match="topics="):
        qradar.open_recording(CHAMBER, topics=("raw", "frames"))
    with pytest.raises(ReplayError, match="end=1 s must come after start=2 s"):
        qradar.open_recording(CHAMBER, start=2, end=1)
    with pytest.raises(ReplayError, match="start='x' must be seconds"):
        qradar.open_recording(CHAMBER, start="x")


def test_a_window_touching_a_damaged_chunk_reports_it_and_no_other(tmp_path):
    """One bit flipped in the third chunk: a window across it returns every other frame of
    the window, equal to the original's, names the chunk and counts the window's messages of
    it lost; a window beside it reads whole and reports nothing."""
    index = sorted(McapFile(CHAMBER).read_index().chunk_indexes, key=lambda c: c.chunk_start_offset)
    ci = index[2]
    data = bytearray(CHAMBER.read_bytes())
    data[ci.chunk_start_offset + ci.chunk_length // 2] ^= 8
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)
    messages, t0 = recorded(CHAMBER)
    start, end = (ci.message_start_time - t0) / 1e9 - 0.5, (ci.message_start_time - t0) / 1e9 + 0.5
    clean = qradar.open_recording(CHAMBER, start=start, end=end).raw()
    rec = qradar.open_recording(bad, start=start, end=end)
    raw = rec.raw()
    in_chunk = [t for t, _ in in_window(messages, t0, "radar/kmd2-0/raw", start, end)
                if ci.message_start_time <= t <= ci.message_end_time]
    assert 0 < len(in_chunk) and len(raw) == len(clean) - len(in_chunk)
    keep = np.isin(clean.seq, raw.seq)
    assert np.array_equal(clean.data[keep], raw.data)
    assert len(rec.damaged) == 1 and f"chunk at byte {ci.chunk_start_offset}" in rec.damaged[0]
    assert rec.lost["radar/kmd2-0/raw"] == len(in_chunk)
    # the chunk is lost whole: the window's messages of every topic in it count
    every = [k for k, t, _ in messages if ci.message_start_time <= t < t0 + round(end * 1e9)]
    assert sum(rec.lost.values()) == len(every)
    rec.targets()  # the same chunk again: named and counted once
    assert len(rec.damaged) == 1 and sum(rec.lost.values()) == len(every)
    beside = qradar.open_recording(bad, start=0.0, end=(index[1].message_end_time - t0) / 1e9)
    assert len(beside.raw()) > 0 and beside.damaged == [] and beside.lost == {}


def test_a_cut_short_recording_is_read_at_open_and_windowed_the_same(tmp_path):
    data = CHAMBER.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])
    messages, t0 = recorded(cut)
    rec = qradar.open_recording(cut, topics=("raw",), start=1.0, end=2.5)
    assert rec.truncated and rec.start_ns == t0
    want = in_window(messages, t0, "radar/kmd2-0/raw", 1.0, 2.5)
    assert len(want) > 0 and len(rec.raw()) == len(want)


def fullest(files: list[Path]) -> Path:
    """The file of a split set with the most confirmed tracks (the tracker needs a few frames)."""
    return max(files, key=lambda path: sum(len(decode_tracks(bytes(m.data)).tracks) for ch, m in
                                           McapFile(path).messages() if ch.topic.endswith("/tracks")))


def test_tracks_of_a_track_recording(track_recording):
    path = fullest(track_recording)
    msgs = [decode_tracks(bytes(m.data)) for ch, m in McapFile(path).messages() if ch.topic.endswith("/tracks")]
    tracks = qradar.open_recording(path).tracks()
    assert len(tracks) == len(msgs) > 0 and tracks.sensor_id == "kmd2-0"
    assert tracks.count.tolist() == [len(m.tracks) for m in sorted(msgs, key=lambda m: m.seq)]
    rows = [t for m in sorted(msgs, key=lambda m: m.seq) for t in m.tracks]
    assert len(tracks.track_id) == len(rows) > 0 and tracks.track_id.dtype == np.int64
    assert tracks.track_id.tolist() == [t["track_id"] for t in rows]
    np.testing.assert_array_equal(tracks.range_m, [t["range_m"] for t in rows])
    assert tracks.static.dtype == bool and (np.diff(tracks.frame) >= 0).all()
    assert (tracks.t_s >= 0).all() and (np.diff(tracks.seq.astype(np.int64)) > 0).all()
    with pytest.raises(ReplayError, match="holds no tracks messages"):
        qradar.open_recording(CHAMBER).tracks()


def test_tables_have_one_row_per_target_track_frame_or_health_message(track_recording):
    rec = qradar.open_recording(fullest(track_recording))
    targets = rec.targets()
    table = rec.table("targets")
    assert len(table["seq"]) == int(targets.count.sum()) and (np.diff(table["t_s"]) >= 0).all()
    assert set(table) >= {"sensor_id", "seq", "timestamp_ns", "t_s", "published_ns", "algo", "target", "range_m",
                          "angle_deg", "x_m", "y_m", "amplitude"}
    assert len({len(v) for v in table.values()}) == 1
    strongest = table["target"] == 0
    np.testing.assert_array_equal(table["range_m"][strongest], targets.range_m[:, 0])
    assert len(rec.table("tracks")["track_id"]) == len(rec.tracks().track_id)
    assert len(rec.table("raw")["seq"]) == len(rec.raw()) and set(rec.table("quantized")) >= {"alpha", "delta"}
    health = rec.table("health")
    assert len(health["node"]) == len(rec.health()) and "latency_p50_ms" in health
    with pytest.raises(ReplayError, match="no table of 'pointcloud'"):
        rec.table("pointcloud")


def test_to_pandas_is_the_table(track_recording):
    if os.environ.get("QRADAR_REQUIRE_PANDAS") != "1":
        pytest.importorskip("pandas", reason="pandas is an optional extra: pip install -e '.[pandas]'")
    rec = qradar.open_recording(fullest(track_recording), start=0.2, end=60)
    frame = rec.to_pandas("targets")
    table = rec.table("targets")
    assert list(frame.columns) == list(table) and len(frame) == len(table["seq"]) > 0
    np.testing.assert_array_equal(frame["range_m"].to_numpy(), table["range_m"])
    assert frame["t_s"].between(0.2, 60, inclusive="left").all()
    tracks = rec.to_pandas("tracks")
    assert tracks.groupby("track_id")["seq"].count().sum() == len(tracks)


def test_to_pandas_without_pandas_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "pandas", None)  # what an environment without pandas gives
    with pytest.raises(ReplayError, match=r"pip install -e '\.\[pandas\]'"):
        qradar.open_recording(CHAMBER).to_pandas()


def test_info_is_what_the_command_prints():
    info = qradar.open_recording(CHAMBER).info()
    out = subprocess.run([*QRADAR, "info", "--json", str(CHAMBER)], capture_output=True,
                         text=True, timeout=60)
    printed = json.loads(out.stdout)
    info.pop("seconds_to_describe"), printed.pop("seconds_to_describe")
    assert info == printed and info["messages"] == 447


def test_example_recording_window(track_recording):
    out = run_example("recording_window.py", str(CHAMBER), "1", "3")
    assert "window 1-3 s: raw (41, 512, 2)" in out and "tracks: none recorded" in out
    assert 8.0 < figure(out, r"strongest target median range ([\d.]+) m") < 10.0
    out = run_example("recording_window.py", str(fullest(track_recording)), "0", "60")
    assert re.search(r"tracks: \d+ messages, \d+ rows, track ids \[\d", out), out
