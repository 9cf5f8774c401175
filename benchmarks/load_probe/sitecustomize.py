"""Timing probe for benchmarks/bench_driver_load.py --trace DIR (not imported otherwise).

Python imports ``sitecustomize`` at start-up from the path; the benchmark puts this
directory on PYTHONPATH of the simulator, driver and run processes (the busy loops do
not get it) with ``QRADAR_PROBE_DIR`` set. It wraps, on the classes of whichever tree is
running (the same method names before and after the redesign):

- the simulator: ``PtyLink.read`` (when a GNFD arrived), ``SimulatedKMD2._ramp_replies``
  (the device clock: the counter it had, the RADC index it answers, when that RADC and
  the one after the counter are due), ``PtyLink.write`` of each DONE (when it went out);
- the driver: ``SensorSession._fill_inbox`` (when a DONE was read, by its counter) and
  ``SensorSession._write`` of each GNFD (when it went out);
- the consumer: ``SourceNode.publish`` (start, end) and the garbage collector's passes;

with ``time.monotonic()`` (CLOCK_MONOTONIC: one clock for all processes) and writes
them to ``$QRADAR_PROBE_DIR/<pid>.json`` at exit.
"""

from __future__ import annotations

import atexit
import gc
import json
import os
import sys
import threading
import time

_DIR = os.environ.get("QRADAR_PROBE_DIR")
_EV: dict[str, list] = {"gnfd_in": [], "ramp": [], "done_out": [], "done_in": [], "gnfd_out": [], "publish": [],
                        "gc": []}


def _dump() -> None:
    _EV["argv"] = sys.argv
    _EV["pid"] = os.getpid()
    _EV["switchinterval"] = sys.getswitchinterval()
    with open(os.path.join(_DIR, f"{os.getpid()}.json"), "w") as f:
        json.dump(_EV, f)


def _install() -> None:
    mono = time.monotonic
    gc_start = [0.0]

    def on_gc(phase, info):
        if phase == "start":
            gc_start[0] = mono()
        else:
            _EV["gc"].append((gc_start[0], mono(), info.get("generation")))

    gc.callbacks.append(on_gc)

    from radar_driver import session, simulator

    read0, write0, ramp0 = simulator.PtyLink.read, simulator.PtyLink.write, simulator.SimulatedKMD2._ramp_replies

    def read(self, timeout_s):
        data = read0(self, timeout_s)
        if b"GNFD" in data:
            _EV["gnfd_in"].append(mono())
        return data

    def write(self, data, timeout_s=1.0):
        t0 = mono()
        ok = write0(self, data, timeout_s)
        if data[:4] == b"DONE":
            _EV["done_out"].append((t0, mono(), int.from_bytes(data[8:12], "little"), ok))
        return ok

    def ramp(self, mask, now):
        before = self.counter
        out = ramp0(self, mask, now)
        rate = getattr(self, "radc_rate_hz", None) or getattr(self, "ramp_rate_hz", 0)  # after / before
        due = self._t0 + self.counter / rate if rate and self._t0 is not None else None
        # when RADC before+1 was due on the device clock as it stood (a held clock moves it)
        next_due = self._t0 + (before + 1) / rate if due is not None else None
        _EV["ramp"].append((now, before, self.counter, due, next_due))
        return out

    simulator.PtyLink.read, simulator.PtyLink.write = read, write
    simulator.SimulatedKMD2._ramp_replies = ramp

    fill0, swrite0 = session.SensorSession._fill_inbox, session.SensorSession._write

    def fill(self):
        n = len(self._inbox)
        fill0(self)
        new = list(self._inbox)[n:]
        if new:
            t = mono()
            for m in new:
                if isinstance(m, session.Done):
                    _EV["done_in"].append((t, m.frame_counter, threading.get_ident()))

    def swrite(self, data):
        t0 = mono()
        swrite0(self, data)
        if bytes(data[:4]) == b"GNFD":
            _EV["gnfd_out"].append((t0, mono()))

    session.SensorSession._fill_inbox, session.SensorSession._write = fill, swrite

    try:
        from pipeline.nodes import stream as nodes
    except ImportError:
        return
    pub0 = nodes.SourceNode.publish

    def publish(self, *a, **kw):
        t0 = mono()
        pub0(self, *a, **kw)
        _EV["publish"].append((t0, mono()))

    nodes.SourceNode.publish = publish


if _DIR:
    try:
        _install()
        atexit.register(_dump)
    except Exception as exc:  # a probe never breaks the program it watches
        print(f"load_probe: not installed: {exc!r}", file=sys.stderr)
