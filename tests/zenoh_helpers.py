"""Helpers shared by the tests (not fixtures; those are in conftest.py): a bounded wait, a
collecting zenoh subscriber, a free loopback port for code that needs one outside a fixture."""

import socket
import threading
import time

import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(pred, timeout_s=20.0, what="condition", poll_s=0.05):
    """Poll ``pred`` every ``poll_s`` s until it is true; fail the test once ``timeout_s`` has
    passed or after ``timeout_s / poll_s + 1`` polls, whichever comes first."""
    deadline = time.monotonic() + timeout_s
    for _ in range(int(timeout_s / poll_s) + 1):
        if pred():
            return
        if time.monotonic() >= deadline:
            break
        time.sleep(poll_s)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what}", pytrace=False)


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
