"""The option parts several commands share (:class:`~.schema.Part`), each in the lab file's
table it reads from: the quantizer, the decoder and its target count, the range gate,
tracks, the zenoh session and its security, a node's input queue, the sensors it serves
and its intake budgets, its run (duration, status lines, parent), and a few switches.

Options of the library's configs are defined on their fields; the configs of
``pipeline.dsp`` and ``pipeline.nodes.stream`` (modules owned with the maths) get theirs
here, by field name, beside the field's own default. The few dataclasses below hold
what no library config has (a switch of the command line, ``--K auto``), their defaults
taken from the library where it has one."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pipeline.bus.session import BusConfig
from pipeline.defaults import DEFAULT_MAX_TARGETS
from pipeline.dsp.decode import ALGOS, DEFAULT_ALGO, DEFAULT_ALPHA
from pipeline.dsp.gate import LEAKAGE_BINS
from pipeline.dsp.quantize import QuantizerConfig, parse_alpha
from pipeline.dsp.track import TrackerConfig
from pipeline.errors import ParameterError
from pipeline.nodes.budget import IntakeBudget
from pipeline.nodes.intake import QueueConfig, ServeConfig
from pipeline.nodes.status import STATUS_PERIOD_S
from pipeline.nodes.stream import LocalizerConfig
from radar_driver.options import MISSING, Option, OptionValueError, nonneg_float, nonneg_int, option, pos_int

from .schema import Part


# -- value parsers of the command line ----------------------------------------------------------
def alpha(text: str) -> float | str:
    """``auto`` (alpha from each sensor's noise) or a dither scale in [0, 1]."""
    return parse_alpha(text)


def delta(text: str) -> float | str:
    """``auto`` or a quantizer step > 0 (full-scale units)."""
    if text == "auto":
        return text
    try:
        v = float(text)
    except ValueError:
        raise OptionValueError("must be 'auto' or a number > 0") from None
    if not v > 0:
        raise OptionValueError("must be 'auto' or a number > 0")
    return v


def count(text: str) -> int | str:
    """``auto`` or a target count >= 1."""
    if text == "auto":
        return text
    try:
        return pos_int(text)
    except OptionValueError:
        raise OptionValueError("must be 'auto' or an integer >= 1") from None


def false_alarm(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise OptionValueError("is not a number") from None
    if not 0.0 < v < 1.0:
        raise OptionValueError("must be a false-alarm probability in (0, 1)")
    return v


# -- the quantizer ---------------------------------------------------------------------------------
#: --bits, wherever a quantizer is set
BITS_HELP = ("bits per real value (I and Q each) of the dithered quantizer, 1 to 16: 1 = the paper's one bit "
             "(the sign, with delta auto)")
#: --alpha's help wherever a quantizer has no decoder to follow
ALPHA_HELP = (f"dither scale in [0, 1] (default {DEFAULT_ALPHA:g}: the best of the default decoder, {DEFAULT_ALGO}, "
              "off the range grid)")
ALPHA_AUTO = "; 'auto': per sensor from the noise estimated in its frames (published in the quantizer's health)"

QUANTIZER = {
    "bits": Option(BITS_HELP, parse=pos_int),
    "alpha": Option(ALPHA_HELP + ALPHA_AUTO, parse=alpha),
    "delta": Option("'auto' (per frame the smallest step whose 2^bits levels hold the frame and its dither) or a "
                    "step in full-scale units", parse=delta),
    "delta_margin": Option("auto delta x (1 + margin)", parse=nonneg_float),
    "dither_seed": Option("dither seed (per sensor: seed * 2^32 + crc32(id))", flag="--dither-seed",
                          aliases=("--seed",), parse=nonneg_int),
}


def quantizer_part(table: str = "quantizer", alpha_help: str | None = None, seed_alias: bool = True,
                   group: str | None = None, description: str | None = None, **defaults) -> Part:
    """The quantizer's options (``--bits``, ``--alpha``, ``--delta``, ``--delta-margin``,
    ``--dither-seed``; ``--seed`` too unless ``seed_alias`` is False: a command whose
    --seed is another seed); ``alpha_help`` with ``defaults`` for a command whose alpha
    follows something else (``run``: the decoder's best)."""
    change = {} if seed_alias else {"dither_seed": {"aliases": ()}}
    if alpha_help is not None:
        change["alpha"] = {"help": alpha_help + ALPHA_AUTO}
    return Part(QuantizerConfig, table, options=QUANTIZER, change=change, defaults=defaults, group=group,
                description=description)


# -- the decoder ----------------------------------------------------------------------------------
LOCALIZER = {
    "algo": Option("the decoder", choices=tuple(ALGOS)),
    "source": Option("raw = the full-resolution baseline", choices=("quantized", "raw")),
    "fallback_pbp": Option("with qiht: decode frames without dither by PBP"),
    "full_search_every": Option("cml: start each sensor's frame from its last targets (warm start) and search from "
                                "scratch every N frames (and when the fit no longer explains the codes); 1 = always",
                                parse=pos_int),
    "pfa": Option("with --K auto: false-alarm probability per frame and test", parse=false_alarm),
    "uncertainty": Option("cml: targets without their uncertainty (sigma_range_m, sigma_angle_deg, cov_range_angle) "
                          "and p_value, positions only: for a node short of CPU", flag="--no-uncertainty",
                          negate=True),
    "min_range_m": Option(f"default {LEAKAGE_BINS} c/(2B): 1.2 m with the K-MD2's 250 MHz sweep", metavar="M",
                          parse=nonneg_float),
    "max_range_m": Option(f"default the unambiguous range N c/(2B) less {LEAKAGE_BINS} bins: 152.4 m for the K-MD2",
                          metavar="M", parse=nonneg_float),
}


@dataclass(frozen=True)
class Count:
    """``--K N|auto`` and ``--max-targets``: targets a frame, or (auto) decided per frame
    by a CFAR test, at most ``max_targets``."""

    k: int | Literal["auto"] | None = option(LocalizerConfig.k, "targets per frame; auto: decide each frame's count "
                                             "(pbp, cml) by a CFAR test, at most --max-targets", flag="--K",
                                             parse=count, kinds=frozenset({"int", "str"}))
    max_targets: int = option(DEFAULT_MAX_TARGETS, "with --K auto: the most a frame has", parse=pos_int)

    def resolve(self) -> tuple[int | None, bool]:
        """(K, auto): with ``--K auto`` the K is --max-targets."""
        return (self.max_targets, True) if self.k == "auto" else (self.k, False)


def count_of(args) -> tuple[int | None, bool]:
    return Count(args.k, args.max_targets).resolve()


def decoder_parts(k_help: str | None = None, algo_help: str | None = "the decoder", k_default=MISSING,
                  extra: tuple[str, ...] = ()) -> list[Part]:
    """``--algo`` (unless ``algo_help`` is None), ``--K`` (``k_help``; ``k_default``: a
    command's own default, None: the scene's or the truth's count), ``--max-targets``,
    ``--pfa`` and ``extra`` fields of the localizer, in the table ``[decoder]``."""
    count_change = {"k": {"help": k_help + "; auto: decide each frame's count (pbp, cml) by a CFAR test, at most "
                          "--max-targets"}} if k_help else {}
    parts = [Part(Count, "decoder", change=count_change, defaults={} if k_default is MISSING else {"k": k_default}),
             Part(LocalizerConfig, "decoder", only=("pfa", *extra), options=LOCALIZER)]
    if algo_help is not None:
        parts.insert(0, Part(LocalizerConfig, "decoder", only=("algo",), options=LOCALIZER,
                             change={"algo": {"help": f"{algo_help} (default {DEFAULT_ALGO})"}}))
    return parts


GATE = Part(LocalizerConfig, "gate", only=("min_range_m", "max_range_m"), options=LOCALIZER, group="range gate",
            description=f"targets are sought only in [MIN, MAX] m; the default keeps out {LEAKAGE_BINS} range bins at "
            "each end of the circular range axis (TX-to-RX leakage sits within the first bin or two, and leaks into "
            "the top ones)")


# -- tracks ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Tracks:
    """``--track``: tracks after the localizer."""

    track: bool = option(False, "publish radar/<sensor>/tracks, one JSON message a frame")


TRACKER = {"integrate_s": Option("refine each static track on the codes of its last SECONDS of frames decoded "
                                 "together (0: no integration)", flag="--integrate", metavar="SECONDS",
                                 parse=nonneg_float)}
_TRACKS_GROUP = ("tracks of the targets (pipeline.dsp.track): an id, a velocity, an uncertainty and a static flag per "
                 "track, on radar/<sensor>/tracks")
TRACKS = [Part(Tracks, "tracks", description=_TRACKS_GROUP),
          Part(TrackerConfig, "tracks", options=TRACKER)]


def tracker_of(args) -> TrackerConfig | None:
    """The tracker of ``--track`` (None without it)."""
    return TrackerConfig(integrate_s=args.integrate_s) if args.track else None


# -- the zenoh session and --secure ------------------------------------------------------------------
@dataclass(frozen=True)
class Security:
    """``--secure DIR`` and ``--identity NAME``."""

    secure: Path | None = option(None, "mutual TLS and the access-control policy of DIR (made by `qradar security "
                                 "init`); only tls/ endpoints", metavar="DIR")
    identity: str | None = option(None, "with --secure: the certificate to use (default: this command's role, e.g. "
                                  "quantizer, localizer, recorder, viewer, router, sensor-<id>)", metavar="NAME")


def zenoh_parts(modes: tuple[str, ...] = ("peer", "client")) -> list[Part]:
    """The session's options (``--mode`` among ``modes``, none for one mode) and ``--secure``."""
    only = ("config_file", "connect", "listen", "mode", "prefix") if len(modes) > 1 else \
        ("config_file", "connect", "listen", "prefix")
    return [Part(BusConfig, "zenoh", only=only, change={"mode": {"choices": modes}}),
            Part(Security, "security", group="zenoh")]


# -- a node's input and run --------------------------------------------------------------------------
QUEUE = Part(QueueConfig, "queue", group="input queue")
SERVE = Part(ServeConfig, "serve", group="sensors served",
             description="several processes (on one host or many) share the sensors")
INTAKE = Part(IntakeBudget, "intake", group="intake budgets",
              description="checked where each message arrives, before any work; a message over a budget is dropped "
              "and counted (over_budget, refused), so a flooding sender cannot delay the others (0: no limit)")


@dataclass(frozen=True)
class NodeRun:
    """How long a stand-alone node runs and what it says meanwhile."""

    duration_s: float | None = option(None, "stop after S seconds (default: Ctrl-C)", flag="--duration",
                                      parse=nonneg_float)
    quiet: bool = option(False, f"no start line and no status line every {STATUS_PERIOD_S:g} s on stderr (rates, "
                         "sensors, losses, the last targets)")
    parent_pid: int | None = option(None, "stop within a second once process PID is no longer this one's parent, "
                                    "however it died (qradar up and run set it for their children)", metavar="PID",
                                    parse=pos_int)


def node_part(*only: str, **change) -> Part:
    return Part(NodeRun, only=only or None, change={k: {"help": v} for k, v in change.items()})


# -- switches --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Switches:
    """Switches many commands have, each with its command's help."""

    json: bool = option(False, "print the result as one JSON object on stdout")
    force: bool = option(False, "replace the output if it exists (without it: refused, nothing written)")


def switches(**helps: str) -> Part:
    """``--json`` and/or ``--force`` (the keys of ``helps``), with these helps."""
    return Part(Switches, only=tuple(helps), change={k: {"help": v} for k, v in helps.items()})


def force_help(what: str) -> str:
    """``--force``: the one overwrite policy (replay.outputs)."""
    return f"replace {what} if it exists (without it: refused, nothing written)"


@dataclass(frozen=True)
class CalibrationFile:
    """``--calibration CAL.json``."""

    calibration: Path | None = option(
        None, "remove the front end measured by `qradar calibrate` (background: DC, leakage, clutter; I/Q imbalance; "
        "receiver 2's gain and phase) where frames are quantized; raw frames and their recordings keep what the "
        "sensor sent", metavar="CAL.json")


CALIBRATION = Part(CalibrationFile)


@dataclass(frozen=True)
class Edge:
    """Edge quantization in a sensor's own process (``--quantize`` / ``--quantized``)."""

    edge_quantize: bool = option(False, "publish quantized frames (raw ones only with --raw-every)")
    raw_every: int | None = option(None, "also publish the raw frames whose seq is a multiple of N (e.g. for "
                                   "recording; default 0 = none)", metavar="N", parse=nonneg_int)


def edge_parts(switch: str) -> list[Part]:
    """``switch`` (--quantized / --quantize), the quantizer's options, --raw-every and
    --calibration, in one ``--help`` group (table ``[edge]``)."""
    group, description = "edge quantization", ("quantize in this process, with the quantize node's dither seed rule "
                                               "and options, and publish 1-bit frames on <prefix>/<id>/quantized")
    return [Part(Edge, "edge", group=group, description=description,
                 change={"edge_quantize": {"flag": switch},
                         "raw_every": {"help": f"with {switch}: also publish the raw frames whose seq is a multiple "
                                       "of N (e.g. for recording; default 0 = none)"}}),
            quantizer_part("edge", seed_alias=False, group=group),
            Part(CalibrationFile, "edge", group=group)]


def edge_quantizer(args) -> tuple[QuantizerConfig | None, int | None]:
    """(quantizer or None, raw_every) of :func:`edge_parts`."""
    if not args.edge_quantize:
        if args.raw_every is not None:
            raise ParameterError("--raw-every is for edge quantization (--quantized / --quantize)")
        if args.calibration is not None:
            raise ParameterError("--calibration is applied where frames are quantized: give --quantized / "
                                 "--quantize too (or --calibration to the quantize node)")
        return None, None
    return quantizer_of(args), args.raw_every


def quantizer_of(args, alpha: float | str | None = None) -> QuantizerConfig:
    return QuantizerConfig(bits=args.bits, alpha=args.alpha if alpha is None else alpha, delta=args.delta,
                           delta_margin=args.delta_margin, dither_seed=args.dither_seed)


# -- qradar up: which host runs which node ----------------------------------------------------------
#: the name of the host of every node a lab file's [hosts] table does not place
LOCALHOST = "localhost"


@dataclass(frozen=True)
class Hosts:
    """``[hosts]`` of a lab file: the host whose ``qradar up --host NAME`` starts each node
    (a sensor's driver: its ``[[sensor]]`` table's ``host``); ``qradar run`` runs them all
    in one process and reads none of it."""

    default: str = option(LOCALHOST, "qradar up: the host of every node not placed otherwise", cli=False)
    router: str | None = option(None, "qradar up: the host of the zenoh router every node joins", cli=False)
    sources: str | None = option(None, "qradar up: the host of the simulated sensors (qradar source), without "
                                 "[[sensor]]", cli=False)
    quantize: str | None = option(None, "qradar up: the host of the quantizer", cli=False)
    localize: str | None = option(None, "qradar up: the host of the localizer", cli=False)
    record: str | None = option(None, "qradar up: the host of the recorder", cli=False)
    view: str | None = option(None, "qradar up: the host of the views ([views] foxglove, web)", cli=False)


HOSTS = Part(Hosts, "hosts", dests={f: f"host_{f}" for f in Hosts.__dataclass_fields__})
