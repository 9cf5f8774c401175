"""Helpers shared by the zenoh tests: bounded waits, a collecting subscriber, a free port."""

import socket
import threading
import time


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(pred, timeout_s=20.0, what="condition"):
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, f"timed out after {timeout_s} s waiting for {what}"
        time.sleep(0.05)


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
