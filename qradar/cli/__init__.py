"""The ``qradar`` command: one entry point, subcommands in four groups.

- :mod:`.sensor`: ``sim``, ``drive``
- :mod:`.stream`: ``quantize``, ``localize``, ``source``, ``router``, ``run``
- :mod:`.record`: ``record``, ``recover``, ``replay``
- :mod:`.analysis`: ``montecarlo``, ``reprocess``
- :mod:`.view`: ``view`` (the live stream in Foxglove)

A command function parses its arguments into the libraries' configs and delegates.
Errors: only the packages' roots (RadarError, PipelineError, ReplayError) are caught;
their messages say what failed and where (a file, a port, a key). The command prints
``qradar <command>: error: <message>`` and exits 2; ``-v`` adds the traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
import traceback

from pipeline.errors import PipelineError
from radar_driver.errors import RadarError
from replay.errors import ReplayError

from . import analysis, record, sensor, stream, view

log = logging.getLogger("qradar")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="qradar", description="1-bit dithered FMCW radar localization: simulation, streaming, replay."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging, tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True)
    analysis.add_montecarlo(sub)  # the order of `qradar -h`, as before the split into groups
    sensor.add_commands(sub)
    stream.add_commands(sub)
    record.add_commands(sub)
    analysis.add_reprocess(sub)
    view.add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (PipelineError, RadarError, ReplayError) as exc:
        if args.verbose:
            traceback.print_exc()
        print(f"qradar {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"qradar {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
