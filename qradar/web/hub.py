"""The events of a view on their way to every open page: each event encoded once as a
Server-Sent Event, a bounded queue per page (in events and in bytes: a page that reads
slower than the view writes loses its oldest events, counted, and never grows the view's
memory), and the latest event of each kind and sensor kept for a page that opens later."""

from __future__ import annotations

import json
import threading
from collections import deque

#: events a page's queue holds at most, and bytes
CLIENT_EVENTS = 256
CLIENT_BYTES = 4 << 20
#: pages served at once at most (one more is refused with 503)
MAX_CLIENTS = 8
#: the latest events kept for pages that open later, at most (kind, sensor[, node]) keys
MAX_LATEST = 4096


def sse(kind: str, data: dict) -> bytes:
    """``event: <kind>`` and one ``data:`` line of compact JSON (no NaN), as an SSE frame."""
    return b"event: %s\ndata: %s\n\n" % (kind.encode(), json.dumps(data, separators=(",", ":"),
                                                                   allow_nan=False).encode())


class Client:
    """One page's queue: :meth:`offer` never blocks (beyond ``max_events`` or ``max_bytes``
    the oldest events go, counted in ``dropped``); :meth:`take` waits for events."""

    def __init__(self, max_events: int = CLIENT_EVENTS, max_bytes: int = CLIENT_BYTES):
        self.max_events, self.max_bytes = max_events, max_bytes
        self._queue: deque[bytes] = deque()
        self._bytes = 0
        self._cond = threading.Condition()
        self.closed = False
        self.dropped = 0  # events dropped, oldest first, because the page read too slowly
        self.sent = 0  # events handed to the connection

    def offer(self, frame: bytes) -> None:
        with self._cond:
            if self.closed:
                return
            self._queue.append(frame)
            self._bytes += len(frame)
            while len(self._queue) > self.max_events or (self._bytes > self.max_bytes and len(self._queue) > 1):
                self._bytes -= len(self._queue.popleft())
                self.dropped += 1
            self._cond.notify()

    def take(self, timeout_s: float) -> list[bytes] | None:
        """Every queued event (waiting up to ``timeout_s`` for one; [] after it), or None
        once the client is closed."""
        with self._cond:
            if not self._queue and not self.closed:
                self._cond.wait(timeout_s)
            if self.closed:
                return None
            frames = list(self._queue)
            self._queue.clear()
            self._bytes = 0
            self.sent += len(frames)
            return frames

    @property
    def queued(self) -> tuple[int, int]:
        """(events, bytes) waiting."""
        with self._cond:
            return len(self._queue), self._bytes

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._queue.clear()
            self._bytes = 0
            self._cond.notify_all()


class EventHub:
    """The view's events to its pages. :meth:`publish` encodes an event once and offers it
    to every page; with a ``key`` it is also kept as the latest of its kind (a page that
    connects gets ``hello`` and then these, in the order they were last published)."""

    def __init__(self, max_clients: int = MAX_CLIENTS, client_events: int = CLIENT_EVENTS,
                 client_bytes: int = CLIENT_BYTES):
        self.max_clients, self.client_events, self.client_bytes = max_clients, client_events, client_bytes
        self._lock = threading.Lock()
        self._clients: list[Client] = []
        self._latest: dict[tuple, bytes] = {}
        self._hello: dict = {}
        self.published = 0
        self.refused = 0  # connections beyond max_clients
        self.connections = 0
        self._gone_dropped = 0  # the drops of pages that closed
        self._closed = False

    def set_hello(self, data: dict) -> None:
        """What every page gets first (the view's configuration)."""
        with self._lock:
            self._hello = dict(data)

    def publish(self, kind: str, data: dict, key: tuple | None = None) -> int:
        """Offer the event to every page (and keep it as the latest under ``key``); its size, bytes."""
        frame = sse(kind, data)
        with self._lock:
            if key is not None:
                self._latest.pop(key, None)  # re-inserted last: the order of the latest events
                if len(self._latest) >= MAX_LATEST:
                    self._latest.pop(next(iter(self._latest)))
                self._latest[key] = frame
            clients = list(self._clients)
            self.published += 1
        for c in clients:
            c.offer(frame)
        return len(frame)

    def reset(self, data: dict) -> None:
        """Forget the latest events (a recording was sought) and tell the pages (``reset``)."""
        with self._lock:
            self._latest.clear()
        self.publish("reset", data)

    def connect(self) -> Client | None:
        """A new page's queue, holding ``hello`` and the latest events; None when
        ``max_clients`` pages are open (or the hub is closed)."""
        with self._lock:
            if self._closed or len(self._clients) >= self.max_clients:
                self.refused += 1
                return None
            client = Client(self.client_events, self.client_bytes)
            client.offer(sse("hello", self._hello))
            for frame in self._latest.values():
                client.offer(frame)
            self._clients.append(client)
            self.connections += 1
            return client

    def disconnect(self, client: Client) -> None:
        client.close()
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)
                self._gone_dropped += client.dropped

    def close(self) -> None:
        """Close every page's queue (their connections end) and refuse new ones."""
        with self._lock:
            self._closed = True
            clients = list(self._clients)
        for c in clients:
            c.close()

    def totals(self) -> dict:
        """Pages open now, connections in all, refused, events published, and events
        dropped for slow pages (open or closed)."""
        with self._lock:
            clients = list(self._clients)
            out = {"clients": len(clients), "connections": self.connections, "refused": self.refused,
                   "published": self.published}
            gone = self._gone_dropped
        out["dropped_for_slow_clients"] = gone + sum(c.dropped for c in clients)
        return out
