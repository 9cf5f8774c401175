"""The audit log of ``--secure``: refused TLS handshakes and messages denied by the
access-control policy, counted and summarized on stderr.

zenoh enforces mutual TLS and its access control in its Rust core and tells a Python
process nothing of what it refuses, except in its own log (the ``tracing`` crate), which
the Python package writes, once turned on with ``zenoh.init_log_from_env_or``, as text
lines to the process's **stdout** (file descriptor 1; zenoh 1.10). Under ``--secure`` a
command calls :func:`start` before its session opens: it turns that log on for the two
places that matter (``RUST_LOG`` directives :data:`DIRECTIVES`), points file descriptor 1
at a pipe read by a thread of this module, and gives Python's ``sys.stdout`` the real
stdout back, so what the program prints never passes through the pipe. The reader
counts what it recognizes and passes every line that is not zenoh's on to the real
stdout unchanged (a child process or a C library writing to descriptor 1).

What zenoh says, and what is counted (zenoh 1.10.2; message texts of
``io/zenoh-links/zenoh-link-tls/src/unicast.rs`` and
``zenoh/src/net/routing/interceptor/access_control.rs``):

- a TLS handshake that fails on a listener (plain TCP to a TLS port, a certificate of
  another CA or none, a self-signed or expired one, a handshake not finished within
  zenoh's timeout): ``WARN zenoh_link_tls::unicast: <reason>. Hint: increase the system
  open file limit.`` (sic: zenoh's accept loop says that of every accept error). It
  names neither the peer's address nor anything else of the peer: counted as
  ``refused_handshakes`` by reason;
- a message a remote sent and the policy denies: at TRACE,
  ``<zid> on <subject> is unauthorized to <Put|Delete|...> (ingress) on <key>``, or, for a
  key the remote declared, ``Using cached result: <zid> is unauthorized to ...``; the
  subject names the certificate's common name (``CertCommonName(sensor-s1)``). zenoh logs
  the same text when it computes its cache for a declared key (after ``ACL (ingress):
  caching permissions for `<key>` ...``): those lines are not messages and not counted.
  Counted by kind (:data:`KINDS`), identity and key;
- a session whose certificate (valid, of the project's CA) names no identity of the
  policy, e.g. a withdrawn one: ``INFO ... <zid> did not match any configured ACL subject``;
  zenoh then denies everything it sends but logs only the messages on keys it declared:
  counted as ``unlisted_identities``, its common name looked up in the admin space.

Egress decisions (what this process declines to send to a remote) are not counted: they
are the policy deciding who may read, not someone trying to write.

The TRACE lines are the cost: zenoh writes one for every message it lets through too
(ingress, and egress once per subscriber), ~5 µs of a core each with their reading here
(docs/security.md, *Audit log*); a client without a listener does without them (:func:`start`).
"""

from __future__ import annotations

import atexit
import io
import json
import os
import re
import select
import sys
import threading
import time
from collections import defaultdict
from typing import Callable, TextIO

#: the zenoh log directives the audit needs (tracing's EnvFilter syntax); LIGHT_DIRECTIVES for a
#: session that can meet only the router (see start)
DIRECTIVES = ("zenoh::net::routing::interceptor::access_control=trace", "zenoh_link_tls::unicast=warn")
LIGHT_DIRECTIVES = ("zenoh::net::routing::interceptor::access_control=info", "zenoh_link_tls::unicast=warn")
#: what is counted, in this order in health and summaries
KINDS = ("refused_handshakes", "denied_publications", "denied_tokens", "denied_declarations", "denied_queries",
         "unlisted_identities")
#: a summary line per kind and identity/key pair at most this often, s
INTERVAL_S = 60.0
#: the first events after a quiet interval are summarized this long after the first, s
FIRST_DELAY_S = 1.0
#: the reader waits this long after a read of fewer than BATCH_BYTES, for more lines to come at
#: once (a Python wake-up per line of zenoh's cost more than reading them), s
BATCH_WAIT_S = 0.02
BATCH_BYTES = 1 << 15
#: the most identity/key lines per kind in one summary (the rest in one more line)
MAX_LINES = 5
#: the most identity/key pairs a kind keeps between two summaries (an attacker spraying
#: keys: the others are counted together); the most zenoh ids named
MAX_PAIRS = 1000
MAX_NAMES = 10000
#: look-ups of an unnamed zenoh id in the admin space (one each 0.25 s)
RESOLVE_ATTEMPTS = 4

_NOUN = {"refused_handshakes": ("refused TLS handshake", "refused TLS handshakes"),
         "denied_publications": ("denied publication", "denied publications"),
         "denied_tokens": ("denied liveliness token", "denied liveliness tokens"),
         "denied_declarations": ("denied declaration", "denied declarations"),
         "denied_queries": ("denied query", "denied queries"),
         "unlisted_identities": ("session", "sessions")}

_ANSI = re.compile(rb"\x1b\[[0-9;]*m")
#: a line of zenoh's log (tracing-subscriber's default format), ANSI colours or not
_ZENOH_LINE = re.compile(rb"(?:\x1b\[[0-9;]*m)?\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d")
_MARKERS = (b"unauthorized", b"authorization error", b"caching permissions", b"did not match", b"Hint: increase",
            b"Error getting client cert")
#: the lines that matter, from ANSI-free text
_EVENT = re.compile(
    rb"^[^\n]*?\b(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\b[^\n]*?ThreadId\((?P<tid>\d+)\)\s+"
    rb"(?P<target>zenoh_link_tls::unicast|zenoh::net::routing::interceptor::access_control): "
    rb"(?P<msg>[^\n]*?(?:unauthorized|authorization error|caching permissions|did not match|Hint: increase|"
    rb"Error getting client cert)[^\n]*)$", re.M)
_CACHED = re.compile(r"Using cached result: (?P<zid>[0-9a-f]+) is unauthorized to (?P<action>.+?) "
                     r"\((?P<flow>ingress|egress)\) on (?P<key>\S+)$")
_DECIDED = re.compile(r"(?P<zid>[0-9a-f]+) on (?P<subject>.+?) (?:is unauthorized|has an authorization error) to "
                      r"(?P<action>.+?) \((?P<flow>ingress|egress)\) on (?P<key>\S+?)(?:: .*)?$")
_CACHING = re.compile(r"ACL \((?P<flow>ingress|egress)\): caching permissions for `(?P<key>[^`]*)`")
_NO_SUBJECT = re.compile(r"(?P<zid>[0-9a-f]+) did not match any configured ACL subject")
_HANDSHAKE = re.compile(r"(?P<reason>.*?)\.? Hint: increase the system open file limit\.?$")
_CERT_ERROR = re.compile(r"(?P<reason>Error getting client cert .*)$")
_CN = re.compile(r"CertCommonName\(([^)]*)\)")
_LINK = re.compile(r"Transport\(([^)]*)\)")
#: the last action zenoh computes when it caches the permissions of a declared key
_LAST_CACHED_ACTION = "Declare Liveliness Subscriber"


def kind_of(action: str) -> str:
    """The kind a denied message counts as, from zenoh's name of its action."""
    if "Put" in action or "Delete" in action:
        return "denied_publications"
    if "Liveliness Token" in action:
        return "denied_tokens"
    if "Subscriber" in action or "Queryable" in action:
        return "denied_declarations"
    if "Query" in action or "Reply" in action:
        return "denied_queries"
    return "denied_declarations"  # a message type zenoh may add


def _plural(kind: str, n: int) -> str:
    one, many = _NOUN[kind]
    return f"{n} {one if n == 1 else many}"


class AuditLog:
    """The counting and reporting half: fed zenoh's log text (:meth:`feed`), it counts
    by kind and keeps, per kind, the counts by (identity, key) since its last summary;
    :meth:`report` writes the summaries that are due to ``stream``, one line per kind and
    identity/key pair (:data:`MAX_LINES` at most, then one line for the rest), never
    sooner than ``interval_s`` after the kind's previous summary (``first_delay_s`` after
    its first event when it was quiet). ``resolve(zid)``, if given, names a zenoh id no
    log line named (a certificate's common name, or None)."""

    def __init__(self, name: str, stream: TextIO | None = None, interval_s: float = INTERVAL_S,
                 first_delay_s: float = FIRST_DELAY_S, clock: Callable[[], float] = time.monotonic):
        self.name, self.interval_s, self.first_delay_s, self.clock = name, interval_s, first_delay_s, clock
        self.stream = stream
        self.resolve: Callable[[str], str | None] | None = None
        self._lock = threading.Lock()
        self._counts = dict.fromkeys(KINDS, 0)
        self._window: dict[str, dict[tuple[str, str], int]] = {k: defaultdict(int) for k in KINDS}
        self._first: dict[str, float] = {}  # kind -> when the first event of its window came
        self._last_report: dict[str, float] = {}
        self._names: dict[str, str] = {}  # zenoh id -> who (common name, "unix-socket peer", ...)
        self._unresolved: set[str] = set()
        self._caching: dict[bytes, list] = {}  # thread id -> [flow, key, actions seen] of a cache computation
        self._overflow = dict.fromkeys(KINDS, 0)  # events beyond MAX_PAIRS identity/key pairs in a window
        self._attempts: dict[str, int] = {}  # zenoh id -> look-ups tried
        self.user_log = False  # RUST_LOG was set: zenoh's lines go on to stdout too (see start)
        self.full = True  # denied messages watched too (False: handshakes and unlisted identities only)

    # -- input ---------------------------------------------------------------------------------
    def feed(self, text: bytes) -> None:
        """Complete lines of zenoh's log (ANSI colours or not)."""
        if not any(m in text for m in _MARKERS):
            return
        text = _ANSI.sub(b"", text)
        with self._lock:
            for m in _EVENT.finditer(text):
                try:
                    self._line(m.group("tid"), m.group("target"), m.group("level"),
                               m.group("msg").decode("utf-8", "replace"))
                except Exception:  # noqa: BLE001 -- a line of an unexpected shape must not stop the reader
                    continue

    def _line(self, tid: bytes, target: bytes, level: bytes, msg: str) -> None:
        now = self.clock()
        if target == b"zenoh_link_tls::unicast":
            if level != b"WARN":
                return
            m = _HANDSHAKE.match(msg) or _CERT_ERROR.match(msg)
            if m:
                self._count("refused_handshakes", "", m.group("reason"), now)
            return
        m = _CACHING.match(msg)
        if m:
            self._caching[tid] = [m.group("flow"), m.group("key"), set()]
            return
        m = _DECIDED.match(msg)
        if m:
            zid, subject, action, flow, key = m.group("zid", "subject", "action", "flow", "key")
            self._learn(zid, subject)
            block = self._caching.get(tid)
            if block is not None and block[0] == flow and block[1] == key and (action, subject) not in block[2]:
                block[2].add((action, subject))  # zenoh computing its cache for a declared key: no message
                if action == _LAST_CACHED_ACTION:
                    del self._caching[tid]
                return
            self._caching.pop(tid, None)
            if flow == "ingress":
                self._count(kind_of(action), zid, key, now)
            return
        m = _CACHED.match(msg)
        if m:
            self._caching.pop(tid, None)
            if m.group("flow") == "ingress":
                self._count(kind_of(m.group("action")), m.group("zid"), m.group("key"), now)
            return
        m = _NO_SUBJECT.match(msg)
        if m:
            zid = m.group("zid")
            if zid not in self._names:
                self._unresolved.add(zid)
            self._count("unlisted_identities", zid, "", now)

    def _learn(self, zid: str, subject: str) -> None:
        if zid in self._names:
            return
        if len(self._names) >= MAX_NAMES:
            self._names.clear()
        cn = _CN.search(subject)
        if cn:
            self._names[zid] = cn.group(1)
        else:
            link = _LINK.search(subject)
            self._names[zid] = f"a {link.group(1)} peer (zenoh id {zid})" if link else f"zenoh id {zid}"
        self._unresolved.discard(zid)

    def _count(self, kind: str, who: str, key: str, now: float) -> None:
        self._counts[kind] += 1
        window = self._window[kind]
        if not window and not self._overflow[kind]:
            self._first[kind] = now
        if (who, key) in window or len(window) < MAX_PAIRS:
            window[(who, key)] += 1
        else:
            self._overflow[kind] += 1

    # -- output --------------------------------------------------------------------------------
    def counts(self) -> dict[str, int]:
        """Every kind's count since the start."""
        with self._lock:
            return dict(self._counts)

    def who(self, zid: str) -> str:
        return self._names.get(zid) or f"zenoh id {zid}"

    def resolve_pending(self) -> None:
        """Names the zenoh ids of sessions no log line named (with ``resolve``)."""
        if self.resolve is None:
            return
        with self._lock:
            pending = list(self._unresolved)
        for zid in pending:
            try:
                name = self.resolve(zid)
            except Exception:  # noqa: BLE001 -- a session closing under us: the id stays
                name = None
            with self._lock:
                self._attempts[zid] = self._attempts.get(zid, 0) + 1
                if name or self._attempts[zid] >= RESOLVE_ATTEMPTS:
                    self._unresolved.discard(zid)
                    self._attempts.pop(zid, None)
                if name and zid not in self._names:
                    self._names[zid] = name

    def report(self, final: bool = False) -> list[str]:
        """Writes (to ``stream``) and returns the summary lines that are due (``final``:
        every kind with events since its last summary)."""
        now = self.clock()
        lines = []
        with self._lock:
            for kind in KINDS:
                window = self._window[kind]
                if not window and not self._overflow[kind]:
                    continue
                last, first = self._last_report.get(kind), self._first[kind]
                due = first + self.first_delay_s if last is None else max(first + self.first_delay_s,
                                                                          last + self.interval_s)
                if not final and now < due:
                    continue
                # since the last summary, or since the first event if it came after a quiet interval
                span = now - (last if last is not None and first - last <= self.interval_s else first)
                lines += self._lines(kind, window, self._overflow[kind], max(1, round(span)))
                self._window[kind] = defaultdict(int)
                self._overflow[kind] = 0
                self._last_report[kind] = now
        if lines and self.stream is not None:
            try:
                self.stream.write("".join(line + "\n" for line in lines))
                self.stream.flush()
            except (OSError, ValueError):  # stderr gone
                pass
        return lines

    def _lines(self, kind: str, window: dict[tuple[str, str], int], overflow: int, span_s: int) -> list[str]:
        head = f"{self.name}: audit:"
        groups = sorted(window.items(), key=lambda item: (-item[1], item[0]))
        out = []
        for (who, key), n in groups[:MAX_LINES]:
            if kind == "refused_handshakes":
                out.append(f"{head} {_plural(kind, n)} ({key}) in the last {span_s} s")
            elif kind == "unlisted_identities":
                out.append(f"{head} {_plural(kind, n)} from {self.who(who)}, an identity not in the policy (zenoh "
                           f"denies everything it sends), in the last {span_s} s")
            else:
                out.append(f"{head} {_plural(kind, n)} from {self.who(who)} on {key} in the last {span_s} s")
        rest = groups[MAX_LINES:]
        if rest or overflow:
            n = sum(c for _, c in rest) + overflow
            what = "reasons" if kind == "refused_handshakes" else "identity/key pairs"
            out.append(f"{head} and {_plural(kind, n)} more, from {len(rest)}{' or more' if overflow else ''} "
                       f"other {what}, in the last {span_s} s")
        return out


class _Capture:
    """File descriptor 1 through a pipe: zenoh's lines to ``log.feed``, any other line on
    to the real stdout unchanged; Python's ``sys.stdout`` writes to the real stdout."""

    def __init__(self, log: AuditLog, passthrough: Callable[[bytes], bool]):
        self.log, self.passthrough = log, passthrough
        sys.stdout.flush()
        self.real = os.dup(1)
        r, w = os.pipe()
        try:  # room for a burst of zenoh lines while the reader waits for the GIL (Linux; 1 MiB unprivileged)
            import fcntl
            fcntl.fcntl(w, getattr(fcntl, "F_SETPIPE_SZ", 1031), 1 << 20)
        except (ImportError, OSError):
            pass
        os.dup2(w, 1)
        os.close(w)
        self.read_fd = r
        self.old_stdout = sys.stdout
        old = sys.stdout
        sys.stdout = io.TextIOWrapper(io.FileIO(self.real, "w", closefd=False),
                                      encoding=getattr(old, "encoding", None) or "utf-8",
                                      errors=getattr(old, "errors", None) or "strict",
                                      line_buffering=bool(getattr(old, "line_buffering", False)))
        self.reader = threading.Thread(target=self._read, name="audit-reader", daemon=True)
        self.reader.start()

    def _read(self) -> None:
        pending = b""
        while True:
            try:
                chunk = os.read(self.read_fd, 1 << 16)
            except InterruptedError:
                continue
            except OSError:
                break
            if not chunk:
                break
            if len(chunk) < BATCH_BYTES:  # let lines gather: a wake-up per line would cost more than the lines
                time.sleep(BATCH_WAIT_S)
                try:
                    chunk += os.read(self.read_fd, 1 << 20) if _readable(self.read_fd) else b""
                except OSError:
                    pass
            data = pending + chunk
            end = data.rfind(b"\n") + 1
            whole, pending = data[:end], data[end:]
            if pending and pending[:1] != b"\x1b" and not pending[:1].isdigit():
                whole, pending = data, b""  # a partial line, not zenoh's (which starts with its time): on at once
            if whole:
                try:
                    self._handle(whole)
                except Exception:  # noqa: BLE001 -- the reader must keep draining, or zenoh blocks on the pipe
                    pass
        if pending:
            try:
                self._handle(pending)
            except Exception:  # noqa: BLE001
                pass
        os.close(self.read_fd)

    def _handle(self, data: bytes) -> None:
        n_lines = data.count(b"\n") + (0 if data.endswith(b"\n") else 1)
        starts = data.startswith(b"\x1b[2m2") + data.count(b"\n\x1b[2m2")  # zenoh's lines (coloured)
        if starts == n_lines and not self.log.user_log:  # all zenoh's (the usual case): no line by line
            self.log.feed(data)
            return
        other, zenoh = [], []
        for line in data.splitlines(keepends=True):
            if _ZENOH_LINE.match(line):
                zenoh.append(line)
                if self.log.user_log and self.passthrough(line):
                    other.append(line)
            else:
                other.append(line)
        if zenoh:
            self.log.feed(b"".join(zenoh))
        if other:
            _write_all(self.real, b"".join(other))

    def close(self, timeout_s: float = 5.0) -> None:
        """The real stdout back on descriptor 1 (the pipe ends: the reader drains it) and
        in ``sys.stdout``."""
        try:
            sys.stdout.flush()
            self.old_stdout.flush()  # what went to descriptor 1 through the old object: into the pipe
        except (OSError, ValueError):
            pass
        os.dup2(self.real, 1)
        self.reader.join(timeout_s)
        sys.stdout = self.old_stdout


def _readable(fd: int) -> bool:
    return bool(select.select([fd], [], [], 0)[0])


def _write_all(fd: int, data: bytes) -> None:
    while data:
        try:
            n = os.write(fd, data)
        except InterruptedError:
            continue
        except OSError:
            return
        data = data[n:]


# -- the process's audit -----------------------------------------------------------------------------
class ProcessAudit:
    """The audit of this process while it is on: its log (the counts), the capture of
    descriptor 1 that feeds it, and the thread that writes its summaries every 0.25 s, each
    owned here and ended by :meth:`stop`."""

    def __init__(self, log: AuditLog, capture: _Capture):
        self.log, self.capture = log, capture
        self._stopped = threading.Event()
        self._ticker = threading.Thread(target=self._tick, name="audit", daemon=True)
        self._ticker.start()

    def _tick(self) -> None:
        while not self._stopped.wait(0.25):
            self.log.resolve_pending()
            self.log.report()

    def stop(self, timeout_s: float) -> dict[str, int]:
        self._stopped.set()
        self.capture.close(timeout_s)
        self._ticker.join(timeout_s)
        self.log.resolve_pending()
        self.log.report(final=True)
        return self.log.counts()


#: zenoh's log is the process's (zenoh.init_log_* takes effect once) and its capture holds
#: descriptor 1: one audit a process, set by start() and cleared by stop() (tests/test_layering.py)
_active: ProcessAudit | None = None
_start_lock = threading.Lock()


def start(name: str, stream: TextIO | None = None, interval_s: float = INTERVAL_S, full: bool = True) -> AuditLog:
    """Turn the audit on for this process (once; a second call returns the first's
    log): zenoh's log of :data:`DIRECTIVES` (plus ``RUST_LOG``'s own, if set) into the
    audit, summaries as ``<name>: audit: ...`` lines on ``stream`` (stderr). Call it
    before the first zenoh session opens.

    ``full=False`` (:data:`LIGHT_DIRECTIVES`) for a zenoh client without a listener: its
    only remote is the router it dials (only the router's certificate names hosts, and a
    client checks the name), which the policy lets send everything, so nothing there can
    be denied and zenoh's TRACE line for every message would be paid for nothing; refused
    handshakes (none without a listener) and unlisted identities are still watched."""
    global _active
    with _start_lock:
        if _active is not None:
            return _active.log
        import zenoh  # here: the counting half needs no zenoh

        log = AuditLog(name, stream if stream is not None else sys.stderr, interval_s=interval_s)
        log.full = full
        user = os.environ.get("RUST_LOG", "").strip()
        log.user_log = bool(user)
        user_traces = "trace" in user.lower()

        def passthrough(line: bytes) -> bool:  # only with RUST_LOG set: zenoh's lines as without the audit
            return user_traces or not (b"TRACE" in line[:60] and b"access_control" in line)

        capture = _Capture(log, passthrough)
        saved = os.environ.pop("RUST_LOG", None)
        try:
            zenoh.init_log_from_env_or(",".join([user or "off", *(DIRECTIVES if full else LIGHT_DIRECTIVES)]))
        finally:
            if saved is not None:
                os.environ["RUST_LOG"] = saved
        _active = ProcessAudit(log, capture)
        atexit.register(stop)
        return log


def active() -> AuditLog | None:
    """This process's audit, if :func:`start` turned it on."""
    audit = _active
    return None if audit is None else audit.log


def stdout_fd() -> int:
    """The descriptor of the real stdout (1, unless the audit holds 1 for zenoh's log): for
    a write that must not wait for the reader (before ``os._exit``)."""
    audit = _active
    return 1 if audit is None else audit.capture.real


def counts() -> dict[str, int] | None:
    log = active()
    return None if log is None else log.counts()


def health(extra: dict) -> dict:
    """A node's health ``extra`` with ``"audit"``: the counts, while the audit is on."""
    log = active()
    return extra if log is None else {**extra, "audit": log.counts()}


def summary() -> dict:
    """``{"audit": counts}`` for a command's summary while the audit is on, else {}."""
    log = active()
    return {} if log is None else {"audit": log.counts()}


def admin_links(session, remote: str = "*") -> list[dict]:
    """The links of ``session`` to the remote zenoh id ``remote`` (``*``: every one), as its
    admin space describes them (JSON: ``src``, ``dst``, ``auth_identifier`` (the peer's
    certificate common name), ...)."""
    out = []
    for reply in session.get(f"@/{session.zid()}/session/transport/unicast/{remote}/link/*", timeout=1.0):
        if reply.ok is None:
            continue
        try:
            link = json.loads(reply.ok.payload.to_bytes())
        except ValueError:
            continue
        if isinstance(link, dict):
            out.append(link)
    return out


def attach(session) -> None:
    """Look up, in ``session``'s admin space, the common names of the sessions that
    matched no subject of the policy (zenoh logs only their zenoh id)."""
    log = active()
    if log is None:
        return

    def resolve(zid: str) -> str | None:
        if session.is_closed():
            return None
        for link in admin_links(session, zid):
            cn = link.get("auth_identifier")
            addr = str(link.get("dst", "")).split("/", 1)[-1]
            if cn:
                return f"{cn} (at {addr})" if addr else str(cn)
        return None

    log.resolve = resolve


def format_counts(counts: dict[str, int]) -> str:
    """``3 refused_handshakes, 0 denied_publications, ...``"""
    return ", ".join(f"{counts.get(k, 0)} {k}" for k in KINDS)


def finish() -> dict:
    """:func:`stop`, as ``{"audit": counts}`` for a command's end summary ({} without the audit)."""
    final = stop()
    return {} if final is None else {"audit": final}


def stop(timeout_s: float = 5.0) -> dict[str, int] | None:
    """The audit's end (after the sessions closed): the pipe drained, the last
    summaries written, the counts returned. Safe to call twice (also called at exit)."""
    global _active
    with _start_lock:
        audit, _active = _active, None
        return None if audit is None else audit.stop(timeout_s)
