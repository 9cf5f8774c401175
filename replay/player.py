"""The player: an MCAP recording back onto zenoh, every qradar channel as recorded, with
its original timing scaled by ``rate`` or as fast as the subscribers take it (``fast``:
publishers block rather than drop). ``prefix`` remaps the first key chunk(s), so
replayed data cannot be mistaken for live data. The recording is read in time by
:func:`replay.source.recorded_messages`, as the recording frame source reads it: every
chunk's CRC checked, a damaged chunk named in the log and its messages counted in
``lost``, never played."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import zenoh

from pipeline.bus.session import BusConfig, check_prefix
from pipeline.errors import ParameterError
from radar_driver.options import option, pos_float

from .errors import NoQradarChannelsError, ReplayError
from .mcapio import McapFile, qradar_channels
from .source import recorded_messages

log = logging.getLogger("qradar.replay")


@dataclass(frozen=True)
class PlayConfig:
    """How a recording plays: at ``rate`` times its pace, or ``fast``; once or in a
    ``loop``; from ``start_s`` to ``end_s`` (s from its start); the channels of
    ``topics``; under ``prefix`` (None: the recorded one)."""

    rate: float = option(1.0, "speed factor of the original timing (default 1)", parse=pos_float)
    fast: bool = option(False, "as fast as subscribers take it (publishers block, no drops)")
    loop: bool = option(False, "play the file again from its start, until Ctrl-C")
    start_s: float | None = option(None, "seconds from the start of the file", flag="--start")
    end_s: float | None = option(None, "seconds from the start of the file", flag="--end")
    topics: str | None = option(None, "key expression of the channels to play")
    prefix: str | None = option(None, "publish under this key prefix instead of the recorded one (e.g. replay)",
                                flag="--replay-prefix")

    def __post_init__(self) -> None:
        if not self.rate > 0:
            raise ReplayError(f"--rate {self.rate!r} must be > 0")
        if self.prefix is not None:
            try:
                check_prefix(self.prefix, "--replay-prefix")
            except ParameterError as exc:
                raise ReplayError(str(exc)) from None
        if self.start_s is not None and self.end_s is not None and self.end_s <= self.start_s:
            raise ReplayError(f"--end {self.end_s} must come after --start {self.start_s}")


@dataclass
class PlayResult:
    published: int = 0
    loops: int = 0
    truncated: bool = False
    seconds: float = 0.0
    lost: int = 0  # messages of damaged chunks (not played), in one pass over the file
    damaged: int = 0  # damaged chunks (each logged once)


def remap(key: str, recorded_prefix: str, prefix: str | None) -> str:
    if prefix is None or not key.startswith(recorded_prefix + "/"):
        return key
    return prefix + key[len(recorded_prefix):]


def nothing_selected(path, cfg: PlayConfig, channels: dict) -> str:
    """The one line that says why ``cfg`` plays nothing of a recording with qradar
    ``channels``: its ``topics`` match none of them (named), or its window holds no message."""
    topics = sorted({c.topic for c in qradar_channels(channels).values()})
    if cfg.topics and not any(zenoh.KeyExpr(cfg.topics).intersects(t) for t in topics):
        return f"--topics {cfg.topics!r} matches none of the channels of {path}: {', '.join(topics)}"
    window = " ".join(f"{flag} {v:g}" for flag, v in (("--start", cfg.start_s), ("--end", cfg.end_s)) if v is not None)
    if not window:
        return f"{path} holds no message on its qradar channels ({', '.join(topics)})" + (
            f" that --topics {cfg.topics!r} selects" if cfg.topics else "")
    return (f"{path} has no message {'of --topics ' + repr(cfg.topics) + ' ' if cfg.topics else ''}"
            f"within {window} (s from its first message; `qradar info {path}` gives its length)")


def play(path, bus: BusConfig, cfg: PlayConfig, session: zenoh.Session | None = None,
         stop: threading.Event | None = None) -> PlayResult:
    """Publish the qradar channels of ``path``; returns what was done."""
    f = McapFile(path)
    own = session is None
    session = session or bus.open()
    stop = stop or threading.Event()
    result = PlayResult()
    t_wall0 = time.monotonic()
    selector = zenoh.KeyExpr(cfg.topics) if cfg.topics else None
    publishers: dict[str, zenoh.Publisher] = {}
    try:
        while not stop.is_set():
            recorded_prefix = None
            seen_qradar = False
            for ch, msg in recorded_messages(f, None if cfg.fast else cfg.rate, stop, cfg.start_s, cfg.end_s,
                                             None if selector is None else selector.intersects):
                seen_qradar = True
                if recorded_prefix is None:
                    recorded_prefix = ch.topic.rsplit("/", 2)[0]
                key = remap(ch.topic, recorded_prefix, cfg.prefix)
                pub = publishers.get(key)
                if pub is None:
                    encoding = zenoh.Encoding.APPLICATION_JSON if ch.message_encoding == "json" \
                        else zenoh.Encoding.APPLICATION_OCTET_STREAM
                    pub = session.declare_publisher(key, encoding=encoding,
                                                    congestion_control=zenoh.CongestionControl.BLOCK)
                    publishers[key] = pub
                pub.put(msg.data)
                result.published += 1
            if f.truncated and not result.truncated:
                result.truncated = True
                log.warning("%s is cut short (%s); played up to its last complete chunk", path, f.truncation_reason)
            if f.complete and result.loops == 0 and not f.intact:
                result.lost, result.damaged = f.lost, len(f.damaged)
                f.warn(log, "not played")
            if not seen_qradar and not stop.is_set() and not qradar_channels(f.channels):
                raise NoQradarChannelsError(
                    f"{path} has no qradar channels (<prefix>/<sensor>/raw|quantized|targets|health); "
                    f"its topics: {sorted({c.topic for c in f.channels.values()}) or 'none'}")
            if result.published == 0 and result.loops == 0 and not stop.is_set() and f.intact:
                raise ReplayError(nothing_selected(path, cfg, f.channels))
            result.loops += 1
            if not cfg.loop or stop.is_set():
                break
    finally:
        for pub in publishers.values():
            pub.undeclare()
        if own:
            session.close()
    result.seconds = time.monotonic() - t_wall0
    return result
