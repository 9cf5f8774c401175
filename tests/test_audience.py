"""A source whose frames reach no node says so: ``qradar source`` on a prefix nobody
subscribes to (or with no router in common with the nodes) counted its frames out and ended
with status 0; now one line and status 1, as a recorder that received nothing. The check is
zenoh's matching status (:class:`pipeline.nodes.transport.Audience`)."""

from __future__ import annotations

import json
import os
import subprocess

from pipeline.bus.session import BusConfig
from pipeline.nodes.transport import Audience, MemoryTransport, ZenohTransport
from zenoh_helpers import QRADAR, Collector, qradar, wait_until


def test_an_audience_hears_a_subscriber_that_came_and_went_and_not_one_of_another_prefix(tmp_path):
    """Real zenoh sessions over a unix socket, and the in-memory transport: a subscriber of
    another prefix is no audience; one that matched once is, though it left before the end."""
    sock = tmp_path / "zenoh.sock"
    listener = BusConfig(listen=(f"unixsock-stream/{sock}",)).open()
    speaker = BusConfig(mode="client", connect=(f"unixsock-stream/{sock}",)).open()
    try:
        audience = Audience(ZenohTransport(speaker), ["radar/*/raw", "radar/*/quantized"])
        other = listener.declare_subscriber("lab2/**", lambda s: None)
        assert not audience.heard.wait(1.0) and not audience.matched()  # (a bounded look: nothing to wait for)
        sub = listener.declare_subscriber("radar/kmd2-0/quantized", lambda s: None)
        wait_until(audience.matched, 30, "the subscriber of radar/kmd2-0/quantized matched")
        sub.undeclare()
        other.undeclare()
        assert audience.matched()  # it came: the frames of that time reached it
        audience.close()
    finally:
        speaker.close()
        listener.close()
    mem = MemoryTransport()
    audience = Audience(mem, ["radar/*/raw"])
    mem.declare_subscriber("lab2/**", lambda s: None)
    assert not audience.matched()
    mem.declare_subscriber("radar/**", lambda s: None)
    assert audience.matched()


def test_a_source_that_nobody_hears_says_so_and_fails():
    out = qradar("source", "--frames", 10, "--quiet")
    assert out.returncode == 1, out.stderr[-2000:]
    assert json.loads(out.stdout)["subscribed"] is False
    assert out.stderr.strip().splitlines()[-1] == (
        "qradar source: error: nothing subscribed to radar/<sensor>/raw: its 10 frames reached no node (are the nodes "
        "up, on this --prefix, and joined to the same router as this source?)")


def test_a_node_of_other_sensors_is_no_audience_and_a_child_of_up_only_warns(tmp_path):
    """A subscriber of another sensor's frames (a node's --sensors pattern that leaves this
    source's ids out) hears none of them: status 1. Under ``--parent-pid`` (a node of ``qradar
    up``, which would restart a node that ends with 1 and send its frames again): a warning, 0."""
    sock = tmp_path / "zenoh.sock"
    session = BusConfig(listen=(f"unixsock-stream/{sock}",)).open()
    try:
        col = Collector(session, "radar/lab9/raw")
        z = ["--mode", "client", "--connect", f"unixsock-stream/{sock}", "--frames", "10", "--quiet"]
        alone = qradar("source", *z)
        assert alone.returncode == 1 and "error: nothing subscribed" in alone.stderr, alone.stderr[-2000:]
        child = qradar("source", *z, "--parent-pid", os.getpid())
        assert child.returncode == 0 and "warning: nothing subscribed" in child.stderr, child.stderr[-2000:]
        assert col.of("/raw") == []
    finally:
        session.close()


def test_a_source_heard_by_a_node_ends_with_status_0(tmp_path):
    """The subscriber (a recorder's, a quantizer's) on the same router: status 0, and every
    frame reached it."""
    sock = tmp_path / "zenoh.sock"
    session = BusConfig(listen=(f"unixsock-stream/{sock}",)).open()
    try:
        col = Collector(session, "radar/*/raw")
        proc = subprocess.run([*QRADAR, "source", "--frames", "10", "--quiet", "--mode", "client", "--connect",
                               f"unixsock-stream/{sock}"], capture_output=True, text=True, timeout=120,
                              stdin=subprocess.DEVNULL)
        assert proc.returncode == 0 and "nothing subscribed" not in proc.stderr, proc.stderr[-2000:]
        assert json.loads(proc.stdout)["subscribed"] is True
        wait_until(lambda: len(col.of("/raw")) == 10, 30, "the source's 10 frames")
    finally:
        session.close()
