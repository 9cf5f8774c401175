"""The recorder on a full disk and other write errors: real files on a real tmpfs (mounted
in a private mount namespace this test creates), RLIMIT_FSIZE, a removed folder; the
recorder closes its file readable, says so in health, counts what it loses, and the
pipeline runs on. Every wait is bounded."""

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from pipeline.wire import RawFrameMsg, encode_raw
from radar_driver.model import RadarConfig
from replay.mcapio import McapFile, recover
from replay.recorder import RecorderNode, RecordingState
from zenoh_helpers import QRADAR, RUNTIME_DECODER, Collector, read_lines, wait_until

ROOT = Path(__file__).resolve().parents[1]
CHUNK = 64 * 1024


@contextlib.contextmanager
def private_tmpfs(where: Path, size_bytes: int):
    """A tmpfs of ``size_bytes`` mounted on ``where`` in a private mount namespace held by a
    sleeping process; yields the path through which this process reaches it
    (``/proc/<holder>/root/<where>``). The namespace, and the mount, end with the holder."""
    if shutil.which("unshare") is None:
        pytest.skip("unshare (util-linux) is not installed: cannot create a private mount namespace")
    where.mkdir(parents=True, exist_ok=True)
    holder = subprocess.Popen(
        ["unshare", "--mount", "--propagation", "private", "sh", "-c",
         f'mount -t tmpfs -o size={size_bytes} qradar-test "$0" && echo ready && exec sleep 600', str(where)],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = holder.stdout.readline()  # "ready", or EOF when the mount failed and sh exited
        if line.strip() != "ready":
            holder.wait(10)
            pytest.skip(f"cannot mount a tmpfs in a private mount namespace: {holder.stderr.read().strip()}")
        root = Path(f"/proc/{holder.pid}/root") / where.relative_to("/")
        st = os.statvfs(root)
        assert st.f_blocks * st.f_frsize == size_bytes  # the tmpfs, not the folder below it
        yield root
    finally:
        holder.kill()
        holder.wait(10)


def fill(root: Path, leave_bytes: int) -> Path:
    """A file that fills ``root``'s file system, then gives back ``leave_bytes``."""
    filler = root / "filler"
    zeros = b"\0" * CHUNK
    st = os.statvfs(root)
    with open(filler, "wb") as fh:
        for _ in range(st.f_blocks * st.f_frsize // CHUNK + 2):
            try:
                fh.write(zeros)
                fh.flush()
            except OSError:
                break
        else:
            pytest.fail(f"{root} did not fill up")
    with open(filler, "r+b") as fh:
        fh.truncate(max(0, filler.stat().st_size - leave_bytes))
    return filler


def raw_frame(sensor: str, seq: int) -> bytes:
    """A raw frame of 512 x 2 noise samples (8 240 bytes, nearly incompressible)."""
    rng = np.random.default_rng(seq)
    data = (rng.standard_normal((512, 2)) + 1j * rng.standard_normal((512, 2))).astype(np.complex64)
    return encode_raw(RawFrameMsg(sensor, seq, 1_000 + seq, RadarConfig().config_id(), data))


def raw_seqs(path) -> tuple[list[int], McapFile]:
    f = McapFile(path)
    return [m.sequence for ch, m in f.messages() if ch.topic.endswith("/raw")], f


def reader_count(path) -> int:
    """Messages the mcap package's own reader finds."""
    with open(path, "rb") as fh:
        return sum(1 for _ in make_reader(fh).iter_messages())


def recorder_health(col: Collector, state: str):
    for payload in col.of("/health"):
        obj = json.loads(payload)
        if obj.get("node") == "record" and obj["extra"]["recorder"]["state"] == state:
            return obj
    return None


def test_full_disk_pauses_the_recorder_and_it_resumes_into_a_new_file(tmp_path, bus, zenoh_session):
    with private_tmpfs(tmp_path / "disk", 4 << 20) as disk:
        filler = fill(disk, 512 << 10)
        path = disk / "rec.mcap"
        col = Collector(zenoh_session, "radar/dk/health")
        rec = RecorderNode(bus, path, topics="radar/dk/raw", session=zenoh_session, retry_s=0.2,
                           health_period_s=0.2).start()
        try:
            pub = zenoh_session.declare_publisher("radar/dk/raw")
            seq = 0
            for seq in range(400):  # 8 KB frames at ~20 Hz: the disk is full after a few seconds
                if rec.state is not RecordingState.WRITING:
                    break
                pub.put(raw_frame("dk", seq))
                rec.wait(0.05)
            assert rec.state is RecordingState.PAUSED, "the disk never filled up"
            assert str(path) in rec.error and "No space left on device (ENOSPC)" in rec.error
            assert rec.errors == []  # nothing for run_nodes to raise: the node runs on
            wait_until(lambda: recorder_health(col, "paused") is not None, 10, "health saying paused")
            extra = recorder_health(col, "paused")["extra"]["recorder"]
            assert "ENOSPC" in extra["error"] and extra["files_written"] == 1 and extra["write_errors"] == 1

            # the first file: cut back to its last flushed chunk and ended with a footer
            seqs, f = raw_seqs(path)
            assert len(seqs) >= 1 and seqs == list(range(len(seqs))) and not f.truncated
            assert reader_count(path) == len(seqs)
            assert recover(path, tmp_path / "recovered.mcap")["messages"] == len(seqs)

            lost_before = rec.lost
            for i in range(10):  # while paused: counted as lost, by topic
                pub.put(raw_frame("dk", 1000 + i))
            wait_until(lambda: rec.lost_by_topic.get("raw", 0) >= lost_before + 10, 10, "lost frames counted")
            assert rec.state is RecordingState.PAUSED and len(rec.paths) == 1

            filler.unlink()  # space returns
            wait_until(lambda: rec.state is RecordingState.WRITING, 10, "the recorder to resume")
            assert rec.paths == [path, disk / "rec_0001.mcap"]
            for i in range(10):
                pub.put(raw_frame("dk", 2000 + i))
            wait_until(lambda: rec.written >= len(seqs) + 10, 10, "frames after the resume")
        finally:
            rec.stop()
            col.sub.undeclare()
        assert rec.errors == []
        seqs2, f2 = raw_seqs(disk / "rec_0001.mcap")
        assert seqs2 == list(range(2000, 2010)) and not f2.truncated and "qradar.versions" in f2.metadata_dict()
        assert reader_count(disk / "rec_0001.mcap") == 10
        # every message received is in a file, lost, or dropped by the queue: none unaccounted for
        t = rec.totals()
        assert rec.written == len(seqs) + len(seqs2)
        assert t["frames_in"] == seq + 20 and t["frames_in"] == rec.written + rec.lost + t["drops"]
        assert rec.summary()["state"] == "writing" and rec.summary()["files_written"] == 2


def test_a_removed_folder_pauses_the_recorder_until_it_can_write_again(tmp_path, bus, zenoh_session):
    folder = tmp_path / "gone"
    path = folder / "rec.mcap"
    rec = RecorderNode(bus, path, topics="radar/rm/raw", session=zenoh_session, retry_s=0.2,
                       health_period_s=60).start()
    try:
        pub = zenoh_session.declare_publisher("radar/rm/raw")
        for i in range(5):
            pub.put(raw_frame("rm", i))
        wait_until(lambda: rec.written == 5, 10, "the first frames")
        shutil.rmtree(folder)  # the open file now writes to nowhere; its next flush sees it
        for i in range(5, 400):
            if rec.state is not RecordingState.WRITING:
                break
            pub.put(raw_frame("rm", i))
            rec.wait(0.02)
        assert rec.error is not None and "removed" in rec.error and str(path) in rec.error
        wait_until(lambda: len(rec.paths) == 2 and rec.state is RecordingState.WRITING, 10, "a resume")
        for i in range(1000, 1005):
            pub.put(raw_frame("rm", i))
        wait_until(lambda: rec.written >= 5, 10, "frames in the new file")
    finally:
        rec.stop()
    assert rec.errors == [] and rec.paths[1] == folder / "rec_0001.mcap"
    seqs, f = raw_seqs(rec.paths[1])
    assert seqs[-5:] == list(range(1000, 1005)) and not f.truncated
    t = rec.totals()
    assert rec.written == len(seqs) and t["frames_in"] == rec.written + rec.lost + t["drops"] and rec.lost >= 5


#: live target lines (a line a second, ~20 frames) a run shows after the event a test waits
#: for, before its Ctrl-C: frames written after the event, not a fixed duration
LINES_AFTER = 2


def run_to_event(argv: list[str], event: str, on_line=None, timeout_s: float = 120.0) -> tuple[int, list[str], str]:
    """``qradar run`` (``argv``, its ``--json`` summary on stdout) until a stderr line holds
    ``event`` and :data:`LINES_AFTER` live target lines follow it, then Ctrl-C (as a user
    would; the run ends with its summary); ``on_line`` is called on each stderr line.
    Returns the exit status, the stderr lines and stdout. Every wait is bounded."""
    seen, after = threading.Event(), [0]

    def watch(line):
        if on_line is not None:
            on_line(line)
        if event in line:
            seen.set()
        elif seen.is_set() and " targets " in line:
            after[0] += 1
            if after[0] == LINES_AFTER:
                proc.send_signal(signal.SIGINT)

    proc = subprocess.Popen(argv, cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    lines, err_reader = read_lines(proc.stderr, watch)
    out, out_reader = read_lines(proc.stdout)
    try:
        proc.wait(timeout=timeout_s)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    err_reader.join(10)
    out_reader.join(10)
    assert seen.is_set(), f"no {event!r} in the run's lines: " + "".join(lines[-20:])
    return proc.returncode, lines, "".join(out)


@pytest.mark.slow
def test_qradar_run_goes_on_through_a_full_disk_and_records_again_when_space_returns(tmp_path):
    with private_tmpfs(tmp_path / "disk", 4 << 20) as disk:
        filler = fill(disk, 256 << 10)  # about 2.5 s of a run's traffic
        path = disk / "run.mcap"
        freed = threading.Event()

        def on_line(line):
            if "recording paused" in line and not freed.is_set():
                filler.unlink()
                freed.set()

        code, lines, out = run_to_event([*QRADAR, "run", *RUNTIME_DECODER, "--duration", "60", "--json", "--record",
                                      str(path), "--write-retry", "0.5"], "recording resumed", on_line)
        assert code == 0, "".join(lines[-20:])
        assert freed.is_set(), "the recording never paused: " + "".join(lines[-20:])
        paused = [ln for ln in lines if "recording paused" in ln]
        assert len(paused) == 1 and str(path) in paused[0] and "ENOSPC" in paused[0]
        s = json.loads(out)
        rec = s["recording"]
        second = disk / "run_0001.mcap"
        assert rec["state"] == "writing" and rec["files"] == [str(path), str(second)] and rec["files_written"] == 2
        assert rec["write_errors"] == 1 and "No space left on device (ENOSPC)" in rec["error"]
        assert rec["lost"] > 0 and rec["lost_by_topic"].get("targets", 0) > 0  # targets went on while paused

        def targets(p):
            f = McapFile(p)
            return [m.sequence for ch, m in f.messages() if ch.topic.endswith("/targets")], f

        t1, f1 = targets(path)
        t2, f2 = targets(second)
        assert t1 and not f1.truncated and reader_count(path) > 0
        assert t2 and not f2.truncated and reader_count(second) > 0
        assert min(t2) > max(t1) + 1  # a gap: the frames targeted while the recording was paused
        assert s["frames_targets"] >= len(t1) + len(t2) + rec["lost_by_topic"]["targets"]


def qradar_with_fsize_limit(limit_bytes: int, *args: str) -> list[str]:
    """The command line of ``qradar *args`` in a process whose files may not grow past
    ``limit_bytes`` (RLIMIT_FSIZE), with SIGXFSZ ignored so that a write past it fails with
    EFBIG. Set in a small launcher that then execs, not in a preexec_fn (unsafe with threads)."""
    launcher = ("import os, resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
                f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit_bytes}, {limit_bytes})); "
                "os.execv(sys.executable, [sys.executable, '-m', 'qradar', *sys.argv[1:]])")
    return [sys.executable, "-c", launcher, *args]


@pytest.mark.slow
def test_qradar_run_with_stop_ends_the_recording_on_efbig_and_runs_on(tmp_path):
    path = tmp_path / "run.mcap"
    limit = 300_000
    cmd = qradar_with_fsize_limit(limit, "run", *RUNTIME_DECODER, "--duration", "60", "--json", "--record", str(path),
                                  "--on-write-error", "stop")
    code, lines, out = run_to_event(cmd, "recording stopped")
    assert code == 0, "".join(lines[-20:])
    stopped = [ln for ln in lines if "recording stopped" in ln]
    assert len(stopped) == 1 and "File too large (EFBIG)" in stopped[0] and str(path) in stopped[0]
    s = json.loads(out)
    rec = s["recording"]
    assert rec["state"] == "stopped" and rec["files"] == [str(path)] and "EFBIG" in rec["error"]
    f = McapFile(path)
    in_file = [m.sequence for ch, m in f.messages() if ch.topic.endswith("/targets")]
    assert in_file and not f.truncated and path.stat().st_size <= limit
    assert rec["lost_by_topic"]["targets"] > 0
    assert s["frames_targets"] >= len(in_file) + rec["lost_by_topic"]["targets"]  # targets went on


def test_qradar_record_with_stop_exits_cleanly_on_efbig(tmp_path, free_port, connect_when_ready):
    ep = f"tcp/127.0.0.1:{free_port}"
    path = tmp_path / "r.mcap"
    proc = subprocess.Popen(qradar_with_fsize_limit(400_000, "record", "-o", str(path), "--listen", ep, "--topics",
                                                    "radar/ef/raw", "--on-write-error", "stop"),
                            cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        session = connect_when_ready(ep, timeout_s=30)
        wait_until(lambda: any(r.ok is not None for r in session.liveliness().get("radar/alive/record/**",
                                                                                  timeout=1.0)), 20, "recorder alive")
        pub = session.declare_publisher("radar/ef/raw")
        for i in range(400):  # 8 KB each at ~20 Hz (a flush a second): past 400 kB in a few flushes
            if proc.poll() is not None:
                break
            pub.put(raw_frame("ef", i))
            threading.Event().wait(0.05)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 2, err
    errors = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(errors) == 1 and errors[0].startswith("qradar record: error: recording stopped after a write error")
    assert str(path) in errors[0] and "File too large (EFBIG)" in errors[0] and "Traceback" not in err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["state"] == "stopped" and summary["files"] == [str(path)]
    seqs, f = raw_seqs(path)
    assert seqs == list(range(len(seqs))) and len(seqs) >= 1 and not f.truncated
    assert summary["written"] == len(seqs)
