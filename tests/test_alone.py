"""No silent emptiness: a stand-alone command whose zenoh session reaches no other
process within ALONE_AFTER_S says so once on stderr, naming where it looked and the fix,
and keeps running; ``qradar run`` (one in-process session on purpose) does not."""

from __future__ import annotations

import subprocess

from pipeline.bus.session import ALONE_AFTER_S
from zenoh_helpers import QRADAR, RUNTIME_DECODER, interrupt, qradar

WARNING = "no zenoh peer or router reached"


def test_a_command_alone_says_so_once_with_the_fix():
    out = qradar("view", "--port", "0", "--duration", str(ALONE_AFTER_S + 3))
    assert out.returncode == 0, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if WARNING in ln]
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith("qradar view: ") and "mode peer, connect [], listen []" in lines[0]
    assert "qradar router --listen tcp/127.0.0.1:7447" in lines[0] and "--mode client --connect" in lines[0]
    assert '"node": "view"' in out.stdout  # it kept running to its end


def test_a_connect_endpoint_that_answers_nothing_is_named(free_port):
    """The warning waited for (a line of stderr), then Ctrl-C: the node kept running."""
    ep = f"tcp/127.0.0.1:{free_port}"
    proc = subprocess.Popen([*QRADAR, "localize", *RUNTIME_DECODER, "--connect", ep, "--duration", "60"],
                            stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(40):  # bounded: its first lines, and EOF when it ends
            line = proc.stderr.readline()
            if WARNING in line or not line:
                break
        running = proc.poll() is None
    finally:
        out, err = interrupt(proc, 30)
    assert running, "it did not keep running"
    assert WARNING in line and f"nothing answers at {ep}" in line, line + err
    assert proc.returncode == 0 and WARNING not in err, err  # said once


def test_the_main_job_alone_on_purpose_does_not_warn():
    # frames, not a duration (a run without a frame fails, and a loaded host may start its driver late): at 20
    # a second of the simulated sensor's clock, which a busy host only slows, they span ALONE_AFTER_S + 2 s
    frames = int((ALONE_AFTER_S + 2) * 20)
    out = qradar("run", *RUNTIME_DECODER, "--rate", "20", "--frames", frames, "--duration", "120", "--no-record",
                 timeout_s=180)
    assert out.returncode == 0, out.stderr[-2000:]
    assert WARNING not in out.stderr and WARNING not in out.stdout
