"""Helpers shared by the tests (not fixtures; those are in conftest.py): the one way to run
``qradar`` in a process of its own, a bounded wait, a collecting zenoh subscriber, a free
loopback port for code that needs one outside a fixture, a wait for a port, the listening
sockets and the memory of a process."""

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest


#: the command line that starts ``qradar`` with this interpreter
QRADAR = [sys.executable, "-m", "qradar"]
#: the decoder of the tests of the runtime (signals, supervision, recording, security, the bus,
#: exit statuses), not of the decoder: PBP. A cml localizer's start loads numba and its kernels,
#: about 1.2 s of CPU a process (`qradar run --frames 20`: 2.1 s of CPU with cml, 0.9 s with PBP,
#: 2026-11-30), and some 30 such processes were a tenth of the suite's CPU. The decoder's tests,
#: the README's recipes, the runs whose cml accuracy, uncertainty, tracks or count test is asserted
#: and `make run` keep cml, the default (the security runs' sanity bounds on the on-grid `single`
#: scene hold for PBP too).
RUNTIME_DECODER = ("--algo", "pbp")


def qradar(*args, timeout_s: float = 120, cwd=None, env=None) -> subprocess.CompletedProcess:
    """``qradar ARGS`` (each made a string) in a process of its own, its output captured as
    text, stdin closed; ended (and the test failed by ``TimeoutExpired``) after ``timeout_s``."""
    return subprocess.run([*QRADAR, *map(str, args)], capture_output=True, text=True, timeout=timeout_s,
                          stdin=subprocess.DEVNULL, cwd=cwd, env=env)


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range of ports for outgoing connections (and for bind to port 0)."""
    try:
        lo, hi = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(lo), int(hi)
    except (OSError, ValueError):
        return 32768, 60999


_HANDED_OUT: set[int] = set()  # this process's ports: never handed out twice
_PORT_LOCK = threading.Lock()


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that was free a moment ago, outside the kernel's ephemeral
    range (so no outgoing connection of this or another test takes it before its owner
    listens), never one this process handed out before, and spread by pid so parallel test
    workers draw from different places. At most 2000 candidates are tried."""
    lo, hi = _ephemeral_range()
    pool = [p for p in range(10000, 32768) if not lo <= p <= hi] or list(range(lo, hi + 1))
    start = (os.getpid() * 7919 + int(time.monotonic_ns() // 1000)) % len(pool)
    with _PORT_LOCK:
        for i in range(min(2000, len(pool))):
            port = pool[(start + i * 131) % len(pool)]
            if port in _HANDED_OUT:
                continue
            with socket.socket() as s:
                try:
                    s.bind((host, port))
                except OSError:
                    continue
            _HANDED_OUT.add(port)
            return port
    pytest.fail("no free port found among 2000 candidates", pytrace=False)


#: the least a wait gives its event before the test fails, s: a bound says when the event is
#: lost, not how fast it comes (four workers on two busy cores stall a thread for seconds)
WAIT_FLOOR_S = 30.0


def wait_until(pred, timeout_s=20.0, what="condition", poll_s=0.05):
    """Poll ``pred`` every ``poll_s`` s until it is true; fail the test once
    max(``timeout_s``, WAIT_FLOOR_S) has passed or after as many polls as fit in it, whichever
    comes first. ``what`` may be a callable, asked then (to say how far it got)."""
    timeout_s = max(timeout_s, WAIT_FLOOR_S)
    deadline = time.monotonic() + timeout_s
    for _ in range(int(timeout_s / poll_s) + 1):
        if pred():
            return
        if time.monotonic() >= deadline:
            break
        time.sleep(poll_s)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what() if callable(what) else what}", pytrace=False)


class Collector:
    """Every (key, payload) a subscriber on ``key`` receives."""

    def __init__(self, session, key):
        self.items, self.lock = [], threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample):
        with self.lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def of(self, suffix):
        with self.lock:
            return [p for k, p in self.items if k.endswith(suffix)]


def interrupt(proc: subprocess.Popen, timeout_s: float = 20) -> tuple[str, str]:
    """Ctrl-C (SIGINT) to ``proc`` if it still runs, then its (stdout, stderr); killed if it
    has not ended within ``timeout_s``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.communicate(timeout=timeout_s)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def read_lines(stream, on_line=None) -> tuple[list[str], threading.Thread]:
    """Lines of ``stream`` read by a thread (returned) into a list, ``on_line`` called on each."""
    lines = []

    def read():
        for line in stream:
            lines.append(line)
            if on_line is not None:
                on_line(line)

    t = threading.Thread(target=read, daemon=True)
    t.start()
    return lines, t


def stop_when(pred, stop: threading.Event, timeout_s: float, poll_s: float = 0.05) -> None:
    """Set ``stop`` once ``pred()`` holds, or after ``timeout_s`` (the test's assertions then
    say what is missing): a run's end on what it is to produce, not on a duration."""
    deadline = time.monotonic() + timeout_s
    try:
        while not pred() and time.monotonic() < deadline:
            time.sleep(poll_s)
    finally:
        stop.set()


def run_until(nodes, pred, timeout_s: float = 60.0) -> None:
    """``run_nodes(nodes)`` until ``pred()`` holds (what the run is to produce: frames, not
    seconds), at most ``timeout_s``."""
    from pipeline.nodes.runtime import run_nodes

    stop = threading.Event()
    threading.Thread(target=stop_when, args=(pred, stop, timeout_s), daemon=True).start()
    run_nodes(nodes, duration_s=timeout_s + 5.0, stop=stop)


def listening_sockets(pid: int) -> set[tuple[str, str, int]]:
    """(protocol, local address as /proc/net writes it in hex, port) of every TCP socket in
    LISTEN state and every unconnected UDP socket that process ``pid`` holds."""
    table = {}
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        with open(f"/proc/{pid}/net/{proto}") as f:
            for line in f.readlines()[1:]:
                cols = line.split()
                if cols[3] in ("0A", "07"):  # TCP LISTEN, or an unconnected UDP socket
                    addr, port = cols[1].split(":")
                    table[cols[9]] = (proto, addr, int(port, 16))
    out = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:[") and target[8:-1] in table:
            out.add(table[target[8:-1]])
    return out


def wait_port(port: int, timeout_s: float = WAIT_FLOOR_S) -> None:
    """Until something accepts TCP connections on 127.0.0.1:port (AssertionError after
    max(timeout_s, WAIT_FLOOR_S))."""
    timeout_s = max(timeout_s, WAIT_FLOOR_S)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise AssertionError(f"nothing listens on 127.0.0.1:{port}")


def rss_mb(pid: int | str = "self") -> float:
    """Resident memory (VmRSS) of process ``pid`` (default this one), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for {pid}")


def alive_nodes(session) -> list[str]:
    """The kinds of the nodes whose liveliness token ``session`` sees (``radar/alive/<kind>/...``),
    one entry per node: a node declares it once it subscribes."""
    return [str(r.ok.key_expr).split("/")[2] for r in session.liveliness().get("radar/alive/**", timeout=1.0)
            if r.ok is not None]
