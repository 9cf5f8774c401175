"""``qradar info`` (replay.mcapinfo) on real recordings: a ``qradar run --track --record``
split into files, the committed chamber recording, one cut short, one recovered, one
damaged; each described against what a whole, checked read of the file finds. It reads the
summary and metadata only (no chunk) when the file has a summary; ``qradar inspect`` sends
an MCAP file here."""

import json
from collections import Counter
from datetime import datetime
from pathlib import Path

import pytest

from radar_driver.model import RadarConfig
from replay.mcapinfo import describe, format_info
from replay.mcapio import recover
from replay.mcapread import McapFile
from zenoh_helpers import qradar

ROOT = Path(__file__).resolve().parents[1]
CHAMBER = ROOT / "recordings" / "chamber.mcap"


def whole_read(path: Path) -> tuple[Counter, int, int, McapFile]:
    """Messages by topic, first and last log time, of a whole read with every CRC checked."""
    f = McapFile(path)
    counts, times = Counter(), []
    for ch, msg in f.messages():
        counts[ch.topic] += 1
        times.append(msg.log_time)
    return counts, min(times), max(times), f


def topics_of(info: dict) -> dict[str, int]:
    return {t["topic"]: t["messages"] for t in info["topics"]}


def flipped_in_chunk(src: Path, dst: Path, chunk: int) -> tuple[Path, object]:
    """A copy of ``src`` with one bit flipped inside its chunk number ``chunk`` (file order)."""
    f = McapFile(src)
    ci = sorted(f.read_index().chunk_indexes, key=lambda c: c.chunk_start_offset)[chunk]
    data = bytearray(src.read_bytes())
    data[ci.chunk_start_offset + ci.chunk_length // 2] ^= 8
    dst.write_bytes(data)
    return dst, ci


def test_a_run_recording_and_its_split_set(track_recording):
    """`qradar info --json` of every file of a `qradar run --track` split set: counts, rates and
    times are a whole read's; the run's configuration and the recorder's counters are there;
    each file names the set."""
    out = qradar("info", "--json", *track_recording)
    assert out.returncode == 0, out.stderr
    infos = [json.loads(line) for line in out.stdout.splitlines()]
    assert [i["file"] for i in infos] == [str(p) for p in track_recording]
    for part, (path, info) in enumerate(zip(track_recording, infos)):
        counts, first, last, _ = whole_read(path)
        assert info["index"] == "summary" and not info["truncated"] and info["chunks"] >= 1
        assert topics_of(info) == dict(counts) and info["messages"] == sum(counts.values())
        assert info["start_ns"] == first and info["end_ns"] == last
        assert info["duration_s"] == pytest.approx((last - first) / 1e9, abs=1e-3)
        assert datetime.fromisoformat(info["start"]["utc"].replace("Z", "+00:00")).timestamp() == \
            pytest.approx(first / 1e9, abs=1e-3)
        assert datetime.fromisoformat(info["end"]["local"]).timestamp() == pytest.approx(last / 1e9, abs=1e-3)
        for t in info["topics"]:
            # a part of the set can hold one instant (the last, on a loaded host): no rate, not a division by 0
            rate = None if last == first else pytest.approx(t["messages"] * 1e9 / (last - first), rel=1e-3)
            assert t["sensor"] == "kmd2-0" and t["rate_hz"] == rate
        # a part of the set may hold no sensor's data (its last instant: the run's own messages or the sensor's
        # health alone, on a loaded host); a sensor is one whose data is there (health is the nodes', too)
        assert info["sensors"] == (["kmd2-0"] if any(topic.startswith("radar/kmd2-0/") and
                                                     not topic.endswith("/health") for topic in counts) else [])
        assert info["radar"]["config_id"] == RadarConfig().config_id()
        assert info["quantizer"]["alpha"] == 0.55 and info["quantizer"]["bits"] == 1
        assert info["decoder"]["algo"] == "pbp" and info["decoder"]["K"] == 2
        cal = info["calibration"]
        assert cal["file"].endswith("chamber-cal.json") and [e["sensor_id"] for e in cal["entries"]] == ["kmd2-0"]
        assert info["truth"]["simulated"] is True
        assert [t["range_m"] for t in info["truth"]["targets"]] == [4.87, 9.23]
        assert info["recorder"]["part"] == part and info["split"] == [str(p) for p in track_recording]
        rec = info["losses"]["recorder"]
        assert rec["lost"] == 0 and rec["verify_errors"] == 0 and rec["refused_shape"] == 0
        assert info["recovered"] is None and info["losses"]["damage"] == []
    kinds = {t["kind"] for i in infos for t in i["topics"]}
    assert kinds == {"raw", "quantized", "targets", "tracks", "pointcloud", "scene", "profile", "health"}
    # the last file ends the run: its counters count every message of the set
    assert sum(i["messages"] for i in infos) >= infos[-1]["losses"]["recorder"]["written"] > 0
    text = qradar("info", track_recording[0])
    assert text.returncode == 0
    for words in ("radar/kmd2-0/tracks", "Hz", "quantizer", "alpha 0.55", "decoder", "algo pbp", "recovered     no",
                  "chamber-cal.json (entries for kmd2-0)",
                  f"split         {len(track_recording)} files", "refused_shape 0", "(local "):
        assert words in text.stdout, words


def test_the_committed_recording_is_described_without_reading_a_chunk(chunks_opened):
    info = describe(CHAMBER)
    assert chunks_opened == []  # the summary and metadata only
    assert info["messages"] == 447 and topics_of(info)["radar/kmd2-0/raw"] == 106 and info["chunks"] == 6
    assert info["duration_s"] == pytest.approx(5.453, abs=1e-3) and info["split"] == [str(CHAMBER)]
    assert info["losses"]["chunks_checked"] is False and info["losses"]["recorder"]["written"] == 341
    text = format_info(info)
    assert "chunks not checked: --check reads them" in text and "M = 512" in text
    assert "chamber (simulated scene): 4.87 m -20.0 deg, 9.23 m +15.0 deg" in text
    # --check reads every chunk, each once
    checked = describe(CHAMBER, check=True)
    assert len(chunks_opened) == 6 and checked["losses"]["messages_read"] == 447 and checked["losses"]["lost"] == 0


def test_a_cut_short_recording_is_read_whole_and_says_so(tmp_path):
    ci = sorted(McapFile(CHAMBER).read_index().chunk_indexes, key=lambda c: c.chunk_start_offset)[4]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(CHAMBER.read_bytes()[:ci.chunk_start_offset + ci.chunk_length // 2])  # killed mid-chunk
    counts, first, last, f = whole_read(cut)
    assert f.truncated and 0 < sum(counts.values()) < 447
    info = describe(cut)
    assert info["index"] == "read whole" and info["truncated"] and "cut short" in info["truncation_reason"]
    assert topics_of(info) == dict(counts) and (info["start_ns"], info["end_ns"]) == (first, last)
    assert info["losses"]["recorder"] is None and info["losses"]["chunks_checked"] and info["losses"]["lost"] == 0
    assert info["radar"]["config_id"] == RadarConfig().config_id()  # its metadata come first
    out = qradar("info", cut)
    assert out.returncode == 0 and "CUT SHORT" in out.stdout and "qradar recover" in out.stdout
    assert "no counters (the recorder did not close this file" in out.stdout


def test_a_recovered_recording_says_what_its_source_lost(tmp_path):
    bad, ci = flipped_in_chunk(CHAMBER, tmp_path / "bad.mcap", 2)
    fixed = tmp_path / "fixed.mcap"
    r = recover(bad, fixed)
    assert r["lost"] == 84
    info = describe(fixed)
    rc = info["recovered"]
    assert rc["source"] == str(bad) and rc["messages"] == 447 - 84 and rc["lost"] == 84
    assert rc["lost_by_topic"]["radar/kmd2-0/raw"] == 20 and rc["truncated"] is False
    assert len(rc["damage"]) == 1 and f"chunk at byte {ci.chunk_start_offset}" in rc["damage"][0]
    assert info["messages"] == 447 - 84 and topics_of(info)["radar/kmd2-0/raw"] == 86
    out = qradar("info", fixed)
    assert f"recovered     from {bad}: 363 messages kept, 84 lost" in out.stdout


def test_a_damaged_recording_names_its_chunk_with_check(tmp_path):
    bad, ci = flipped_in_chunk(CHAMBER, tmp_path / "bad.mcap", 2)
    quick = describe(bad)  # the summary is whole: what the file was written with
    assert quick["messages"] == 447 and quick["losses"]["chunks_checked"] is False
    info = describe(bad, check=True)
    losses = info["losses"]
    assert info["messages"] == 447 and losses["messages_read"] == 363 and losses["lost"] == 84
    assert losses["lost_by_topic"]["radar/kmd2-0/raw"] == 20
    assert len(losses["damage"]) == 1 and f"chunk at byte {ci.chunk_start_offset}" in losses["damage"][0]
    out = qradar("info", "--check", bad, CHAMBER)  # as record --verify: status 1, the damaged file named
    assert out.returncode == 1 and "363 messages read, 84 lost" in out.stdout and "CRC mismatch" in out.stdout
    assert out.stderr == (f"qradar info --check: not intact: {bad} (84 messages lost); qradar recover writes what "
                          "reads back\n")
    assert qradar("info", "--check", CHAMBER).returncode == 0 and qradar("info", bad).returncode == 0
    # a damaged summary: the file is read whole instead, and says why
    data = bytearray(CHAMBER.read_bytes())
    data[-40] ^= 1  # inside the summary section, before the footer
    (tmp_path / "summary.mcap").write_bytes(data)
    info = describe(tmp_path / "summary.mcap")
    assert info["index"] == "read whole" and info["messages"] == 447
    assert any("summary" in line for line in info["losses"]["damage"])


def test_inspect_sends_an_mcap_file_to_info_and_info_refuses_what_is_not_mcap(tmp_path):
    out = qradar("inspect", CHAMBER)
    assert out.returncode == 2
    (line,) = out.stderr.strip().splitlines()
    assert "is an MCAP recording" in line and f"qradar info {CHAMBER}" in line
    (tmp_path / "x.bin").write_bytes(b"not a recording at all")
    out = qradar("info", tmp_path / "x.bin")
    assert out.returncode == 2
    (line,) = out.stderr.strip().splitlines()
    assert "is not an MCAP file" in line


def test_reprocess_of_a_calibrated_run_names_its_calibration(track_recording, tmp_path):
    """A recording of a calibrated run keeps the front end in its raw frames: reprocess without
    --calibration names the run's file (it told the user to calibrate again, as for a sensor
    never calibrated); with it, no warning."""
    cal = str(Path(__file__).resolve().parents[1] / "recordings" / "chamber-cal.json")
    for extra, warned in (((), True), (("--calibration", cal), False)):
        out = qradar("reprocess", track_recording[0], "--algos", "pbp", "--alpha", "0.5", "--quiet",
                     "--out", tmp_path / f"rp{len(extra)}", *extra)
        assert out.returncode == 0, out.stderr[-2000:]
        said = out.stdout + out.stderr
        assert (f"was recorded by a run calibrated with {cal}, and its raw frames keep the front end: give "
                f"--calibration {cal}" in said) == warned, said
        assert "uncalibrated" not in said, said
        # the first file of a split set, read alone: said
        assert (f"note: {track_recording[0]} is file 1 of the {len(track_recording)} of a split recording (run.mcap, "
                "run_0001.mcap") in said and "reprocess reads this file alone" in said, said
