"""The ``qradar`` command: one entry point, subcommands in four groups.

- :mod:`.sensor`: ``sim``, ``drive``
- :mod:`.stream`: ``quantize``, ``localize``, ``source``, ``router``
- :mod:`.run_command`: ``run`` (the main job)
- :mod:`.record`: ``record``, ``recover``, ``replay``, ``info``
- :mod:`.analysis`: ``montecarlo``, ``montecarlo-time``, ``reprocess``
- :mod:`.view`: ``view`` (the live stream in Foxglove)
- :mod:`.bringup`: ``capture``, ``inspect`` (an unknown sensor's layout)
- :mod:`.ports`: ``ports`` (the serial adapters; ``--probe``: which answer as a K-MD2)
- :mod:`.security`: ``security init|add|remove|list`` (certificates for ``--secure``)

A command function parses its arguments into the libraries' configs and delegates.
Errors: only the packages' roots (RadarError, PipelineError, ReplayError) are caught;
their messages say what failed and where (a file, a port, a key) and what to check.
The command prints one line, ``qradar <command>: error: <message>``, and exits 2;
``-v`` (before or after the command) adds the traceback; a command run with ``--json``
prints ``{"error": ..., "exit_code": 2, "command": ...}`` on stdout as well. ``--help``
shows every default.
"""

from __future__ import annotations

import argparse
import ctypes
import importlib
import json
import logging
import os
import sys
import threading
import traceback

from pipeline.errors import PipelineError
from radar_driver.errors import RadarError, SetupError
from replay.errors import ReplayError

from . import lab
from .common import DefaultsFormatter, StopOnSignals

log = logging.getLogger("qradar")


class VersionAction(argparse.Action):
    """``--version``: the installed version, looked up only when asked (``qradar.__version__``)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0,
                         help=help or "show the installed version and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        import qradar

        print(f"qradar {qradar.__version__}")  # on stdout, as argparse's version action
        parser.exit()


class UsageError(SystemExit):
    """An argument error, said on stderr already (status 2); ``message`` for ``--json``."""

    def __init__(self, message: str):
        super().__init__(2)
        self.message = message


class CommandParser(argparse.ArgumentParser):
    """argparse's parser, whose argument errors are one line and the ``--help`` hint (not
    the usage block first), naming the command (``qradar run: error: ...``) even for an
    option the top parser found unknown."""

    #: the command of the top parser's arguments (:func:`build_parser`), for its errors
    command: str | None = None

    def error(self, message: str):
        prog = f"{self.prog} {self.command}" if self.command and self.prog == "qradar" else self.prog
        self._print_message(f"{prog}: error: {message} (see `{prog} --help`)\n", sys.stderr)
        raise UsageError(message)


#: The functions that add the commands to the parser, as (module, function), in the order of
#: `qradar -h`; and the commands each adds (tests/test_cli_help.py checks them against the parser).
ADDERS: dict[tuple[str, str], tuple[str, ...]] = {
    ("analysis", "add_montecarlo"): ("montecarlo",),
    ("analysis", "add_montecarlo_time"): ("montecarlo-time",),
    ("sensor", "add_commands"): ("sim", "drive"),
    ("stream", "add_commands"): ("quantize", "localize", "source", "router"),
    ("run_command", "add_commands"): ("run",),
    ("up", "add_commands"): ("up",),
    ("record", "add_commands"): ("record", "recover", "replay", "info"),
    ("analysis", "add_reprocess"): ("reprocess",),
    ("view", "add_commands"): ("view",),
    ("bringup", "add_commands"): ("capture", "inspect"),
    ("ports", "add_commands"): ("ports",),
    ("security", "add_commands"): ("security",),
    ("calibrate", "add_commands"): ("calibrate",),
}


def command_of(argv: list[str] | None) -> str | None:
    """The command ``argv`` names (its first word that is not an option: ``qradar``'s own
    options take no value), or None."""
    words = sys.argv[1:] if argv is None else argv
    return next((w for w in words if not w.startswith("-")), None)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """``qradar``'s parser: every command's, or only ``command``'s group when it is one (a
    node's process then imports only its own command's modules, ~0.2 s less at each start)."""
    parser = CommandParser(
        prog="qradar", description="1-bit dithered FMCW radar localization: simulation, streaming, replay.",
        formatter_class=DefaultsFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging, tracebacks on errors")
    parser.add_argument("--version", action=VersionAction)
    sub = parser.add_subparsers(dest="command", required=True)
    known = any(command in names for names in ADDERS.values())
    parser.command = command if known else None
    for (module, adder), names in ADDERS.items():
        if not known or command in names:
            getattr(importlib.import_module(f".{module}", __name__), adder)(sub)
    for p in sub.choices.values():
        p.formatter_class = DefaultsFormatter
        p.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                       help="debug logging, tracebacks on errors")
    return parser


#: glibc's mallopt parameter M_ARENA_MAX
_M_ARENA_MAX = -8


def limit_malloc_arenas(arenas: int = 2) -> bool:
    """Cap glibc's heap arenas, as ``MALLOC_ARENA_MAX=arenas`` would (unless the environment
    sets it). glibc gives threads that allocate their own arenas (up to 8 per core) and
    seldom returns their memory: a busy ``qradar run`` with zenoh's threads and its own grew
    ~10 MB/min with no Python object growing, and stayed flat with 2 (benchmarks/soak.py).
    True when the cap was set."""
    if "MALLOC_ARENA_MAX" in os.environ or not sys.platform.startswith("linux"):
        return False
    try:
        return ctypes.CDLL("libc.so.6").mallopt(_M_ARENA_MAX, arenas) == 1
    except (OSError, AttributeError):  # not glibc (musl has no arenas to cap)
        return False


def main(argv: list[str] | None = None) -> int:
    """The ``qradar`` command; ``argv`` None: the process's own arguments, and a process
    that loaded zenoh then ends here (:func:`_end_process`)."""
    code = _main(argv)
    if argv is None and "zenoh" in sys.modules:
        _end_process(code)
    return code


def _end_process(code: int) -> None:
    """End the process without the interpreter's finalization once the command is done
    (its sessions closed, files written, summary printed): zenoh's own threads outlive the
    closed sessions, and one calling into Python while the interpreter finalizes is
    aborted by the C library ("FATAL: exception not rethrown", status -6; seen once in a
    --secure node under attack). The exit handlers run first, the output is flushed."""
    import atexit

    atexit._run_exitfuncs()
    for out in (sys.stdout, sys.stderr):
        try:
            out.flush()
        except (OSError, ValueError):
            pass
    StopOnSignals.EXIT.acquire()  # never released: a forced exit (status 130) under way ends the process first
    os._exit(code if isinstance(code, int) else 1)


def _main(argv: list[str] | None) -> int:
    limit_malloc_arenas()
    command = command_of(argv)
    parser = build_parser(command)
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:  # said on stderr; with --json the error object on stdout too
        if "--json" in (sys.argv[1:] if argv is None else argv):
            print(json.dumps({"error": exc.message, "exit_code": 2, "command": command}), flush=True)
        return 2
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    threading.excepthook = _thread_failed
    try:
        args = with_config(parser, args, argv)
        return args.func(args)
    except (PipelineError, RadarError, ReplayError) as exc:
        return fail(args, exc, 2)
    except KeyboardInterrupt:
        return fail(args, "interrupted", 130)


def command_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The parser of the command ``args`` were parsed for (a subcommand's, e.g. ``security init``)."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[args.command]
    action = getattr(args, "action", None)
    if action is not None:
        sub = next(a for a in sub._actions if isinstance(a, argparse._SubParsersAction)).choices[action]
    return sub


def with_config(parser: argparse.ArgumentParser, args: argparse.Namespace, argv) -> argparse.Namespace:
    """``args`` with a lab file's (``run LAB.toml``) or ``--config-json``'s values under
    the command line's: the file's values become the command's defaults and the command
    line is parsed again. A file that does not read: a LabError (one line, exit 2)."""
    schema = getattr(args, "schema", None)
    if schema is None:
        return args
    sub = command_parser(parser, args)
    values = {}
    if getattr(args, "lab", None) is not None and schema.reads_lab:
        values.update(lab.read_file(args.lab, schema))
    if getattr(args, "config_json", None) is not None:
        values.update(lab.read_json(args.config_json, schema))
    if values:
        sub.set_defaults(**values)
        args = parser.parse_args(argv)
    schema.check_required(args, sub)
    return args


def _thread_failed(hook: threading.ExceptHookArgs) -> None:
    """A thread that dies of an exception: one log line (its traceback under -v), not
    Python's traceback on stderr. pyserial's RFC 2217 reader thread dies when the other end
    hangs up; the session reports that itself, so it is only a debug line."""
    name = hook.thread.name if hook.thread is not None else "a thread"
    level = logging.DEBUG if name.startswith("pySerial") else logging.ERROR
    log.log(level, "%s died: %s", name, hook.exc_value)
    log.debug("%s died", name, exc_info=(hook.exc_type, hook.exc_value, hook.exc_traceback))


def fail(args, exc: BaseException | str, code: int) -> int:
    """One line on stderr (the traceback too under -v); with --json, a JSON object on stdout."""
    if args.verbose and isinstance(exc, BaseException):
        traceback.print_exception(exc)
    message = " ".join(str(exc).split()) or type(exc).__name__
    print(f"qradar {args.command}: error: {message}" if code != 130 else f"qradar {args.command}: {message}",
          file=sys.stderr, flush=True)
    if getattr(args, "json", False):
        # "setup": a wrong set-up (radar_driver.errors.SetupError), which a restart does not mend
        setup = {"setup": True} if isinstance(exc, SetupError) else {}
        print(json.dumps({"error": message, "exit_code": code, "command": args.command, **setup}), flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
