"""Memory stays bounded over restarts: a publisher started again and again against one
long-running router and subscriber (each a process of its own) does not grow them. With
zenoh's shared-memory transport on (its default), each new publisher session left a
16 MB pool mapped in the router and the subscriber for as long as they ran."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from zenoh_helpers import free_port, rss_mb, wait_port

QRADAR = [sys.executable, "-m", "qradar"]
RESTARTS = 20


@pytest.mark.slow
def test_publisher_restarts_do_not_grow_the_router_or_the_subscriber():
    port = free_port()
    client = ["--mode", "client", "--connect", f"tcp/127.0.0.1:{port}"]
    router = subprocess.Popen([*QRADAR, "router", "--listen", f"tcp/127.0.0.1:{port}"],
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    quantize = None
    try:
        wait_port(port)
        quantize = subprocess.Popen([*QRADAR, "quantize", *client], stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

        def source() -> None:
            out = subprocess.run([*QRADAR, "source", "--frames", "5", "--rate", "50", *client],
                                 capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
            assert out.returncode == 0 and '"frames_out": 5' in out.stdout, out.stderr[-2000:]

        source()  # the first session warms every cache up
        time.sleep(0.5)
        before = rss_mb(router.pid), rss_mb(quantize.pid)
        for _ in range(RESTARTS):
            source()
        time.sleep(0.5)
        after = rss_mb(router.pid), rss_mb(quantize.pid)
        assert quantize.poll() is None and router.poll() is None
    finally:
        for p in (quantize, router):
            if p is not None:
                p.terminate()
                p.wait(20)
    growth = [round(a - b, 1) for a, b in zip(after, before)]
    print(f"RSS growth over {RESTARTS} restarts (router, quantize): {growth} MB")
    assert max(growth) <= 10.0, f"RSS growth over {RESTARTS} publisher restarts (router, quantize): {growth} MB"
