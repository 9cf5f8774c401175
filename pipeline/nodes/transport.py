"""How a node reaches the bus: the :class:`Transport` protocol, its zenoh adapter
(:class:`ZenohTransport`, what every command runs) and an in-memory transport
(:class:`MemoryTransport`: nodes of one process that share it hear each other's puts,
delivered in the putting thread; for tests of what a node does with its input).

A transport declares liveliness tokens, subscribers (a callback per message, or a
bounded FIFO the node drains: ``declare_pull_subscriber``) and publishers, puts, and
closes. A message is a :class:`Sample`: ``str(sample.key_expr)`` is its key,
``len(sample.payload)`` its length (known before any copy) and
``sample.payload.to_bytes()`` its bytes. ``drop=True`` marks messages a slow network
may lose (health), the others wait for room (zenoh's ``CongestionControl``).
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Callable, Protocol

import zenoh

OCTETS = "application/octet-stream"
#: how long undeclaring a callback subscriber waits for zenoh's callback thread to hand over
#: the messages it already held (s)
DRAIN_S = 5.0
#: what a transport raises when a declaration, a put or a drained input fails or is closed
TransportError = zenoh.ZError


class Payload(Protocol):
    def __len__(self) -> int: ...

    def to_bytes(self) -> bytes: ...


class Sample(Protocol):
    """One message: ``key_expr`` (its str is the key) and ``payload``."""

    @property
    def key_expr(self) -> object: ...

    @property
    def payload(self) -> Payload: ...


class Declared(Protocol):
    """A token, subscriber or publisher: undeclared when no longer needed."""

    def undeclare(self) -> None: ...


class Publisher(Declared, Protocol):
    def put(self, payload: bytes) -> None: ...


class PullSubscriber(Declared, Protocol):
    """A subscriber whose messages wait in a bounded FIFO: ``try_recv`` gives the next
    one or None; once undeclared it still gives what it holds, then raises TransportError."""

    def try_recv(self) -> Sample | None: ...


class Transport(Protocol):
    def declare_token(self, key: str) -> Declared: ...

    def declare_subscriber(self, key: str, callback: Callable[[Sample], None]) -> Declared: ...

    def declare_pull_subscriber(self, key: str, capacity: int) -> PullSubscriber: ...

    def declare_publisher(self, key: str, encoding: str, drop: bool) -> Publisher: ...

    def put(self, key: str, payload: bytes, encoding: str, drop: bool) -> None: ...

    def close(self) -> None: ...


def _congestion(drop: bool) -> zenoh.CongestionControl:
    return zenoh.CongestionControl.DROP if drop else zenoh.CongestionControl.BLOCK


class _ZenohPull:
    """A zenoh subscriber with a FifoChannel handler (which still yields what it holds
    after undeclare, then raises ZError)."""

    __slots__ = ("_sub", "try_recv")

    def __init__(self, sub: zenoh.Subscriber):
        self._sub = sub
        self.try_recv = sub.handler.try_recv

    def undeclare(self) -> None:
        self._sub.undeclare()


class ZenohTransport:
    """A :class:`Transport` over a zenoh session (the session's owner closes it)."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self._encodings: dict[str, zenoh.Encoding] = {}

    def _encoding(self, encoding: str) -> zenoh.Encoding:
        enc = self._encodings.get(encoding)
        if enc is None:
            enc = self._encodings[encoding] = zenoh.Encoding(encoding)
        return enc

    def declare_token(self, key: str) -> Declared:
        return self.session.liveliness().declare_token(key)

    def declare_subscriber(self, key: str, callback: Callable[[Sample], None]) -> Declared:
        return DrainingSubscriber(self.session, key, callback)

    def declare_pull_subscriber(self, key: str, capacity: int) -> PullSubscriber:
        return _ZenohPull(self.session.declare_subscriber(key, zenoh.handlers.FifoChannel(capacity)))

    def declare_publisher(self, key: str, encoding: str, drop: bool) -> Publisher:
        return self.session.declare_publisher(key, encoding=self._encoding(encoding),
                                              congestion_control=_congestion(drop))

    def put(self, key: str, payload: bytes, encoding: str, drop: bool) -> None:
        self.session.put(key, payload, encoding=self._encoding(encoding), congestion_control=_congestion(drop))

    def close(self) -> None:
        self.session.close()


class Audience:
    """Whether any subscriber, anywhere, matched one of ``keys`` at some time since this was
    made (zenoh's matching status of a publisher that never puts, on each key; a
    :class:`MemoryTransport`: its subscribers when asked): a producer's way to tell "my
    messages went to nobody" (another --prefix, no router in common) from a quiet consumer.
    :meth:`close` undeclares its publishers (a session's close has done it too)."""

    def __init__(self, transport: "Transport", keys: list[str]):
        self.heard, self.keys = threading.Event(), keys
        self._transport, self._declared = transport, []
        session = getattr(transport, "session", None)
        if session is None:
            return
        for key in keys:
            pub = session.declare_publisher(key)
            self._declared += [pub.declare_matching_listener(self._status), pub]
            if pub.matching_status.matching:
                self.heard.set()

    def _status(self, status) -> None:
        if status.matching:
            self.heard.set()

    def matched(self) -> bool:
        if not self.heard.is_set() and isinstance(self._transport, MemoryTransport):
            if self._transport.subscribed(self.keys):
                self.heard.set()
        return self.heard.is_set()

    def close(self) -> None:
        for d in self._declared:
            d.undeclare()
        self._declared = []


class DrainingSubscriber:
    """A zenoh subscriber with a Python callback, which zenoh runs on a callback thread of its
    own, fed by a queue: a message put before :meth:`undeclare` may still wait there when
    zenoh's undeclare returns. This one's undeclare returns once that thread has handed over
    every message it held (zenoh then calls the handler's ``drop``), so a node that stops
    after its producers has seen all they put."""

    def __init__(self, session: zenoh.Session, key: str, callback: Callable[[Sample], None]):
        self._drained = threading.Event()
        self._sub = session.declare_subscriber(key, zenoh.handlers.Callback(callback, self._drained.set))

    def undeclare(self, timeout_s: float = DRAIN_S) -> bool:
        """Undeclare; whether the callback had every held message within ``timeout_s`` (s)."""
        self._sub.undeclare()
        return self._drained.wait(timeout_s)


def as_transport(session: zenoh.Session | Transport) -> Transport:
    """A zenoh session wrapped in a :class:`ZenohTransport`; a transport as it is."""
    return ZenohTransport(session) if isinstance(session, zenoh.Session) else session


class MemoryPayload(bytes):
    """The bytes of an in-memory message (``to_bytes`` as zenoh's ZBytes has it)."""

    def to_bytes(self) -> bytes:
        return bytes(self)


@dataclass(frozen=True, slots=True)
class MemorySample:
    key_expr: str
    payload: MemoryPayload
    encoding: str


class _Declaration:
    """A token, subscriber or publisher of a :class:`MemoryTransport`."""

    def __init__(self, transport: "MemoryTransport", key: str):
        self.transport, self.key = transport, key

    def undeclare(self) -> None:
        self.transport._undeclare(self)


class _MemorySubscriber(_Declaration):
    def __init__(self, transport: "MemoryTransport", key: str, callback: Callable[[Sample], None]):
        super().__init__(transport, key)
        self.expr = zenoh.KeyExpr(key)
        self.deliver = callback


class _MemoryPull(_MemorySubscriber):
    """A bounded FIFO: a put finding it full waits for room (drop=False) or is lost."""

    def __init__(self, transport: "MemoryTransport", key: str, capacity: int):
        super().__init__(transport, key, self._offer)
        self._fifo: deque[MemorySample] = deque()
        self._capacity = capacity
        self._cond = threading.Condition()
        self._closed = False

    def _offer(self, sample: MemorySample, drop: bool = False) -> None:
        with self._cond:
            while len(self._fifo) >= self._capacity and not self._closed:
                if drop:
                    return
                self._cond.wait(0.1)
            if not self._closed:
                self._fifo.append(sample)

    def try_recv(self) -> MemorySample | None:
        with self._cond:
            if self._fifo:
                sample = self._fifo.popleft()
                self._cond.notify_all()
                return sample
            if self._closed:
                raise TransportError(f"subscriber {self.key} is undeclared")
            return None

    def undeclare(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        super().undeclare()


class _MemoryPublisher(_Declaration):
    def __init__(self, transport: "MemoryTransport", key: str, encoding: str, drop: bool):
        super().__init__(transport, key)
        self.encoding, self.drop = encoding, drop

    def put(self, payload: bytes) -> None:
        self.transport.put(self.key, payload, self.encoding, self.drop)


class MemoryTransport:
    """A :class:`Transport` inside one process: a put reaches, in the putting thread,
    every subscriber of this transport whose key expression intersects the key (zenoh's
    own key-expression rules). ``tokens``: the keys of the liveliness tokens declared."""

    def __init__(self):
        self._lock = threading.Lock()
        self._subscribers: list[_MemorySubscriber] = []
        self._declared: set[_Declaration] = set()
        self._matches: dict[str, list[_MemorySubscriber]] = {}  # key -> its subscribers
        self.closed = False

    @property
    def tokens(self) -> list[str]:
        with self._lock:
            return sorted(d.key for d in self._declared if type(d) is _Declaration)

    def _declare(self, d: _Declaration) -> _Declaration:
        with self._lock:
            if self.closed:
                raise TransportError(f"declaration of {d.key} on a closed transport")
            self._declared.add(d)
            if isinstance(d, _MemorySubscriber):
                self._subscribers.append(d)
                self._matches.clear()
        return d

    def _undeclare(self, d: _Declaration) -> None:
        with self._lock:
            self._declared.discard(d)
            if d in self._subscribers:
                self._subscribers.remove(d)
                self._matches.clear()

    def subscribed(self, keys: list[str]) -> bool:
        """Whether a subscriber of this transport matches one of ``keys`` now."""
        exprs = [zenoh.KeyExpr(k) for k in keys]
        with self._lock:
            return any(sub.expr.intersects(e) for sub in self._subscribers for e in exprs)

    def declare_token(self, key: str) -> Declared:
        return self._declare(_Declaration(self, key))

    def declare_subscriber(self, key: str, callback: Callable[[Sample], None]) -> Declared:
        return self._declare(_MemorySubscriber(self, key, callback))

    def declare_pull_subscriber(self, key: str, capacity: int) -> PullSubscriber:
        return self._declare(_MemoryPull(self, key, capacity))

    def declare_publisher(self, key: str, encoding: str = OCTETS, drop: bool = False) -> Publisher:
        return self._declare(_MemoryPublisher(self, key, encoding, drop))

    def put(self, key: str, payload: bytes, encoding: str = OCTETS, drop: bool = False) -> None:
        with self._lock:
            if self.closed:
                raise TransportError(f"put on {key}: the transport is closed")
            subs = self._matches.get(key)
            if subs is None:
                expr = zenoh.KeyExpr(key)
                subs = self._matches[key] = [s for s in self._subscribers if s.expr.intersects(expr)]
        sample = MemorySample(key, MemoryPayload(payload), encoding)
        for s in subs:
            if isinstance(s, _MemoryPull):
                s._offer(sample, drop)
            else:
                s.deliver(sample)

    def close(self) -> None:
        with self._lock:
            self.closed = True
            pulls = [s for s in self._subscribers if isinstance(s, _MemoryPull)]
        for s in pulls:
            s.undeclare()
