"""Argument types and options shared by the command groups."""

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
from pipeline.nodes.budget import (
    DEFAULT_BYTES_PER_S,
    DEFAULT_NEW_SENSORS_BURST,
    DEFAULT_NEW_SENSORS_PER_S,
    DEFAULT_RATE_HZ,
    IntakeBudget,
)
from pipeline.bus.session import BusConfig, Shard, check_sensor_pattern
from pipeline.dsp.calibration import Calibration
from pipeline.dsp.calibration import load as load_calibration_file
from pipeline.bus.security import SecureConfig
from pipeline.dsp.decode import ALGOS, DEFAULT_ALGO, DEFAULT_ALPHA, Algo
from pipeline.errors import ParameterError
from pipeline.dsp.gate import LEAKAGE_BINS
from pipeline.dsp.localize import DEFAULT_PFA
from pipeline.dsp.quantize import QuantizerConfig, parse_alpha
from pipeline.dsp.track import TrackerConfig


def force_option(p, what: str) -> None:
    """``--force``: the one overwrite policy (replay.outputs): an existing output is replaced
    only when told."""
    p.add_argument("--force", action="store_true", help=f"replace {what} if it exists (without it: refused, "
                   "nothing written)")


def nonneg_int(text: str) -> int:
    v = int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return v


def pos_int(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return v


def pos_float(text: str) -> float:
    v = float(text)
    if not v > 0.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return v


class DefaultsFormatter(argparse.RawDescriptionHelpFormatter):
    """``--help`` shows every option's default (unless its help already says it)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text.lower() or action.default in (None, False, [], (), argparse.SUPPRESS)
                or action.option_strings == [] or isinstance(action, argparse._HelpAction)):
            return text
        return f"{text} (default: %(default)s)"


def sensor_pattern_arg(text: str) -> str:
    try:
        return check_sensor_pattern(text)
    except ParameterError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def shard_arg(text: str) -> Shard:
    try:
        return Shard.parse(text)
    except ParameterError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def prob(text: str) -> float:
    v = float(text)
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a probability in [0, 1]")
    return v


def nonneg_float(text: str) -> float:
    v = float(text)
    if not v >= 0.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return v


def alpha_arg(text: str) -> str | float:
    """``auto`` (alpha from each sensor's noise) or a dither scale in [0, 1]."""
    try:
        return parse_alpha(text)
    except ParameterError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def delta_arg(text: str) -> str | float:
    """``auto`` or a quantizer step > 0 (full-scale units)."""
    if text == "auto":
        return text
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} must be 'auto' or a number > 0") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be 'auto' or a number > 0")
    return v


def k_arg(text: str) -> int | str:
    """``auto`` or a target count >= 1."""
    if text == "auto":
        return text
    try:
        return pos_int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} must be 'auto' or an integer >= 1") from None


def pfa_arg(text: str) -> float:
    v = float(text)
    if not 0.0 < v < 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a false-alarm probability in (0, 1)")
    return v


def count_options(p: argparse.ArgumentParser, default, help: str) -> None:
    """``--K N|auto``, ``--max-targets`` and ``--pfa``; see :func:`count_from_args`."""
    p.add_argument("--K", dest="k", type=k_arg, default=default,
                   help=f"{help}; auto: decide each frame's count (pbp, cml) by a CFAR test, at most --max-targets")
    p.add_argument("--max-targets", type=pos_int, default=4, help="with --K auto: the most a frame has (default 4)")
    p.add_argument("--pfa", type=pfa_arg, default=DEFAULT_PFA,
                   help=f"with --K auto: false-alarm probability per frame and test (default {DEFAULT_PFA:g})")


def count_from_args(args) -> tuple[int | None, bool]:
    """(K, auto): with ``--K auto`` the K is --max-targets."""
    return (args.max_targets, True) if args.k == "auto" else (args.k, False)


def algo_option(p: argparse.ArgumentParser, help: str, default: Algo = DEFAULT_ALGO) -> None:
    """``--algo``, one of the decoders (pipeline.dsp.decode.Algo); default the one definition's
    (:data:`pipeline.defaults.DEFAULT_ALGO`)."""
    p.add_argument("--algo", choices=list(ALGOS), default=default.value, help=f"{help} (default {default})")


#: --alpha's help wherever a quantizer has no decoder to follow
ALPHA_HELP = (f"dither scale in [0, 1] (default {DEFAULT_ALPHA:g}: the best of the default decoder, {DEFAULT_ALGO}, "
              "off the range grid)")


def gate_options(p: argparse.ArgumentParser) -> None:
    """``--min-range-m`` / ``--max-range-m``: the range gate the decoder searches inside
    (pipeline.dsp.gate); None: the radar's default gate."""
    g = p.add_argument_group("range gate", "targets are sought only in [MIN, MAX] m; the default keeps out "
                             f"{LEAKAGE_BINS} range bins at each end of the circular range axis (TX-to-RX leakage "
                             "sits within the first bin or two, and leaks into the top ones)")
    g.add_argument("--min-range-m", type=nonneg_float, default=None, metavar="M",
                   help=f"default {LEAKAGE_BINS} c/(2B): 1.2 m with the K-MD2's 250 MHz sweep")
    g.add_argument("--max-range-m", type=nonneg_float, default=None, metavar="M",
                   help=f"default the unambiguous range N c/(2B) less {LEAKAGE_BINS} bins: 152.4 m for the K-MD2")


def track_options(p: argparse.ArgumentParser) -> None:
    """``--track`` and ``--integrate SECONDS``: tracks after the localizer (pipeline.dsp.track)."""
    g = p.add_argument_group("tracks", "tracks of the targets (pipeline.dsp.track): an id, a velocity, an uncertainty "
                             "and a static flag per track, on radar/<sensor>/tracks")
    g.add_argument("--track", action="store_true", help="publish radar/<sensor>/tracks, one JSON message a frame")
    g.add_argument("--integrate", type=nonneg_float, default=TrackerConfig.integrate_s, metavar="SECONDS",
                   help="refine each static track on the codes of its last SECONDS of frames decoded together "
                   f"(default {TrackerConfig.integrate_s:g}; 0: no integration)")


def tracker_config(args) -> TrackerConfig | None:
    """The tracker of ``--track`` (None without it)."""
    return TrackerConfig(integrate_s=args.integrate) if args.track else None


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
    _wakeup: tuple[int, int] | None = None  # the pipe the signals' numbers come through (read, write)

    def __init__(self, stop: threading.Event | None, name: str, json_error: bool = False,
                 on_force: Callable[[], None] | None = None):
        self.stop, self.name, self.json_error, self.on_force = stop, name, json_error, on_force
        self.interrupted: str | None = None  # the signal's name, once one came
        self._received = 0
        self._first_s = 0.0  # monotonic time of the first signal
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
        """In the main thread; the watcher does the rest."""
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
        if self._received and now - self._first_s < SAME_SIGNAL_S:
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

    def force(self, name: str) -> None:
        """Exit at once, status 130, after one line and ``on_force``."""
        try:
            os.write(2, f"qradar {self.name}: {name} again while stopping: exiting at once (status 130)\n".encode())
            if self.json_error:
                os.write(audit.stdout_fd(),  # (not 1: under --secure the audit's pipe, never read after _exit)
                         (json.dumps({"error": "interrupted", "exit_code": 130, "command": self.name}) + "\n").encode())
            if self.on_force is not None:
                self.on_force()
        finally:
            os._exit(130)


#: how often a child process looks whether its parent is still there, s
PARENT_POLL_S = 0.2
#: after its parent's death, how long a child may take to stop cleanly before it exits anyway, s
PARENT_GONE_GRACE_S = 3.0


def watch_parent(parent_pid: int, name: str) -> threading.Thread:
    """End this process when ``parent_pid`` is no longer its parent (it died, however:
    SIGKILL, the OOM killer, a crash), within PARENT_POLL_S: SIGTERM to itself, so the
    command stops as on a SIGTERM (a driver says GBYE), and, should that not end it within
    PARENT_GONE_GRACE_S, ``os._exit(1)``. A poll, not Linux's ``PR_SET_PDEATHSIG``:
    that fires when the *thread* that started the child ends, which may be long before
    its process does."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        try:  # stderr may be a pipe to the parent that died
            print(f"qradar {name}: its parent process {parent_pid} is gone; stopping", file=sys.stderr, flush=True)
        except (OSError, ValueError):
            pass
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(PARENT_GONE_GRACE_S)
        os._exit(1)

    t = threading.Thread(target=watch, name="parent-watch", daemon=True)
    t.start()
    return t


def bus_options(parser: argparse.ArgumentParser, modes: tuple[str, ...] = ("peer", "client")) -> None:
    """Add --zenoh-config, --connect, --listen, --mode, --prefix, --secure, --identity."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--zenoh-config", type=Path, default=None, help="zenoh JSON5 config file")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="e.g. tcp/127.0.0.1:7447 (with --secure: tls/HOST:PORT)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="e.g. tcp/127.0.0.1:7447; none by default (nothing listens unless asked, here or in "
                   "--zenoh-config)")
    if len(modes) > 1:
        g.add_argument("--mode", choices=list(modes), default=modes[0], help="zenoh mode")
    else:
        parser.set_defaults(mode=modes[0])
    g.add_argument("--prefix", default="radar", help="key prefix (default radar)")
    g.add_argument("--secure", type=Path, default=None, metavar="DIR",
                   help="mutual TLS and the access-control policy of DIR (made by `qradar security init`); "
                   "only tls/ endpoints")
    g.add_argument("--identity", default=None, metavar="NAME",
                   help="with --secure: the certificate to use (default: this command's role, e.g. quantizer, "
                   "localizer, recorder, viewer, router, sensor-<id>)")


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
                    config_file=args.zenoh_config, prefix=args.prefix, secure=secure,
                    alone_warning=f"qradar {args.command}")  # a stand-alone command says if it reaches nobody
    if secure is not None:  # refused handshakes and denied messages, from zenoh's log (pipeline/bus/audit.py)
        audit.start(f"qradar {args.command}", full=bus.mode != "client" or bool(bus.listen_endpoints()))
    return bus


#: --bits, wherever a quantizer is set
BITS_HELP = ("bits per real value (I and Q each) of the dithered quantizer, 1 to 16: 1 = the paper's one bit "
             "(the sign, with delta auto)")


def quantizer_options(p, alpha_default: float | None, alpha_help: str,
                      seed_flags: tuple[str, ...] = ("--seed", "--dither-seed")) -> None:
    """--bits, --alpha, --delta, --delta-margin and the dither seed (``seed_flags``: a
    command whose --seed is another seed, e.g. the simulated sensors' noise, takes
    --dither-seed only)."""
    p.add_argument("--bits", type=pos_int, default=1, help=BITS_HELP)
    p.add_argument("--alpha", type=alpha_arg, default=alpha_default,
                   help=alpha_help + "; 'auto': per sensor from the noise estimated in its frames (published in the "
                   "quantizer's health)")
    p.add_argument("--delta", type=delta_arg, default="auto", help="'auto' (smallest 1-bit step per frame) or a step in full-scale units")
    p.add_argument("--delta-margin", type=nonneg_float, default=0.0, help="auto delta x (1 + margin)")
    p.add_argument(*seed_flags, dest="dither_seed", type=nonneg_int, default=0,
                   help="dither seed (per sensor: seed * 2^32 + crc32(id))")


def quantizer_config(args, alpha: float | None = None) -> QuantizerConfig:
    return QuantizerConfig(bits=args.bits, alpha=args.alpha if alpha is None else alpha, delta=args.delta,
                           delta_margin=args.delta_margin, dither_seed=args.dither_seed)


def edge_quantizer_options(p, switch: str) -> None:
    """``switch`` (--quantized / --quantize), the quantizer's options and --raw-every, for a
    sensor's own process that quantizes its frames (edge quantization)."""
    g = p.add_argument_group("edge quantization", "quantize in this process, with the quantize node's dither "
                             "seed rule and options, and publish 1-bit frames on <prefix>/<id>/quantized")
    g.add_argument(switch, dest="edge_quantize", action="store_true",
                   help="publish quantized frames (raw ones only with --raw-every)")
    quantizer_options(g, DEFAULT_ALPHA, ALPHA_HELP, ("--dither-seed",))
    g.add_argument("--raw-every", type=nonneg_int, default=None, metavar="N",
                   help=f"with {switch}: also publish the raw frames whose seq is a multiple of N (e.g. for "
                   "recording; default 0 = none)")
    calibration_option(g)


CALIBRATION_HELP = ("remove the front end measured by `qradar calibrate` (background: DC, leakage, clutter; "
                    "I/Q imbalance; receiver 2's gain and phase) where frames are quantized; raw frames and their "
                    "recordings keep what the sensor sent")


def calibration_option(p) -> None:
    p.add_argument("--calibration", type=Path, default=None, metavar="CAL.json", help=CALIBRATION_HELP)


def load_calibration(path: Path | None, sensor_ids: list[str] | tuple[str, ...] = ()) -> Calibration | None:
    """The calibration file at ``path`` (None: none), refused with one line when it has no
    entry for one of ``sensor_ids``."""
    if path is None:
        return None
    cal = load_calibration_file(path)
    for sid in sensor_ids:
        cal.check_sensor(sid)
    return cal


def edge_quantizer(args) -> tuple[QuantizerConfig | None, int | None]:
    """(quantizer or None, raw_every) of edge_quantizer_options."""
    if not args.edge_quantize:
        if args.raw_every is not None:
            raise ParameterError("--raw-every is for edge quantization (--quantized / --quantize)")
        if args.calibration is not None:
            raise ParameterError("--calibration is applied where frames are quantized: give --quantized / "
                                 "--quantize too (or --calibration to the quantize node)")
        return None, None
    return quantizer_config(args), args.raw_every


def intake_options(p) -> None:
    """The intake budgets of a node that subscribes (pipeline.nodes.budget)."""
    g = p.add_argument_group("intake budgets", "checked where each message arrives, before any work; a message "
                             "over a budget is dropped and counted (over_budget, refused), so a flooding sender "
                             "cannot delay the others (0: no limit)")
    g.add_argument("--budget-rate", type=nonneg_float, default=DEFAULT_RATE_HZ, metavar="HZ",
                   help=f"messages a second per key <prefix>/<sensor>/<topic> (default {DEFAULT_RATE_HZ:g}: 5 x a "
                   "K-MD2's 20 frames/s), with a burst of one second")
    g.add_argument("--budget-mb", type=nonneg_float, default=DEFAULT_BYTES_PER_S / 1e6, metavar="MB",
                   help=f"payload megabytes a second per key (default {DEFAULT_BYTES_PER_S / 1e6:g})")
    g.add_argument("--admit-rate", type=nonneg_float, default=DEFAULT_NEW_SENSORS_PER_S, metavar="N",
                   help=f"new sensor ids admitted a second (default {DEFAULT_NEW_SENSORS_PER_S:g}, after a burst of "
                   f"{DEFAULT_NEW_SENSORS_BURST}); the frames of ids not admitted count as refused")


def intake_budget(args) -> IntakeBudget:
    """The IntakeBudget of the options of :func:`intake_options`."""
    return IntakeBudget(rate_hz=args.budget_rate, bytes_per_s=args.budget_mb * 1e6, new_sensors_per_s=args.admit_rate)
