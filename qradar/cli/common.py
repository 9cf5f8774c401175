"""What the command groups share: the help formatter, the signals that stop a live command,
a child's watch on its parent, the zenoh session and the configs of the parsed options."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

from pipeline.bus import audit
from pipeline.bus.security import SecureConfig
from pipeline.bus.session import BusConfig
from pipeline.dsp.calibration import Calibration
from pipeline.dsp.calibration import load as load_calibration_file
from pipeline.errors import ParameterError
from pipeline.nodes.budget import IntakeBudget


class DefaultsFormatter(argparse.RawDescriptionHelpFormatter):
    """``--help`` shows every option's default (unless its help already says it; not a
    switch's: ``--no-uncertainty``'s field defaults to True, which the switch makes False)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text.lower() or action.default in (None, False, [], (), argparse.SUPPRESS)
                or action.option_strings == [] or isinstance(action, argparse._HelpAction) or action.nargs == 0):
            return text
        return f"{text} (default: %(default)s)"


def install_sigterm(name: str) -> "StopOnSignals":
    """SIGTERM and SIGINT end command ``name`` cleanly, also when started in the background
    (where a shell ignores SIGINT): the first raises KeyboardInterrupt in the main thread,
    a second one while the command stops exits at once (:class:`StopOnSignals`)."""
    return StopOnSignals(None, name)


#: a second SIGINT / SIGTERM within this many seconds of the first is the same interrupt
#: (``timeout`` and some supervisors signal the child and its process group, ms apart)
SAME_SIGNAL_S = 0.5


class StopOnSignals:
    """SIGINT and SIGTERM end a live command normally. The first sets ``stop`` (the
    command then stops its nodes in order and prints its summary) or, for a command
    without such an event, raises KeyboardInterrupt in its main thread; ``interrupted``
    names it. A second within SAME_SIGNAL_S of the first is the same one, delivered twice.
    A second later, while it is stopping, ends the process at once with status 130:
    one line on stderr (with ``json_error`` also the error object on stdout), then
    ``on_force`` (a quick clean-up; its children stop by themselves: :func:`watch_parent`).

    The signals reach a thread of their own through ``signal.set_wakeup_fd``, which sets
    the event, prints and forces the exit however busy the main thread is: in a signal
    handler, Event.set can deadlock on the lock the interrupted main thread holds (in
    Event.wait), and a print fail on the stream it was writing. A process has one set of
    handlers, so the newest instance is the one in charge."""

    _current: "StopOnSignals | None" = None
    #: held by whoever ends the process: :meth:`force` (status 130) or the command's normal end
    #: (:func:`qradar.cli._end_process`), so that a process that said "exiting at once (status
    #: 130)" never ends 0 (the main thread ending normally between that line and the exit)
    EXIT = threading.Lock()
    _wakeup: tuple[int, int] | None = None  # the pipe the signals' numbers come through (read, write)

    def __init__(self, stop: threading.Event | None, name: str, json_error: bool = False,
                 on_force: Callable[[], None] | None = None):
        self.stop, self.name, self.json_error, self.on_force = stop, name, json_error, on_force
        self.interrupted: str | None = None  # the signal's name, once one came
        self._received = 0
        self._first_s = 0.0  # monotonic time of the first signal
        #: when the main thread's handler ran for the first and the last signal (monotonic, s; None:
        #: not yet): the signals' own times, where the watcher may read them late and together
        self._handled_s: tuple[float, float] | None = None
        self._raised = False
        if StopOnSignals._wakeup is None:
            r, w = os.pipe()
            os.set_blocking(w, False)
            StopOnSignals._wakeup = (r, w)
            threading.Thread(target=StopOnSignals._watch, name="signals", daemon=True).start()
        StopOnSignals._current = self
        signal.set_wakeup_fd(StopOnSignals._wakeup[1], warn_on_full_buffer=False)
        signal.signal(signal.SIGINT, self._handler)
        signal.signal(signal.SIGTERM, self._handler)

    def _handler(self, signum, frame) -> None:
        """In the main thread: when the signal came (:meth:`_apart`); the watcher does the rest."""
        now = time.monotonic()
        self._handled_s = (now, now) if self._handled_s is None else (self._handled_s[0], now)
        if self.stop is None and not self._raised:
            self._raised = True
            raise KeyboardInterrupt

    @staticmethod
    def _watch() -> None:
        while True:
            for signum in os.read(StopOnSignals._wakeup[0], 64):
                current = StopOnSignals._current
                if current is not None and signum in (signal.SIGINT, signal.SIGTERM):
                    current._on_signal(signal.Signals(signum).name)

    def _on_signal(self, name: str) -> None:
        now = time.monotonic()
        if self._received and now - self._first_s < SAME_SIGNAL_S and not self._apart():
            return  # the same interrupt delivered twice (to the process and to its group): not "again"
        self._received += 1
        if self._received == 1:
            self._first_s = now
        if self._received > 1:
            self.force(name)
        self.interrupted = name
        if self.stop is not None:
            try:
                print(f"qradar {self.name}: {name}: stopping (again to force)", file=sys.stderr, flush=True)
            except (OSError, ValueError):
                pass
            self.stop.set()

    def _apart(self) -> bool:
        """The main thread's handler ran for signals SAME_SIGNAL_S or more apart: two signals,
        however late the watcher (a busy host) read them (the handler runs once for a signal
        that came twice before it could: a duplicate is never apart)."""
        h = self._handled_s
        return h is not None and h[1] - h[0] >= SAME_SIGNAL_S

    def force(self, name: str) -> None:
        """Exit at once, status 130, after one line and ``on_force`` (none if the command is
        already ending normally: it ends with its own status)."""
        StopOnSignals.EXIT.acquire()
        try:
            os.write(2, f"qradar {self.name}: {name} again while stopping: exiting at once (status 130)\n".encode())
            if self.json_error:
                os.write(audit.stdout_fd(),  # (not 1: under --secure the audit's pipe, never read after _exit)
                         (json.dumps({"error": "interrupted", "exit_code": 130, "command": self.name}) + "\n").encode())
            if self.on_force is not None:
                self.on_force()
        finally:
            os._exit(130)


# the identity a command speaks as under --secure unless --identity names another
COMMAND_IDENTITY = {"router": "router", "run": "router", "quantize": "quantizer", "localize": "localizer",
                    "record": "recorder", "view": "viewer"}


def default_identity(args) -> str | None:
    """The identity ``args.command`` uses by default: its role's, or ``sensor-<id>`` for
    a node publishing one sensor (``drive``, ``source`` of one simulated sensor)."""
    command = getattr(args, "command", None)
    if command in COMMAND_IDENTITY:
        return COMMAND_IDENTITY[command]
    if command == "drive":
        return f"sensor-{args.sensor_id}"
    if command == "source" and args.recording is None and args.sensors == 1:
        return f"sensor-{args.id_prefix}0"
    return None


def bus_from_args(args, mode: str | None = None) -> BusConfig:
    secure = None
    if args.secure is not None:
        identity = args.identity or default_identity(args)
        if identity is None:
            raise ParameterError(f"qradar {args.command} --secure needs --identity NAME (it has no single role)")
        secure = SecureConfig(args.secure, identity)
    elif args.identity is not None:
        raise ParameterError("--identity is for --secure DIR")
    bus = BusConfig(mode=mode or args.mode, connect=tuple(args.connect), listen=tuple(args.listen),
                    config_file=args.config_file, prefix=args.prefix, secure=secure,
                    alone_warning=f"qradar {args.command}")  # a stand-alone command says if it reaches nobody
    if secure is not None:  # refused handshakes and denied messages, from zenoh's log (pipeline/bus/audit.py)
        audit.start(f"qradar {args.command}", full=bus.mode != "client" or bool(bus.listen_endpoints()))
    return bus


def load_calibration(path: Path | None, sensor_ids: list[str] | tuple[str, ...] = ()) -> Calibration | None:
    """The calibration file at ``path`` (None: none), refused with one line when it has no
    entry for one of ``sensor_ids``."""
    if path is None:
        return None
    cal = load_calibration_file(path)
    for sid in sensor_ids:
        cal.check_sensor(sid)
    return cal


def intake_budget(args) -> IntakeBudget:
    """The IntakeBudget of the parsed options (:data:`.parts.INTAKE`)."""
    return args.schema.build(IntakeBudget, args)


def nothing_heard(command: str, said: str, role: str, warn_only: bool) -> int:
    """A node that sent or received nothing of its peers (another --prefix, no router in
    common): one line, ``said`` and the hint, on stderr; its status: 1, or 0 as a warning
    (``warn_only``: stopped by a signal before a node came, or a node of ``qradar up``)."""
    print(f"qradar {command}: {'warning' if warn_only else 'error'}: {said} (are the nodes up, on this --prefix, and "
          f"joined to the same router as this {role}?)", file=sys.stderr, flush=True)
    return 0 if warn_only else 1
