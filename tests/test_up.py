"""``qradar up LAB.toml``: the lab file's nodes as real processes (a router, the simulated
sensors or a driver per sensor, the quantizer, the localizer, the recorder), each handed
its own options, supervised, stopped in order by SIGTERM with nothing left behind, and
gone by themselves when ``up`` is SIGKILLed; the nodes placed by host."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

from qradar.cli.up import plan_nodes, read_lab, setup_file
from pipeline.dsp.decode import default_alpha
from radar_driver.model import RadarConfig
from replay.mcapinfo import describe
from replay.mcapio import McapFile
from test_orphans import alive, child_config, children_of, kill_all, wait_for
from zenoh_helpers import QRADAR, RUNTIME_DECODER

STARTED = re.compile(r"qradar up: (.+?): started \(pid (\d+)\) on (\S+)")


def start_up(tmp_path: Path, text: str, *extra: str) -> subprocess.Popen:
    (tmp_path / "lab.toml").write_text(text)
    return subprocess.Popen([*QRADAR, "up", "lab.toml", *extra], cwd=tmp_path, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_started(proc: subprocess.Popen, names: set[str], timeout_s: float = 60.0) -> tuple[dict[str, int], list[str]]:
    """The pids of ``up``'s nodes ``names`` from its stderr lines, once all have started."""
    pids, lines = {}, []
    deadline = time.monotonic() + timeout_s
    while set(pids) != names and time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if m := STARTED.search(line):
            pids[m.group(1)] = int(m.group(2))
    assert set(pids) == names, "".join(lines)[-3000:]
    return pids, lines


def recorded(path: Path) -> list[str]:
    """The topics of the messages of a recording so far ([] before its first chunk)."""
    try:
        return [ch.topic for ch, _ in McapFile(path).messages()]
    except Exception:  # not there yet, or no chunk yet
        return []


#: the lab file's decoder of these tests of the supervision, not of the decoder (zenoh_helpers.RUNTIME_DECODER)
DECODER = f'[decoder]\nalgo = "{RUNTIME_DECODER[1]}"\n\n'

SIMULATED = """\
scene = "chamber-ideal"
rate = 20.0

""" + DECODER + """[recording]
record = "up.mcap"
"""


def test_up_starts_its_nodes_and_stops_them_with_nothing_left_behind(tmp_path):
    proc = start_up(tmp_path, SIMULATED)
    pids = {}
    try:
        pids, _ = wait_started(proc, {"router", "record", "localize", "quantize", "sources"})
        assert all(children_of(proc.pid)) and set(children_of(proc.pid)) == set(pids.values())
        socket_dir = Path(child_config(pids["quantize"])["zenoh"]["connect"][0].removeprefix("unixsock-stream/")).parent
        assert socket_dir.is_dir()  # the nodes meet on a unix socket: nothing listens on the network
        # frames go all the way: source -> quantize -> localize -> record (a file being written reads up to its
        # last flushed chunk)
        # (read every 0.5 s: each look parses the file so far, which at 20 looks a second took a core from
        # the nodes on a loaded host)
        assert wait_for(lambda: recorded(tmp_path / "up.mcap").count("radar/kmd2-0/targets") >= 30, 90.0, 0.5)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        kill_all([proc.pid, *pids.values()])
    assert proc.returncode == 0, err[-3000:]
    report = json.loads(out.strip().splitlines()[-1])["up"]
    nodes = report["nodes"]
    assert set(nodes) == {"router", "record", "localize", "quantize", "sources"} and report["host"] == "localhost"
    assert all(n["restarts"] == 0 and n["exit_code"] == 0 for n in nodes.values()), \
        {name: (n["restarts"], n["exit_code"], n["exits"]) for name, n in nodes.items()}
    assert nodes["localize"]["summary"]["frames_out"] >= 30 and nodes["record"]["summary"]["written"] >= 90
    # each node starts once the one before it is alive: the sensors' first frames reach the localizer
    sent = nodes["sources"]["summary"]["frames_out"]
    assert nodes["localize"]["summary"]["frames_in"] >= 0.9 * sent and nodes["quantize"]["summary"]["frames_in"] \
        >= 0.9 * sent, (sent, nodes["quantize"]["summary"], nodes["localize"]["summary"])
    assert not any(alive(p) for p in pids.values()) and not socket_dir.exists()
    topics = recorded(tmp_path / "up.mcap")
    assert all(topics.count(f"radar/kmd2-0/{t}") >= 30 for t in ("raw", "quantized", "targets")), len(topics)
    # the file says the set-up as a run's does (it said "quantizer none, decoder none, uncalibrated")
    info = describe(tmp_path / "up.mcap")
    assert info["radar"]["config_id"] == RadarConfig().config_id()
    assert info["quantizer"]["alpha"] == default_alpha(RUNTIME_DECODER[1])
    assert info["decoder"]["algo"] == RUNTIME_DECODER[1] and info["decoder"]["K"] == 2 and info["truth"]["name"] \
        == "chamber-ideal"


def test_a_killed_up_leaves_no_node_behind(tmp_path):
    """SIGKILL of up: each of its nodes sees its parent gone and stops by itself."""
    proc = start_up(tmp_path, SIMULATED.replace("[recording]\n", "[recording]\nno-record = true\n"))
    pids = {}
    try:
        pids, _ = wait_started(proc, {"router", "localize", "quantize", "sources"})
        assert all(alive(p) for p in pids.values())
        proc.kill()
        proc.communicate(timeout=20)
        assert wait_for(lambda: not any(alive(p) for p in pids.values()), 30.0), \
            [p for p in pids.values() if alive(p)]
    finally:
        kill_all([proc.pid, *pids.values()])


def test_a_node_that_dies_is_started_again(tmp_path):
    proc = start_up(tmp_path, SIMULATED.replace("[recording]\n", "[recording]\nno-record = true\n"))
    pids = {}
    try:
        pids, _ = wait_started(proc, {"router", "localize", "quantize", "sources"})
        import os

        os.kill(pids["quantize"], signal.SIGKILL)
        again, _ = wait_started(proc, {"quantize"})
        assert again["quantize"] != pids["quantize"] and alive(again["quantize"])
        pids["quantize again"] = again["quantize"]
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        kill_all([proc.pid, *pids.values()])
    quantize = json.loads(out.strip().splitlines()[-1])["up"]["nodes"]["quantize"]
    assert quantize["restarts"] == 1 and "exited with status -9" in quantize["exits"][0]
    assert not any(alive(p) for p in pids.values())


HOSTS = """\
[[sensor]]
url = "/dev/ttyUSB0"
id = "kmd2-0"
host = "bench1"

[[sensor]]
url = "/dev/ttyUSB0"
id = "kmd2-1"
host = "bench2"

[hosts]
default = "hub"

[zenoh]
listen = ["tcp/0.0.0.0:7447"]
connect = ["tcp/10.0.0.2:7447"]
"""


def test_the_nodes_are_placed_by_host(tmp_path):
    (tmp_path / "lab.toml").write_text(HOSTS)
    args, _ = read_lab(tmp_path / "lab.toml")
    nodes = {n.name: n for n in plan_nodes(args, tmp_path)}
    assert {n: x.host for n, x in nodes.items()} == {"router": "hub", "record": "hub", "localize": "hub",
                                                     "quantize": "hub", "driver kmd2-0": "bench1",
                                                     "driver kmd2-1": "bench2"}
    drive = nodes["driver kmd2-0"].config()
    assert drive["port"] == "/dev/ttyUSB0" and drive["zenoh"]["connect"] == ["tcp/10.0.0.2:7447"]
    assert drive["zenoh"]["mode"] == "client" and drive["parent-pid"] > 0
    assert nodes["router"].config()["zenoh"]["listen"] == ["tcp/0.0.0.0:7447"]
    assert nodes["localize"].config()["decoder"]["K"] == 2  # a real sensor without a truth: 2
    # the hub's recorder gets the set-up's metadata though the benches' sensors share a port path
    meta = json.loads(setup_file(args, tmp_path).read_text())
    assert sorted(meta["qradar.sensors"]) == ["kmd2-0", "kmd2-1"] and json.loads(meta["qradar.localizer"]["K"]) == 2
    assert json.loads(meta["qradar.quantizer"]["bits"]) == 1 and "qradar.radar" in meta


@pytest.mark.parametrize("text, host, words", [
    (HOSTS, "nowhere", "no node of lab.toml runs on host 'nowhere'; its hosts: bench1, bench2, hub"),
    (HOSTS.replace('connect = ["tcp/10.0.0.2:7447"]\n', ""), "bench1", "the router runs on host 'hub': give "
     "[zenoh] connect"),
    (HOSTS.replace('host = "bench2"', 'host = "bench1"'), "bench1", "is the port of sensor kmd2-0 too"),
    ("empty = true\n", "localhost", "empty = true (the empty chamber) is for `qradar run`"),
    ("[quantizer]\nbits = 0\n", "localhost", "lab.toml:2: [quantizer] bits = 0: must be >= 1"),
    # what run checks before it starts (its localizer), before a node starts: a localizer failed it twice
    ("[decoder]\nK = 300\n", "localhost", "K=300 must be an integer in [1, N = 256]"),
])
def test_a_set_up_up_cannot_start_is_one_line_and_starts_nothing(tmp_path, text, host, words):
    proc = start_up(tmp_path, text, "--host", host)
    out, err = proc.communicate(timeout=60)
    lines = err.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and words in lines[0], err
    assert "started" not in err


def test_a_router_endpoint_another_set_up_listens_on_is_refused_before_any_node_starts(tmp_path):
    """A second ``up`` of the same file: its router could not bind, and its nodes, started all
    the same, joined the first set-up's router and sent a second kmd2-0 into it."""
    import socket

    with socket.socket() as other:  # the first set-up's router, as far as a connection can tell
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        proc = start_up(tmp_path, f'frames = 40\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n')
        out, err = proc.communicate(timeout=60)
    lines = err.strip().splitlines()
    assert proc.returncode == 2 and lines == [
        f"qradar up: error: tcp/127.0.0.1:{port} already has a listener (another `qradar up` or router?): "
        "this set-up's router cannot listen there, and its nodes would join the other set-up; stop that one, or "
        "give [zenoh] listen another endpoint"], err

def test_readiness_counts_tokens_by_kind_and_holds_a_bounded_number():
    """``up`` sees its nodes' liveliness tokens come and go (a subscriber's samples); a peer
    declaring tokens without end takes no more than MAX_TOKENS of its memory."""
    from types import SimpleNamespace

    import zenoh

    from pipeline.bus.session import BusConfig
    from qradar.cli.up import MAX_TOKENS, Readiness

    ready = Readiness(BusConfig(prefix="radar"))
    ready.session = object()  # counted without a session of its own: the samples are handed in

    def token(key, kind=zenoh.SampleKind.PUT):
        ready._on_token(SimpleNamespace(key_expr=key, kind=kind))

    token("radar/alive/quantize/a1")
    token("radar/alive/localize/b2")
    assert ready.count("quantize") == 1 and ready.count("localize") == 1 and ready.count("record") == 0
    token("radar/alive/quantize/a1", zenoh.SampleKind.DELETE)
    assert ready.count("quantize") == 0
    for i in range(MAX_TOKENS + 500):
        token(f"radar/alive/source/x{i}")
    assert len(ready._alive) == MAX_TOKENS


def test_a_set_up_whose_driver_never_works_ends_with_a_non_zero_status(tmp_path):
    """A sensor's url that names no device: its driver fails at each start, and the set-up ends
    while it waits to start again or has just started again. As ``run`` with no frame, ``up``
    ends with status 1 and one line naming the sensor and why (it ended with 0, the driver
    marked in its JSON only)."""
    text = f'[[sensor]]\nurl = "{tmp_path / "no-such-port"}"\nid = "lab1"\n\n{DECODER}[recording]\nno-record = true\n'
    proc = start_up(tmp_path, text, "--duration", "5")
    try:
        out, err = proc.communicate(timeout=90)
    finally:
        proc.kill()
    assert proc.returncode == 1, (proc.returncode, err[-2000:])
    line = [x for x in err.splitlines() if x.startswith("qradar up: error:")]
    assert len(line) == 1 and "lab1" in line[0] and "no-such-port" in line[0], line
    node = json.loads(out.strip().splitlines()[-1])["up"]["nodes"]
    assert any(v["exits"] for v in node.values()), node
