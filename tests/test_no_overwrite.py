"""No file is replaced that qradar did not make: the simulator's pty link replaces only
its own stale link; recordings are created exclusively, default names do not collide,
and a split file whose name another program took is skipped, never overwritten."""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.wire import RawFrameMsg, encode_raw
from radar_driver.errors import ConfigError
from radar_driver.model import RadarConfig
from radar_driver.scene import resolve_scene
from radar_driver.simulator import PtyLink, SimulatorServer
from replay.errors import ReplayError
from replay.mcapio import McapFile
from replay.recorder import RecorderNode, default_recording_path
from zenoh_helpers import QRADAR, RUNTIME_DECODER, wait_until



def sim(link: Path, timeout_s: float = 30, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([*QRADAR, "sim", "--link", str(link)], capture_output=True, text=True,
                          timeout=timeout_s, stdin=subprocess.DEVNULL, **kw)


def test_sim_link_refuses_a_file_it_did_not_make(tmp_path):
    precious = tmp_path / "README.md"
    precious.write_text("the lab's notes\n")
    out = sim(precious)
    assert out.returncode == 2
    line = out.stderr.strip()
    assert "\n" not in line and str(precious) in line and "refusing to replace" in line and "a file" in line
    assert precious.read_text() == "the lab's notes\n" and not precious.is_symlink()


def test_sim_link_refuses_a_folder_and_a_link_to_something_else(tmp_path):
    (tmp_path / "dir").mkdir()
    (tmp_path / "other").symlink_to(tmp_path / "dir")
    for path, what in ((tmp_path / "dir", "a folder"), (tmp_path / "other", "not to a pty")):
        with pytest.raises(ConfigError, match=what):
            PtyLink(path).open()
    assert (tmp_path / "dir").is_dir() and os.readlink(tmp_path / "other") == str(tmp_path / "dir")


def test_a_stale_link_of_a_killed_simulator_is_replaced(tmp_path):
    link = tmp_path / "kmd2"
    proc = subprocess.Popen([*QRADAR, "sim", "--link", str(link)], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        assert "simulated K-MD2" in proc.stdout.readline()
        old = os.readlink(link)
        live = sim(link)  # a live simulator's link: refused, naming it
        assert live.returncode == 2 and f"served by process {proc.pid}" in live.stderr
    finally:
        proc.kill()  # SIGKILL: its link stays behind, stale
        proc.wait(10)
    assert link.is_symlink() and os.readlink(link) == old
    with SimulatorServer(resolve_scene("chamber"), link_path=link, rate_hz=0):
        assert os.readlink(link).startswith("/dev/pts/")
    assert not os.path.lexists(link)  # its own link, removed at the end


def test_a_link_replaced_by_someone_else_is_not_removed_at_close(tmp_path):
    link = tmp_path / "kmd2"
    pty = PtyLink(link)
    pty.open()
    link.unlink()
    link.write_text("somebody else's now")
    pty.close()
    assert link.read_text() == "somebody else's now"


def test_default_recording_names_are_to_the_millisecond():
    t = 1_790_000_000_123_456_789
    a, b = default_recording_path(Path("r"), t), default_recording_path(Path("r"), t + 1_000_000)
    assert a != b and a.name.startswith("run-") and a.name.endswith("-123.mcap") and b.name.endswith("-124.mcap")


def put_frames(session, n: int, sensor: str = "nw") -> None:
    for i in range(n):
        session.put(f"radar/{sensor}/raw", encode_raw(RawFrameMsg(sensor, i, i, RadarConfig(ramps_per_frame=1).config_id(),
                                                          np.zeros((256, 2), np.complex64))))


def test_an_explicit_recording_path_that_exists_is_refused(tmp_path, bus, zenoh_session):
    path = tmp_path / "lab.mcap"
    path.write_bytes(b"an older recording")
    with pytest.raises(ReplayError, match="exists: qradar does not overwrite a recording"):
        RecorderNode(bus, path, session=zenoh_session)
    assert path.read_bytes() == b"an older recording"


def test_a_taken_default_name_and_a_taken_split_name_are_skipped(tmp_path, bus, zenoh_session):
    base = tmp_path / "run-x.mcap"
    base.write_bytes(b"another run's")
    (tmp_path / "run-x-1_0001.mcap").write_bytes(b"not ours either")
    rec = RecorderNode(bus, base, session=zenoh_session, split_duration_s=0.3, health_period_s=60,
                       new_name_if_taken=True).start()
    try:
        for i in range(3):
            put_frames(zenoh_session, 10, f"s{i}")
            time.sleep(0.4)
        wait_until(lambda: rec.written == 30, 10)
    finally:
        rec.stop()
    names = [p.name for p in rec.paths]
    assert names[0] == "run-x-1.mcap" and "run-x-1_0001.mcap" not in names and len(names) >= 2
    assert names[1] == "run-x-1_0002.mcap"
    assert base.read_bytes() == b"another run's"
    assert (tmp_path / "run-x-1_0001.mcap").read_bytes() == b"not ours either"
    assert sum(McapFile(p).scan() for p in rec.paths) == 30 and rec.lost == 0


def test_two_runs_started_together_write_two_whole_recordings(tmp_path):
    cmd = [*QRADAR, "run", *RUNTIME_DECODER, "--frames", "30", "--json"]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                              stdin=subprocess.DEVNULL) for _ in range(2)]
    try:
        outs = [json.loads(p.communicate(timeout=120)[0].strip().splitlines()[-1]) for p in procs]
    finally:
        for p in procs:
            p.kill()
            p.wait(10)
    files = [Path(tmp_path / o["recording"]["files"][0]) for o in outs]
    assert files[0] != files[1]
    for o, f in zip(outs, files):
        assert o["recording"]["lost"] == 0 and o["recording"]["written"] > 0
        raw = sum(1 for ch, _ in McapFile(f).messages() if ch.topic.endswith("/raw"))
        assert raw == o["frames_raw"] == 30


def test_the_files_after_a_renamed_first_one_are_numbered_from_one(tmp_path, bus, zenoh_session):
    (tmp_path / "run-y.mcap").write_bytes(b"another run's")
    rec = RecorderNode(bus, tmp_path / "run-y.mcap", session=zenoh_session, split_duration_s=0.3,
                       health_period_s=60, new_name_if_taken=True).start()
    try:
        for i in range(2):
            put_frames(zenoh_session, 5, f"y{i}")
            time.sleep(0.4)
        wait_until(lambda: rec.written == 10, 10)
    finally:
        rec.stop()
    assert [p.name for p in rec.paths][:2] == ["run-y-1.mcap", "run-y-1_0001.mcap"]


def test_force_never_replaces_a_commands_own_input(tmp_path, cli):
    """``--force`` replaces an earlier output, never the recording a command reads, by any name:
    ``reprocess --mcap``, ``calibrate --out`` and ``recover -o`` naming the input are refused
    in one line and the input is left as it was."""
    src = tmp_path / "in.mcap"
    src.write_bytes((Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap").read_bytes())
    (tmp_path / "same.mcap").symlink_to(src)
    before = src.read_bytes()
    for argv in (["reprocess", src, "--algos", "pbp", "--alpha", "0.5", "--out", tmp_path / "rp", "--mcap", src],
                 ["reprocess", src, "--algos", "pbp", "--out", tmp_path / "rp", "--mcap", tmp_path / "same.mcap"],
                 ["calibrate", "--empty", src, "--out", tmp_path / "same.mcap"],
                 ["recover", src, "-o", tmp_path / "same.mcap"]):
        code, out, err = cli(*argv, "--force")
        assert code == 2 and len(err.strip().splitlines()) == 1, (argv, err)
        assert "input" in err or "give another output" in err, err
    assert src.read_bytes() == before


def test_a_recover_of_what_is_no_recording_leaves_no_output(tmp_path, cli):
    """A missing input, a folder, an empty file or a text file: refused in one line before the
    output exists, so the retry with the right input is not refused for it."""
    (tmp_path / "empty.mcap").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("the lab's notes\n")
    (tmp_path / "dir.mcap").mkdir()
    for src in ("missing.mcap", "empty.mcap", "notes.txt", "dir.mcap"):
        code, _, err = cli("recover", tmp_path / src, "-o", tmp_path / "out" / "x.mcap")
        assert code == 2 and str(tmp_path / src) in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "out" / "x.mcap").exists()
    code, out, _ = cli("recover", Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap",
                       "-o", tmp_path / "out" / "x.mcap")
    assert code == 0 and json.loads(out)["messages"] > 0


@pytest.mark.parametrize("prefix", ["", "x/", "/x", "a*", "a//b"])
def test_a_replay_prefix_that_is_no_key_is_one_line(prefix, cli):
    code, _, err = cli("replay", Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap",
                       "--replay-prefix", prefix, "--fast")
    assert code == 2 and "--replay-prefix" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_force_never_writes_through_a_link_and_a_folder_is_named_as_one(tmp_path, cli):
    """An output path that is a symbolic link is refused, ``--force`` or not, in one line naming
    the link: writing through it would replace the file it points to, which qradar did not
    make (``run --record``, ``recover -o``, ``calibrate --out``, ``reprocess`` into a folder
    holding one of its names as a link); an output path that is a folder is said to be one."""
    rec = Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap"
    notes = tmp_path / "notes.md"
    notes.write_text("the lab's notes\n")
    (tmp_path / "link.mcap").symlink_to(notes)
    (tmp_path / "rp").mkdir()
    (tmp_path / "rp" / "results.json").symlink_to(notes)
    (tmp_path / "dir.mcap").mkdir()
    for argv in (["run", "--frames", "5", "--record", tmp_path / "link.mcap"],
                 ["recover", rec, "-o", tmp_path / "link.mcap"],
                 ["calibrate", "--empty", rec, "--out", tmp_path / "link.mcap"],
                 ["reprocess", rec, "--algos", "pbp", "--alpha", "0.5", "--out", tmp_path / "rp"]):
        for force in ((), ("--force",)):
            code, _, err = cli(*argv, *force)
            assert code == 2 and len(err.strip().splitlines()) == 1, (argv, err)
            assert "is a symbolic link (to " in err and "remove the link or choose another name" in err, err
    assert notes.read_text() == "the lab's notes\n"
    for argv in (["run", "--frames", "5", "--record", tmp_path / "dir.mcap", "--force"],
                 ["recover", rec, "-o", tmp_path / "dir.mcap"]):
        code, _, err = cli(*argv)
        assert code == 2 and err.strip().endswith(f"{tmp_path / 'dir.mcap'} is a folder, not a file"), err


def test_a_recover_of_a_file_with_no_whole_message_writes_nothing(tmp_path, cli):
    """The first bytes of a recording (its magic and no whole record): nothing to recover, said
    in one line with status 2, and no "recovered" file of no message left to be mistaken for one."""
    rec = Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap"
    (tmp_path / "cut.mcap").write_bytes(rec.read_bytes()[:10])
    code, _, err = cli("recover", tmp_path / "cut.mcap", "-o", tmp_path / "fixed.mcap")
    assert code == 2 and "holds no complete message to recover (10 bytes)" in err, err
    assert not (tmp_path / "fixed.mcap").exists()


@pytest.mark.parametrize("argv", [["run", "--frames", "5", "--no-record"], ["localize"], ["quantize"], ["source"],
                                  ["record", "-o", "x.mcap"], ["view", "--web", "0"]])
def test_a_prefix_with_an_empty_chunk_is_one_line_in_every_command(argv, cli):
    """``--prefix a//b`` (zenoh forbids empty chunks) ended six commands in a traceback."""
    code, _, err = cli(*argv, "--prefix", "a//b")
    assert code == 2 and err.strip().splitlines() == [
        f"qradar {argv[0]}: error: key prefix 'a//b' must be a plain key expression like 'radar' or 'lab/radar'"], err


def test_a_recording_that_is_a_folder_is_said_to_be_one(tmp_path, cli):
    """``view --recording``, ``reprocess`` and ``calibrate`` said "no such file" of a folder."""
    (tmp_path / "rp").mkdir()
    for argv in (["view", "--web", "0", "--recording", tmp_path / "rp"], ["reprocess", tmp_path / "rp", "--out",
                 tmp_path / "x"], ["calibrate", "--empty", tmp_path / "rp", "--out", tmp_path / "c.json"]):
        code, _, err = cli(*argv)
        assert code == 2 and err.strip().endswith(f"cannot open {tmp_path / 'rp'}: Is a directory"), err
