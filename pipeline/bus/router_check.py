"""``--secure``: only the router is the router. After its session opens, and for every
link it makes later (a reconnection after the router restarted), a node checks that the
peer at the other end of a TLS link is a router identity of its policy.

zenoh's TLS checks that the peer's certificate is of the project's CA and, when dialling,
that it names the host dialled; a certificate of another role that names that host (one
issued before only the router's could, or a stolen one) would pass. zenoh 1.x tells a
session who is at the other end of each of its links: ``session.info.links()``, each
with ``auth_identifier``, the common name of the peer's certificate, and
``session.info.declare_link_events_listener`` for links made later (zenoh-python 1.10 has both;
a version without them: the admin space ``@/<zid>/session/transport/unicast/*/link/*`` says the
same, polled). Which links are checked: every TLS link of a session whose own identity
is not a router's (such a node meets only routers under ``--secure``); the links a router
identity (``qradar router``, ``qradar run``) dialled, those whose destination is one of
its ``connect`` endpoints (clients dial it: those links are theirs to check).

A link to anyone else is refused with one line (:class:`~pipeline.errors.BusError`): at
open, the session is closed and the error raised; later, the session is closed and the
error handed to whoever watches it (:func:`watch`: a node puts it in its ``errors``,
which ends its command), so nothing more is sent to an impostor.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from typing import Callable, Iterable

from pipeline.bus.audit import admin_links
from pipeline.errors import BusError

log = logging.getLogger("qradar.bus")

#: the admin space is polled this often for new links where zenoh has no link events (s)
POLL_S = 0.5

_lock = threading.Lock()
_checks: dict[str, "RouterCheck"] = {}  # zenoh id of a session -> its check


def _host_port(locator: str) -> tuple[str, int] | None:
    """(host, port) of ``tls/HOST:PORT`` (IPv6 in brackets; metadata after ? or # cut)."""
    proto, _, rest = locator.partition("/")
    rest = rest.split("?", 1)[0].split("#", 1)[0]
    host, _, port = rest.rpartition(":")
    if not proto or not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def _addresses(endpoint: str) -> set[tuple[str, int]]:
    """Every (address, port) a connect endpoint resolves to."""
    hp = _host_port(endpoint)
    if hp is None:
        return set()
    try:
        infos = socket.getaddrinfo(hp[0], hp[1], type=socket.SOCK_STREAM)
    except OSError:
        return {hp}
    return {(info[4][0], hp[1]) for info in infos} | {hp}


class RouterCheck:
    """The check of one session (see the module's docstring): ``routers``, the common
    names a peer may have (the policy's router identities); ``dialled``, the addresses
    of the session's connect endpoints (None: every TLS link is checked)."""

    def __init__(self, session, routers: Iterable[str], dialled: set[tuple[str, int]] | None, where: str):
        self.session = session
        self.key = str(session.zid())
        self.routers = frozenset(routers)
        self.dialled = dialled
        self.where = where
        self.error: BusError | None = None
        self._watchers: list[Callable[[BusError], None]] = []
        self._listener = None

    def judge(self, dst: str, common_name: str | None) -> BusError | None:
        """The error a link to ``dst`` whose peer's certificate is ``common_name`` makes
        (None: a link this check lets be)."""
        if not dst.startswith("tls/"):
            return None  # a local unix socket: file permissions guard it
        if self.dialled is not None and _host_port(dst) not in self.dialled:
            return None  # a client that dialled this router
        if common_name in self.routers:
            return None
        names = ", ".join(sorted(self.routers)) or "none"
        return BusError(f"--secure {self.where}: the peer at {dst} presents the certificate of {common_name!r}, "
                        f"not a router identity of the policy ({names}): refused (an impostor, or a certificate "
                        f"issued for another role that names this host; `qradar security check DIR` lists them)")

    def links(self) -> list[tuple[str, str | None]]:
        """(destination, peer's common name) of each open link of the session."""
        info = self.session.info
        if hasattr(info, "links"):
            return [(str(link.dst), link.auth_identifier) for link in info.links()]
        # a zenoh-python without SessionInfo.links: the admin space says the same
        return [(str(link.get("dst", "")), link.get("auth_identifier")) for link in admin_links(self.session)]

    def check_now(self) -> None:
        """Raise the error of the first link refused (the session is closed first)."""
        for dst, cn in self.links():
            error = self.judge(dst, cn)
            if error is not None:
                self.error = error
                self._close()
                raise error

    def start(self) -> "RouterCheck":
        """Check every link made from now on, in zenoh's callback (or a polling thread)."""
        info = self.session.info
        if hasattr(info, "declare_link_events_listener"):
            self._listener = info.declare_link_events_listener(self._on_event, history=True)
        else:
            threading.Thread(target=self._poll, name="router-check", daemon=True).start()
        return self

    def _on_event(self, event) -> None:
        if "DELETE" not in str(event.kind):
            self._refuse(self.judge(str(event.link.dst), event.link.auth_identifier))

    def _poll(self) -> None:
        while self.error is None:
            time.sleep(POLL_S)
            try:
                if self.session.is_closed():
                    return
                for dst, cn in self.links():
                    self._refuse(self.judge(dst, cn))
            except Exception:  # the session closed under us
                return

    def _refuse(self, error: BusError | None) -> None:
        """A link refused after the session opened: said once (by whoever watches, who
        raises it, else in the log), and the session closed in a thread of its own."""
        with _lock:
            if error is None or self.error is not None:
                return
            self.error = error
            watchers = list(self._watchers)
        if not watchers:
            log.error("%s", error)
        for watcher in watchers:
            watcher(error)
        threading.Thread(target=self._close, name="router-check-close", daemon=True).start()

    def _close(self) -> None:
        try:
            if not self.session.is_closed():
                self.session.close()
        except Exception:  # closed meanwhile
            pass


def _forget_closed() -> None:
    """Drop the checks of sessions closed since, but those that refused a link (call with
    _lock held)."""
    for key, check in list(_checks.items()):
        try:
            closed = check.session.is_closed()
        except Exception:
            closed = True
        if closed and check.error is None:
            del _checks[key]


def install(session, bus) -> None:
    """The check of a session opened from ``bus`` under ``--secure``: its links now
    (BusError, the session closed, when one is refused), then every later one."""
    secure = bus.secure
    own = secure.policy.get(secure.identity)
    routers = [i.name for i in secure.policy.identities if i.role == "router"]
    dialled = None
    if own is not None and own.role == "router":
        if not bus.connect:
            return  # a router that dials no one: its clients check it
        dialled = set().union(*(_addresses(ep) for ep in bus.connect))
    check = RouterCheck(session, routers, dialled, str(secure.directory))
    check.check_now()
    with _lock:
        _forget_closed()
        _checks[check.key] = check
    check.start()


def watch(session, on_refused: Callable[[BusError], None]) -> None:
    """Call ``on_refused`` with the error when the check of ``session`` (if it has one)
    refuses a link; at once if it did already."""
    try:
        key = str(session.zid())
    except Exception:
        return
    with _lock:
        check = _checks.get(key)
        if check is None:
            return
        if check.error is None:
            check._watchers.append(on_refused)
            return
    on_refused(check.error)
