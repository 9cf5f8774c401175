"""Memory stays bounded over restarts: a publisher started again and again against one
long-running router and its subscribers (each a process of its own) does not grow them.
With zenoh's shared-memory transport on (its default), each new publisher session left a
16 MB pool mapped in the router and the subscriber for as long as they ran. Held since:
20 restarts grew the router, quantize and localize by 0.2-0.3 MB; the test makes 10 (the
16 MB a restart would be 160 MB; MAX_GROWTH_MB allows for a busy host's noise)."""

from __future__ import annotations

import subprocess
import time

import pytest

from zenoh_helpers import QRADAR, Collector, alive_nodes, free_port, rss_mb, wait_port, wait_until

pytestmark = pytest.mark.measure

RESTARTS = 10
#: the most RSS a long-running process may grow by over RESTARTS publisher restarts (held: 0.2-0.3 MB over 20)
MAX_GROWTH_MB = 3.0


def settled(pid: int, timeout_s: float = 20.0) -> None:
    """Until the RSS of ``pid`` moves by less than 0.2 MB over half a second (bounded)."""
    deadline, last = time.monotonic() + timeout_s, rss_mb(pid)
    while time.monotonic() < deadline:
        time.sleep(0.5)
        now = rss_mb(pid)
        if abs(now - last) < 0.2:
            return
        last = now


@pytest.mark.slow
def test_publisher_restarts_do_not_grow_the_router_or_the_subscriber(connect_when_ready):
    port = free_port()
    client = ["--mode", "client", "--connect", f"tcp/127.0.0.1:{port}"]
    router = subprocess.Popen([*QRADAR, "router", "--listen", f"tcp/127.0.0.1:{port}"],
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    quantize = localize = None
    try:
        wait_port(port)
        quantize = subprocess.Popen([*QRADAR, "quantize", *client], stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        localize = subprocess.Popen([*QRADAR, "localize", "--K", "1", *client], stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

        def source(frames: int = 5, rate: float = 50.0) -> None:
            out = subprocess.run([*QRADAR, "source", "--frames", str(frames), "--rate", str(rate), *client],
                                 capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
            assert out.returncode == 0 and f'"frames_out": {frames}' in out.stdout, out.stderr[-2000:]

        # the warm-up must reach the nodes: a node subscribes only once its kernels are loaded (the localizer's
        # cml kernels: 1.5 s idle, 3.5 s on a busy host), then declares its liveliness token. Frames published
        # before are lost, and the localizer's first decodes (~12 MB once: its worker's first frame, its first
        # batches) came after the baseline, read as growth
        session = connect_when_ready(f"tcp/127.0.0.1:{port}", timeout_s=30, mode="client")
        wait_until(lambda: {"quantize", "localize"} <= set(alive_nodes(session)), 60, "the quantize and localize nodes up")
        targets = Collector(session, "radar/*/targets")
        for _ in range(3):  # the first sessions warm every cache up
            source()
        # and a burst: a node takes what its queue holds as one batch, and its arrays' memory is that of the
        # largest batch so far (a busy host batches a restart's 5 frames)
        source(60, 1000.0)
        wait_until(lambda: len(targets.of("/targets")) >= 60, 60,
                   lambda: f"the warm-up's targets (the localizer decoded {len(targets.of('/targets'))} frames)")
        targets.sub.undeclare()
        settled(localize.pid)
        before = rss_mb(router.pid), rss_mb(quantize.pid), rss_mb(localize.pid)
        for _ in range(RESTARTS):
            source()
        settled(localize.pid)
        after = rss_mb(router.pid), rss_mb(quantize.pid), rss_mb(localize.pid)
        assert quantize.poll() is None and localize.poll() is None and router.poll() is None
    finally:
        for p in (localize, quantize, router):
            if p is not None:
                p.terminate()
                p.wait(20)
    growth = [round(a - b, 1) for a, b in zip(after, before)]
    print(f"RSS growth over {RESTARTS} restarts (router, quantize, localize): {growth} MB")
    assert max(growth) <= MAX_GROWTH_MB, \
        f"RSS growth over {RESTARTS} publisher restarts (router, quantize, localize): {growth} MB"
