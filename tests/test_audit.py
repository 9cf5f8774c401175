"""The audit log of ``--secure`` (pipeline/bus/audit.py): refused TLS handshakes and messages
denied by the access-control policy, read from zenoh's own log, counted, summarized on
stderr at most once an interval per kind and identity/key, and shown in health and in
the commands' end summaries.

The first tests feed :class:`AuditLog` lines as zenoh 1.10 writes them (copied from its
output); the capture test runs the real file-descriptor plumbing in a subprocess; the
last two run a secure ``qradar router`` and ``qradar run`` with real certificates and
attackers over 127.0.0.1. Every wait is bounded and every process is stopped."""

import json
import re
import shutil
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from pipeline.bus.audit import KINDS, MAX_LINES, AuditLog
from pipeline.bus.session import BusConfig
from pipeline.errors import BusError
from pipeline.bus.security import SecureConfig
from test_security import pki, qradar  # noqa: F401 -- the module's fixture: the lab's CA and another
from zenoh_helpers import QRADAR, RUNTIME_DECODER, Collector, wait_until

ROOT = Path(__file__).resolve().parents[1]
ACL = "zenoh::net::routing::interceptor::access_control"
TLS = "zenoh_link_tls::unicast"
S1 = "12eb117af9a60120e011c157fe938107"  # the zenoh id of sensor-s1's session, in the lines below
SUBJECT = f"Interface(lo)+CertCommonName(sensor-s1)+Transport(Tls)+{S1}"
LEVEL = {"TRACE": "\x1b[35mTRACE\x1b[0m", "DEBUG": "\x1b[34mDEBUG\x1b[0m", "INFO": "\x1b[32m INFO\x1b[0m",
         "WARN": "\x1b[33m WARN\x1b[0m"}


def zline(level: str, target: str, msg: str, thread: str = " rx-1 ThreadId(10)") -> bytes:
    """One line as zenoh's log writes it (tracing-subscriber's format, ANSI colours)."""
    return (f"\x1b[2m2026-11-25T19:11:25.655554Z\x1b[0m {LEVEL[level]} {thread.strip()} \x1b[2m{target}\x1b[0m"
            f"\x1b[2m:\x1b[0m {msg}\n").encode()


def denied(action: str, flow: str, key: str, zid: str = S1, subject: str = SUBJECT) -> bytes:
    return zline("TRACE", ACL, f"{zid} on {subject} is unauthorized to {action} ({flow}) on {key}")


def caching(flow: str, key: str) -> bytes:
    return zline("TRACE", ACL, f"ACL ({flow}): caching permissions for `{key}` ...")


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


# -- counting what zenoh logs ---------------------------------------------------------------

def test_denied_messages_are_counted_not_zenohs_cache_computations():
    """When a remote declares a key, zenoh computes its permissions for every message type
    and logs each decision (no message was sent): those lines are left out; the puts that
    follow ("Using cached result") and the puts on undeclared keys are counted, by the
    identity the subject names; egress decisions are not someone's publication."""
    log = AuditLog("t", stream=None)
    text = b"".join([
        # verbatim, from zenoh 1.10.2's log of a secure router (sensor-s1 declares radar/s0/raw)
        b"\x1b[2m2026-11-25T19:11:25.655542Z\x1b[0m \x1b[35mTRACE\x1b[0m  rx-1 ThreadId(10) \x1b[2mzenoh::net::routing"
        b"::interceptor::access_control\x1b[0m\x1b[2m:\x1b[0m ACL (ingress): caching permissions for `radar/s0/raw` ...\n",
        b"\x1b[2m2026-11-25T19:11:25.655554Z\x1b[0m \x1b[35mTRACE\x1b[0m  rx-1 ThreadId(10) \x1b[2mzenoh::net::routing"
        b"::interceptor::access_control\x1b[0m\x1b[2m:\x1b[0m 12eb117af9a60120e011c157fe938107 on Interface(lo)+CertCommonName"
        b"(sensor-s1)+Transport(Tls)+12eb117af9a60120e011c157fe938107 is unauthorized to Query (ingress) on radar/s0/raw\n",
        denied("Reply", "ingress", "radar/s0/raw"),
        denied("Put", "ingress", "radar/s0/raw"),
        denied("Delete", "ingress", "radar/s0/raw"),
        denied("Declare/Undeclare Queryable", "ingress", "radar/s0/raw"),
        denied("Declare/Undeclare Liveliness Token", "ingress", "radar/s0/raw"),
        caching("egress", "radar/s0/raw"),
        denied("Query", "egress", "radar/s0/raw"),
        denied("Put", "egress", "radar/s0/raw"),
        # the messages: a put on the declared key, two on an undeclared one, a denied egress
        b"\x1b[2m2026-11-25T19:11:25.655692Z\x1b[0m \x1b[35mTRACE\x1b[0m  rx-1 ThreadId(10) \x1b[2mzenoh::net::routing"
        b"::interceptor::access_control\x1b[0m\x1b[2m:\x1b[0m Using cached result: 12eb117af9a60120e011c157fe938107 is "
        b"unauthorized to Put (ingress) on radar/s0/raw\n",
        denied("Put", "ingress", "radar/s0/quantized"),
        denied("Put", "ingress", "radar/s0/quantized"),
        denied("Put", "egress", "other/key"),
        # allowed ones are not counted, whatever else the line says
        zline("TRACE", ACL, f"Using cached result: {S1} is authorized to Put (ingress) on radar/s1/raw"),
        zline("TRACE", ACL, f"{S1} on {SUBJECT} is authorized to Put (egress) on radar/s1/raw"),
    ])
    log.feed(text)
    counts = log.counts()
    assert counts["denied_publications"] == 3, counts
    assert sum(counts.values()) == 3, counts
    lines = log.report(final=True)
    assert lines == ["t: audit: 2 denied publications from sensor-s1 on radar/s0/quantized in the last 1 s",
                     "t: audit: 1 denied publication from sensor-s1 on radar/s0/raw in the last 1 s"]


def test_a_message_right_after_a_cache_computation_is_counted():
    """The same decision twice in one computation cannot be: the second is a message (a
    put on the undeclared key, on the same thread); tokens, declarations and queries are
    kinds of their own, and lines of other threads do not end a computation."""
    log = AuditLog("t", stream=None)
    log.feed(b"".join([caching("ingress", "radar/alive/localize/x"),
                       denied("Declare/Undeclare Liveliness Token", "ingress", "radar/alive/localize/x"),
                       zline("TRACE", ACL, "ACL (ingress): caching permissions for `radar/s9/raw` ...",
                             thread="rx-2 ThreadId(11)"),
                       denied("Declare/Undeclare Liveliness Token", "ingress", "radar/alive/localize/x"),
                       zline("TRACE", ACL, f"Using cached result: {S1} is unauthorized to Liveliness Token (ingress) "
                                           "on radar/alive/localize/x"),
                       denied("Query", "ingress", "radar/s0/raw"),
                       denied("Declare Subscriber", "ingress", "other/**")]))
    counts = log.counts()
    assert (counts["denied_tokens"], counts["denied_queries"], counts["denied_declarations"]) == (2, 1, 1), counts
    assert counts["denied_publications"] == 0


def test_refused_handshakes_by_reason_and_unlisted_identities():
    log = AuditLog("qradar router", stream=None)
    log.resolve = lambda zid: "recorder (at 127.0.0.1:40000)" if zid == "a0b0" else None
    log.feed(b"".join([
        zline("WARN", TLS, "received corrupt message of type InvalidContentType. Hint: increase the system open "
                           "file limit.", thread="acc-0 ThreadId(05)"),
        zline("WARN", TLS, "received fatal alert: UnknownCA. Hint: increase the system open file limit.",
              thread="acc-0 ThreadId(05)"),
        zline("WARN", TLS, "peer sent no certificates. Hint: increase the system open file limit.",
              thread="acc-0 ThreadId(05)"),
        zline("WARN", TLS, "received corrupt message of type InvalidContentType. Hint: increase the system open "
                           "file limit.", thread="acc-0 ThreadId(05)"),
        zline("WARN", TLS, "Error getting client cert common name: bad name", thread="acc-0 ThreadId(05)"),
        zline("DEBUG", TLS, "Accepted TLS connection on 127.0.0.1:7447: 127.0.0.1:39850. Common Name: sensor-s1.",
              thread="acc-0 ThreadId(05)"),
        zline("INFO", ACL, "a0b0 did not match any configured ACL subject. Default permission `Deny` will be "
                           "applied on all messages", thread="acc-0 ThreadId(05)"),
        zline("TRACE", ACL, "Using cached result: a0b0 is unauthorized to Put (ingress) on radar/s0/raw"),
        b"a line of something else\n",
    ]))
    log.resolve_pending()
    counts = log.counts()
    assert counts == {**dict.fromkeys(KINDS, 0), "refused_handshakes": 5, "unlisted_identities": 1,
                      "denied_publications": 1}
    lines = log.report(final=True)
    assert lines == [
        "qradar router: audit: 2 refused TLS handshakes (received corrupt message of type InvalidContentType) "
        "in the last 1 s",
        "qradar router: audit: 1 refused TLS handshake (Error getting client cert common name: bad name) "
        "in the last 1 s",
        "qradar router: audit: 1 refused TLS handshake (peer sent no certificates) in the last 1 s",
        "qradar router: audit: 1 refused TLS handshake (received fatal alert: UnknownCA) in the last 1 s",
        "qradar router: audit: 1 denied publication from recorder (at 127.0.0.1:40000) on radar/s0/raw "
        "in the last 1 s",
        "qradar router: audit: 1 session from recorder (at 127.0.0.1:40000), an identity not in the policy "
        "(zenoh denies everything it sends), in the last 1 s"]


def test_summaries_are_rate_limited_per_kind():
    """The first events after a quiet spell are said a second later, then at most once
    an interval per kind; never a line per event; at most MAX_LINES identity/key lines a
    kind, the rest in one; the end says what is left."""
    clock, out = Clock(), []
    log = AuditLog("q", stream=None, interval_s=60.0, first_delay_s=1.0, clock=clock)
    for _ in range(50):
        log.feed(denied("Put", "ingress", "radar/s0/raw"))
    clock.t += 0.5
    assert log.report() == []
    clock.t += 0.5
    out = log.report()
    assert out == ["q: audit: 50 denied publications from sensor-s1 on radar/s0/raw in the last 1 s"]
    for i in range(30):  # an attack going on: one line a minute
        clock.t += 1.0
        log.feed(denied("Put", "ingress", "radar/s0/raw"))
        log.feed(zline("WARN", TLS, "tls handshake eof. Hint: increase the system open file limit."))
        assert len(log.report()) == (1 if i == 1 else 0)  # the handshakes' first line (1 s on); publications wait
    clock.t += 30.0
    assert log.report() == ["q: audit: 30 denied publications from sensor-s1 on radar/s0/raw in the last 60 s"]
    clock.t += 1.0
    for i in range(MAX_LINES + 2):  # many keys: MAX_LINES lines and one for the rest
        for _ in range(i + 1):
            log.feed(denied("Put", "ingress", f"radar/x{i}/raw"))
    clock.t += 60.0
    lines = [ln for ln in log.report() if "publication" in ln]
    assert len(lines) == MAX_LINES + 1
    assert lines[0] == "q: audit: 7 denied publications from sensor-s1 on radar/x6/raw in the last 61 s"
    assert lines[-1] == "q: audit: and 3 denied publications more, from 2 other identity/key pairs, in the last 61 s"
    clock.t += 5.0
    log.feed(denied("Put", "ingress", "radar/s0/raw"))
    assert log.report() == []
    assert log.report(final=True) == ["q: audit: 1 denied publication from sensor-s1 on radar/s0/raw "
                                      "in the last 5 s"]
    assert log.counts()["denied_publications"] == 50 + 30 + 28 + 1
    assert log.counts()["refused_handshakes"] == 30


# -- the capture: descriptor 1 through a pipe -------------------------------------------------

CAPTURE = r"""
import os, sys, time
from pipeline.bus import audit
audit.start("t")
print("python's own line", flush=True)
os.write(1, b"a line on descriptor 1\n")
os.write(1, b"\x1b[2m2026-11-25T19:11:25.145620Z\x1b[0m \x1b[33m WARN\x1b[0m acc-0 ThreadId(05) "
            b"\x1b[2mzenoh_link_tls::unicast\x1b[0m\x1b[2m:\x1b[0m received fatal alert: UnknownCA. "
            b"Hint: increase the system open file limit.\n")
os.write(1, b"no newline")
sys.stderr.write("stderr untouched\n")
time.sleep(0.2)
print("|", audit.stop())
"""


@pytest.mark.parametrize("rust_log", [None, "warn"])
def test_capture_counts_zenohs_lines_and_passes_on_the_rest(rust_log):
    """What is not zenoh's reaches stdout unchanged (Python's prints and other writers of
    descriptor 1, partial lines too); zenoh's lines are counted and, unless RUST_LOG asks
    for them, kept off stdout; stderr is not touched."""
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)}
    if rust_log:
        env["RUST_LOG"] = rust_log
    proc = subprocess.run([sys.executable, "-c", CAPTURE], capture_output=True, text=True, timeout=60, env=env,
                          cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert out.startswith("python's own line\n"), out
    zenohs = ("\x1b[2m2026-11-25T19:11:25.145620Z\x1b[0m \x1b[33m WARN\x1b[0m acc-0 ThreadId(05) \x1b[2mzenoh_link_tls"
              "::unicast\x1b[0m\x1b[2m:\x1b[0m received fatal alert: UnknownCA. Hint: increase the system open file "
              "limit.\n")
    # zenoh's line on stdout, as without the audit, only when RUST_LOG asks for zenoh's log
    assert f"a line on descriptor 1\n{zenohs if rust_log else ''}no newline|" in out, out
    assert out.rstrip().endswith("'refused_handshakes': 1, 'denied_publications': 0, 'denied_tokens': 0, "
                                 "'denied_declarations': 0, 'denied_queries': 0, 'unlisted_identities': 0}"), out
    assert proc.stderr.splitlines() == ["stderr untouched",
                                        "t: audit: 1 refused TLS handshake (received fatal alert: UnknownCA) in "
                                        "the last 1 s"], proc.stderr


# -- real sessions ------------------------------------------------------------------------------

class Lines:
    """Every line a process writes on a stream, read by a thread."""

    def __init__(self, stream):
        self.lines, self.lock = [], threading.Lock()
        self.thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self.thread.start()

    def _read(self, stream):
        for line in stream:
            with self.lock:
                self.lines.append(line.rstrip("\n"))

    def matching(self, pattern: str) -> list[re.Match]:
        with self.lock:
            return [m for m in map(re.compile(pattern).fullmatch, self.lines) if m]


def terminate(proc: subprocess.Popen, *readers: Lines, timeout_s: float = 20) -> None:
    """SIGTERM ``proc`` (SIGKILL after ``timeout_s``) and let its readers finish."""
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout_s)
    for r in readers:
        r.thread.join(5)


def summed(lines: Lines, pattern: str) -> int:
    return sum(int(m.group(1)) for m in lines.matching(pattern))


def test_router_logs_and_counts_refused_handshakes_and_denied_publications(pki, tmp_path, free_port,
                                                                           connect_when_ready):
    """A secure router: a plain TCP connection, a zenoh client in plain TCP, one with
    another CA's certificate, a sensor publishing another sensor's key and a withdrawn
    identity. Each is one summary line (or two, when the attack straddles a summary) on
    the router's stderr with the reason or the identity and key, and counted in its end
    summary; what the sensor may publish is not."""
    lab, other = pki
    routers = tmp_path / "router-pki"  # the router's copy: the recorder withdrawn
    shutil.copytree(lab, routers)
    subprocess.run([*QRADAR, "security", "remove", str(routers), "recorder"], check=True,
                   capture_output=True, timeout=60)
    ep = f"tls/127.0.0.1:{free_port}"
    router = qradar("router", "--secure", routers, "--listen", ep, "--duration", "60")
    out, err = Lines(router.stdout), Lines(router.stderr)
    sessions = []
    puts = 12
    try:
        sessions.append(connect_when_ready(ep, timeout_s=30, mode="client", secure=SecureConfig(lab, "viewer")))
        with socket.create_connection(("127.0.0.1", free_port), timeout=5) as s:  # not TLS at all
            s.sendall(b"GET / HTTP/1.0\r\n\r\n")
            s.recv(100)  # until the router hangs up
        for bus in (BusConfig(mode="client", connect=(f"tcp/127.0.0.1:{free_port}",)),
                    BusConfig(mode="client", connect=(ep,), secure=SecureConfig(other, "sensor-s0"))):
            with pytest.raises(BusError, match="cannot open zenoh session"):
                bus.open().close()
        s1 = BusConfig(mode="client", connect=(ep,), secure=SecureConfig(lab, "sensor-s1")).open()
        sessions.append(s1)
        for _ in range(puts):
            s1.put("radar/s0/raw", b"forged")  # another sensor's key
            s1.put("radar/s1/health", b"{}")  # its own: allowed
        withdrawn = BusConfig(mode="client", connect=(ep,), secure=SecureConfig(lab, "recorder")).open()
        sessions.append(withdrawn)
        wait_until(lambda: summed(err, r"qradar router: audit: (\d+) denied publications? from sensor-s1 on "
                                       r"radar/s0/raw in the last \d+ s") == puts
                   and err.matching(r".* refused TLS handshakes? \(received fatal alert: UnknownCA\) .*")
                   and err.matching(r".* session from recorder \(at 127\.0\.0\.1:\d+\), an identity not in the "
                                    r"policy .*"), 20, "the router's audit lines")
    finally:
        for s in sessions:
            s.close()
        terminate(router, out, err)
    assert router.returncode == 0, err.lines
    final = json.loads(out.lines[-1])
    assert final["node"] == "router"
    counts = final["audit"]
    handshakes = summed(err, r"qradar router: audit: (\d+) refused TLS handshakes? \(.*\) in the last \d+ s")
    assert counts["refused_handshakes"] == handshakes >= 3, err.lines  # the plain connections, the other CA
    # the two plain connections: not TLS, each a corrupt message to the router's TLS (which TLS field
    # the first bytes break depends on how they arrive: InvalidContentType, at times
    # UnknownProtocolVersion for the zenoh client's, seen 1 in 4 under three busy loops)
    assert summed(err, r".* (\d+) refused TLS handshakes? \(received corrupt message of type \w+\) "
                       r"in the last \d+ s") >= 2, err.lines
    assert counts["denied_publications"] == puts and counts["unlisted_identities"] == 1, counts
    assert not err.matching(r".*radar/s1/health.*")  # allowed, not audited
    assert len(err.matching(r".*denied publications? from sensor-s1 on radar/s0/raw.*")) <= 2  # not one a put
    assert err.lines[-1] == (f"qradar router: audit: {handshakes} refused_handshakes, {puts} denied_publications, "
                             f"{counts['denied_tokens']} denied_tokens, 0 denied_declarations, 0 denied_queries, "
                             "1 unlisted_identities in all"), err.lines
    assert all(ln.startswith("qradar router: audit: ") for ln in err.lines), err.lines  # nothing else on stderr


def test_run_counts_denials_in_health_and_its_summary(pki, free_port, connect_when_ready):
    """``qradar run --secure --listen tls/...``: a sensor of another id publishing the run's
    sensor's key is denied by the run's session; the run says so on stderr, its nodes'
    health carries the counts (``extra.audit``), and its JSON summary (still the only thing
    on stdout) too. The run ends (SIGTERM, its normal end) once its health counted them and
    its targets flow: not after a number of frames that a slow TLS connect can outlast."""
    lab, _ = pki
    ep = f"tls/127.0.0.1:{free_port}"
    run = qradar("run", *RUNTIME_DECODER, "--secure", lab, "--listen", ep, "--scene", "single", "--K", "1",
                 "--duration", "120", "--no-record", "--json")
    out, err = Lines(run.stdout), Lines(run.stderr)
    attacker = None
    puts = 9
    try:
        viewer = connect_when_ready(ep, timeout_s=30, mode="client", secure=SecureConfig(lab, "viewer"))
        health = Collector(viewer, "radar/*/health")
        targets = Collector(viewer, "radar/kmd2-0/targets")
        attacker = BusConfig(mode="client", connect=(ep,), secure=SecureConfig(lab, "sensor-s1")).open()
        for _ in range(puts):
            attacker.put("radar/kmd2-0/raw", b"forged")

        def audited() -> list[dict]:
            return [json.loads(p)["extra"]["audit"] for p in health.of("kmd2-0/health")
                    if b'"audit"' in p]

        wait_until(lambda: any(a["denied_publications"] == puts for a in audited()) or run.poll() is not None, 30,
                   "the run's health to count the denied publications")
        wait_until(lambda: targets.items or run.poll() is not None, 30, "the run's targets")
        assert run.poll() is None, err.lines
    finally:
        if attacker is not None:
            attacker.close()
        terminate(run, out, err, timeout_s=60)
    assert run.returncode == 0, err.lines
    assert len(out.lines) == 1, out.lines  # one JSON object, nothing else: zenoh's log did not leak onto stdout
    summary = json.loads(out.lines[0])
    assert summary["interrupted"] is True and summary["frames_targets"] > 0
    assert summary["audit"] == {**dict.fromkeys(KINDS, 0), "denied_publications": puts}, summary["audit"]
    assert summed(err, r"qradar run: audit: (\d+) denied publications? from sensor-s1 on radar/kmd2-0/raw "
                       r"in the last \d+ s") == puts, err.lines
    assert all(set(a) == set(KINDS) for a in audited())
