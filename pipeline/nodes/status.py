"""What a stand-alone node says while it runs: a start line (its zenoh mode, where it
listens and connects, the keys it reads and writes) and a status line every few seconds
(rates, sensors, losses; the localizer's last targets), unless the command is ``--quiet``."""

from __future__ import annotations

import sys
import threading
import time
from typing import TextIO

from pipeline.nodes.counters import ERROR_KINDS

#: a stand-alone node's status line comes this often, s
STATUS_PERIOD_S = 5.0
#: what each kind of node writes (``{p}``: the key prefix)
OUTPUTS = {"source": "{p}/<sensor>/raw (or quantized)", "quantize": "{p}/<sensor>/quantized",
           "localize": "{p}/<sensor>/targets (and tracks)", "record": "MCAP files"}


def start_line(node) -> str:
    """``qradar <node>: zenoh <mode>, listening on ..., connecting to ...; reads KEY; writes KEY``."""
    bus = node.bus
    listen = bus.listen_endpoints()
    parts = [f"zenoh {bus.mode}", f"listening on {', '.join(listen)}" if listen else "listening nowhere",
             f"connecting to {', '.join(bus.connect)}" if bus.connect else "connecting to no endpoint"]
    sub = node.subscription() if hasattr(node, "subscription") else None
    keys = ([f"reads {sub}"] if sub else []) + [f"writes {OUTPUTS.get(node.name, 'its topics').format(p=bus.prefix)}"]
    return f"qradar {node.name}: {', '.join(parts)}; {'; '.join(keys)}; a status line every {STATUS_PERIOD_S:g} s"


def status_line(node, before: dict[str, int], now: dict[str, int], seconds: float) -> str:
    """Rates over ``seconds`` between two :meth:`totals`, sensors, losses in all, and the
    localizer's last targets."""
    rate_in = (now.get("frames_in", 0) - before.get("frames_in", 0)) / max(seconds, 1e-9)
    rate_out = (now.get("frames_out", 0) - before.get("frames_out", 0)) / max(seconds, 1e-9)
    losses = {k: now.get(k, 0) for k in ("drops", "frames_missing", *ERROR_KINDS, "over_budget", "refused")}
    lost = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in losses.items() if v) or "none"
    line = (f"qradar {node.name}: {rate_in:.1f} frames/s in, {rate_out:.1f} out, {len(node.stats)} sensor(s); "
            f"{now.get('frames_in', 0)} in, {now.get('frames_out', 0)} out in all; losses: {lost}")
    last = getattr(node, "last_targets", None)
    if last is not None:
        sensor, seq, targets = last
        shown = "  ".join(f"({t['range_m']:.2f} m, {t['angle_deg']:+.1f}°)" for t in targets) or "none"
        line += f"; last: {sensor} #{seq} targets {shown}"
    return line


class StatusLines:
    """A thread printing :func:`start_line` at once (unless the command says its own:
    ``announce`` False) and :func:`status_line` every ``period_s`` to ``stream`` until
    :meth:`stop`; nothing with ``quiet``."""

    def __init__(self, node, stream: TextIO = sys.stderr, period_s: float = STATUS_PERIOD_S, quiet: bool = False,
                 announce: bool = True):
        self.node, self.stream, self.period_s, self.quiet, self.announce = node, stream, period_s, quiet, announce
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "StatusLines":
        if self.quiet:
            return self
        if self.announce:
            self._print(start_line(self.node))
        self._thread = threading.Thread(target=self._loop, name=f"{self.node.name}-status", daemon=True)
        self._thread.start()
        return self

    def _print(self, line: str) -> None:
        try:
            print(line, file=self.stream, flush=True)
        except (OSError, ValueError):  # a closed stream: the node goes on
            pass

    def _loop(self) -> None:
        before, t = self.node.totals(), time.monotonic()
        while not self._stop.wait(self.period_s):
            now, t_now = self.node.totals(), time.monotonic()
            self._print(status_line(self.node, before, now, t_now - t))
            before, t = now, t_now

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
