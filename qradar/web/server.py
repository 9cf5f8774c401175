"""The web view's HTTP server: the standard library's ``http.server``, a thread per
connection.

The live data reach the page as Server-Sent Events, not over a WebSocket: the page only
listens (a recording's play, pause and seek are small POSTs), SSE is plain HTTP that
``http.server`` serves as it is (no handshake, framing or masking to write and get
wrong), and the browser's ``EventSource`` reconnects by itself when the view restarts.

Routes: ``GET /`` the page; ``GET /static/<file>`` its script, style and the plotting
library (package data, nothing of the stream, so no token); ``GET /events`` the event
stream; ``POST /control`` a recording's play, pause and seek (JSON). With a token, ``/``,
``/events`` and ``/control`` need ``?token=...`` (compared in constant time). A request
whose ``Host`` is not this server's (a DNS-rebinding page in the same browser) is refused
when the server listens on a loopback address."""

from __future__ import annotations

import hmac
import ipaddress
import json
import logging
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Callable
from urllib.parse import parse_qs, urlsplit

from ..liveview import ViewError
from .hub import EventHub, sse

log = logging.getLogger("qradar.web")

#: a page's connection with nothing to send gets a comment this often (s), and its counters
KEEPALIVE_S = 1.0
#: a connection that takes no bytes for this long is closed (s)
SOCKET_TIMEOUT_S = 10.0
#: the browser waits this long before it connects again after a lost connection (ms)
RETRY_MS = 500
#: the largest request body (/control), bytes
MAX_BODY = 1024
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".txt": "text/plain; charset=utf-8",
                 ".svg": "image/svg+xml", ".png": "image/png"}
HEADERS = {"X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer", "X-Frame-Options": "DENY",
           "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'; "
                                      "connect-src 'self'; frame-ancestors 'none'"}


def static_files() -> dict[str, tuple[bytes, str]]:
    """The page's files shipped in the package (``qradar/web/static``): path -> (bytes,
    content type). ViewError when they are missing (an install without its package data)."""
    root = resources.files("qradar.web") / "static"
    out: dict[str, tuple[bytes, str]] = {}

    def walk(node, prefix: str) -> None:
        for entry in node.iterdir():
            name = f"{prefix}{entry.name}"
            if entry.is_dir():
                walk(entry, name + "/")
            else:
                suffix = "." + entry.name.rsplit(".", 1)[-1] if "." in entry.name else ".txt"  # LICENSE
                if suffix in CONTENT_TYPES:
                    out[name] = (entry.read_bytes(), CONTENT_TYPES[suffix])

    try:
        walk(root, "")
    except (FileNotFoundError, NotADirectoryError):
        pass
    if "index.html" not in out:
        raise ViewError("the web page's files are not installed (qradar/web/static/index.html is missing: "
                        "reinstall qradar with its package data)")
    return out


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


class WebServer(ThreadingHTTPServer):
    """Serves the page, the event stream of ``hub`` and, for a recording, ``control``
    (action, position_s -> the player's state; None: live, no control)."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, host: str, port: int, hub: EventHub, token: str | None = None,
                 control: Callable[[str, float | None], dict] | None = None):
        self.address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.hub, self.token, self.control = hub, token, control
        self.files = static_files()
        self.stopping = threading.Event()
        self.refused_token = 0  # requests without the right token
        self.refused_host = 0
        try:
            super().__init__((host, port), Handler)
        except OSError as exc:
            raise ViewError(f"cannot serve the web view on {host}:{port}: {exc.strerror or exc}") from None
        self.port = self.server_address[1]
        self.loopback = is_loopback(host)
        names = {host, "localhost", "127.0.0.1", "::1"} if self.loopback else set()
        self.allowed_hosts = {f"{n}:{self.port}" for n in names} | {f"[{n}]:{self.port}" for n in names if ":" in n}

    def stop(self) -> None:
        """Close every page's stream, stop serving and close the socket."""
        self.stopping.set()
        self.hub.close()
        self.shutdown()
        self.server_close()


class Handler(BaseHTTPRequestHandler):
    server: WebServer
    timeout = SOCKET_TIMEOUT_S
    server_version = "qradar-view"
    sys_version = ""

    def log_message(self, format: str, *args) -> None:  # noqa: A002 (the base class's name)
        log.debug("%s %s", self.address_string(), format % args)

    def _send(self, status: int, body: bytes, content_type: str = "text/plain; charset=utf-8",
              cache: str = "no-store") -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", cache)
        for k, v in HEADERS.items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _allowed(self, needs_token: bool) -> bool:
        """The Host is this server's (on loopback) and, where needed, the token is given."""
        srv = self.server
        if srv.loopback and self.headers.get("Host", "") not in srv.allowed_hosts:
            srv.refused_host += 1
            self._send(HTTPStatus.FORBIDDEN, b"qradar view: unexpected Host header\n")
            return False
        if needs_token and srv.token is not None:
            given = parse_qs(urlsplit(self.path).query).get("token", [""])[0]
            if not hmac.compare_digest(given.encode(), srv.token.encode()):
                srv.refused_token += 1
                self._send(HTTPStatus.UNAUTHORIZED, b"qradar view: this view needs its token: open the URL it "
                           b"printed (http://HOST:PORT/?token=...)\n")
                return False
        return True

    def do_HEAD(self) -> None:  # noqa: N802 (http.server's names)
        if urlsplit(self.path).path == "/events":  # what a GET would answer, without starting a stream
            if self._allowed(needs_token=True):
                self._send(HTTPStatus.OK, b"", "text/event-stream")
        else:
            self.do_GET()

    def do_GET(self) -> None:  # noqa: N802
        path = urlsplit(self.path).path
        if path in ("/", "/index.html"):
            if self._allowed(needs_token=True):
                body, ctype = self.server.files["index.html"]
                self._send(HTTPStatus.OK, body, ctype)
        elif path.startswith("/static/"):
            if self._allowed(needs_token=False):
                found = self.server.files.get(path[len("/static/"):])
                if found is None:
                    self._send(HTTPStatus.NOT_FOUND, b"not found\n")
                else:
                    self._send(HTTPStatus.OK, found[0], found[1], cache="max-age=60")
        elif path == "/events":
            if self._allowed(needs_token=True):
                self._events()
        else:
            self._send(HTTPStatus.NOT_FOUND, b"not found\n")

    def do_POST(self) -> None:  # noqa: N802
        if urlsplit(self.path).path != "/control":
            self._send(HTTPStatus.NOT_FOUND, b"not found\n")
            return
        if not self._allowed(needs_token=True):
            return
        if self.server.control is None:
            self._send(HTTPStatus.CONFLICT, b"a live view has no play, pause or seek (only --recording has)\n")
            return
        if self.headers.get_content_type() != "application/json":  # a cross-site form cannot post it
            self._send(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, b"control takes application/json\n")
            return
        try:
            length = int(self.headers.get("Content-Length", "0"))
            if not 0 < length <= MAX_BODY:
                raise ValueError(f"a body of 1 to {MAX_BODY} bytes, got {length}")
            req = json.loads(self.rfile.read(length))
            if not isinstance(req, dict):
                raise ValueError("a JSON object {\"action\": ..., \"position_s\": ...}")
            state = self.server.control(req.get("action"), req.get("position_s"))
        except (ValueError, TypeError) as exc:
            self._send(HTTPStatus.BAD_REQUEST, f"control: {exc}\n".encode())
            return
        self._send(HTTPStatus.OK, json.dumps(state).encode(), "application/json")

    def _events(self) -> None:
        """The event stream: ``hello``, the latest events, then every new one; a ``stats``
        event (this page's events sent and dropped) and a keep-alive each second."""
        hub = self.server.hub
        client = hub.connect()
        if client is None:
            self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"qradar view: too many pages open\n")
            return
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            for k, v in HEADERS.items():
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(b"retry: %d\n\n" % RETRY_MS)
            next_stats = time.monotonic() + KEEPALIVE_S
            while not self.server.stopping.is_set():
                frames = client.take(max(next_stats - time.monotonic(), 0.0))
                if frames is None:
                    break
                if time.monotonic() >= next_stats:
                    frames.append(sse("stats", {"sent": client.sent, "dropped": client.dropped}))
                    next_stats = time.monotonic() + KEEPALIVE_S
                if frames:
                    self.wfile.write(b"".join(frames))
                    self.wfile.flush()
        except OSError:  # the page went away (BrokenPipe, ConnectionReset, a timeout)
            pass
        finally:
            hub.disconnect(client)
            self.close_connection = True
