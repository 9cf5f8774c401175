"""What the recorder lets into a recording: every message checked before any byte of it
is written, with the checks the nodes apply to what they take in.

- **topic** (``refused_topic``): the key is ``<prefix>/<sensor>/<topic>`` with a valid
  sensor id and a qradar topic (raw, quantized, targets, tracks, health);
- **size** (``refused_size``): a raw or quantized frame has a length one of the announced
  radar configurations gives it (``radar`` with 1..``max_ramps`` ramps, as the quantize and
  localize nodes announce them); a JSON message is at most MAX_JSON_BYTES;
- **shape** (``refused_shape``): the payload decodes with the decoder of its topic (the
  frame codecs' vectorized header checks, :func:`pipeline.nodes.frame_codec.check_frames`:
  sensor id of the key, announced config id and its M; raw samples finite and within
  MAX_SAMPLE; the JSON decoders of targets, tracks and health), and the sensor id it
  carries is its key's;
- **time** (``refused_time``): its timestamps (a frame's ``timestamp_ns``; a JSON
  message's ``timestamp_ns`` and ``published_ns``) and the log time are integer ns in
  [0, 2**63), what an MCAP record and qradar's int64 clocks both hold.

The same checks whoever published the message: a sensor's frames, and the health every
identity may publish (a viewer's, a recorder's). Nothing here does I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.nodes.counters import NO_SENSOR
from pipeline.nodes.frame_codec import CODECS, MAX_SAMPLE, bad_samples, check_frames, radar_configs
from pipeline.nodes.intake import QueuedFrame
from pipeline.wire import TOPICS, HealthMsg, QuantizedGroup, TargetsMsg, TracksMsg, WireError
from pipeline.wire.shared import DecodedOnce, decoder
from radar_driver.model import RadarConfig

from .mcapio import MAX_TIME_NS

#: the kinds of refusal the recorder counts, per sensor (docs/recording.md)
REFUSED_KINDS = ("refused_time", "refused_size", "refused_shape", "refused_topic")
#: the largest JSON message (targets, tracks, health) a recording takes, bytes
MAX_JSON_BYTES = 256 * 1024


@dataclass(frozen=True)
class Admitted:
    """A message to write: its position in the batch, its publish time (its own
    timestamp, ns), its MCAP sequence (its seq) and what the recorder derives channels from
    (replay.derived): a JSON message decoded (``message``: targets, tracks, health), a
    quantized frame as its decoded group and its row in it (``frames``, ``row``)."""

    index: int
    publish_ns: int
    sequence: int
    message: TargetsMsg | TracksMsg | HealthMsg | None = None
    frames: QuantizedGroup | None = None
    row: int = 0

    @property
    def targets(self) -> TargetsMsg | None:
        return self.message if isinstance(self.message, TargetsMsg) else None


@dataclass(frozen=True)
class Refused:
    """A message refused: its position in the batch, the kind (one of REFUSED_KINDS), the
    node counter it also counts in (``decode_errors`` or ``invalid_frames``) and why
    (one line naming the key)."""

    index: int
    kind: str
    counter: str
    reason: str


def _time_ok(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, np.integer)) and 0 <= value < MAX_TIME_NS


class Admission:
    """The recorder's checks for the announced configurations ``radar`` with 1..``max_ramps``
    ramps per frame (the nodes' defaults: the K-MD2 and 16); ``decoded``: the process's
    JSON messages decoded once (pipeline.wire.shared; None: decoded here)."""

    def __init__(self, radar: RadarConfig | None = None, max_ramps: int = 16, decoded: DecodedOnce | None = None):
        self._decode = decoder(decoded)
        self.configs = radar_configs(radar or RadarConfig(), max_ramps)
        ms = {c.n_measurements for c in self.configs.values()}
        self.lengths = {topic: CODECS[topic].lengths(ms) for topic in CODECS}

    def before_copy(self, topic: str, sensor: str, n_bytes: int) -> tuple[str, str] | None:
        """(kind, why) a message of ``n_bytes`` on a key of ``sensor`` (NO_SENSOR: none
        valid) and ``topic`` is refused before its payload is copied; None: go on."""
        if sensor == NO_SENSOR or topic not in TOPICS:
            return "refused_topic", "not <prefix>/<sensor id>/<raw|quantized|targets|tracks|health> (not recorded)"
        lengths = self.lengths.get(topic)
        if lengths is not None:
            if n_bytes not in lengths:
                return "refused_size", (f"{n_bytes} bytes, a length no announced radar configuration gives a "
                                        f"{topic} frame ({len(self.configs)} configs, {min(lengths)}-{max(lengths)} "
                                        "bytes; not recorded)")
        elif n_bytes > MAX_JSON_BYTES:
            return "refused_size", f"{n_bytes} bytes, more than the {MAX_JSON_BYTES} a JSON message may have (not recorded)"
        return None

    def check(self, batch: list[QueuedFrame], key_sensors: list[str]) -> tuple[list[Admitted], list[Refused]]:
        """The messages of ``batch`` to write (in batch order) and those refused;
        ``key_sensors``: the sensor id of each message's key (NO_SENSOR: none valid). Frames
        of a topic are decoded together (one vectorized pass per length)."""
        admitted: list[Admitted] = []
        refused: list[Refused] = []
        by_topic: dict[str, list[int]] = {}
        for i, item in enumerate(batch):
            topic = item.key.rsplit("/", 1)[-1]
            why = self.before_copy(topic, key_sensors[i], len(item.payload))
            if why is not None:  # (admitted before a change of configuration: checked again)
                refused.append(Refused(i, why[0], "invalid_frames", f"{item.key}: {why[1]}"))
            elif not _time_ok(item.received_ns):
                refused.append(Refused(i, "refused_time", "invalid_frames",
                                       f"{item.key}: log time {item.received_ns} outside [0, 2**63) ns (the clock?)"))
            else:
                by_topic.setdefault(topic, []).append(i)
        for topic, idx in by_topic.items():
            if topic in CODECS:
                self._frames(topic, [batch[i] for i in idx], [key_sensors[i] for i in idx], idx, admitted, refused)
            else:
                for i in idx:
                    self._json(topic, batch[i], key_sensors[i], i, admitted, refused)
        admitted.sort(key=lambda a: a.index)
        return admitted, refused

    def _frames(self, topic: str, items: list[QueuedFrame], sensors: list[str], idx: list[int],
                admitted: list[Admitted], refused: list[Refused]) -> None:
        keys = [it.key for it in items]
        groups, bad = check_frames(CODECS[topic], self.configs, [it.payload for it in items], keys, sensors)
        refused += [Refused(idx[j], "refused_shape", counter, why) for j, counter, why in bad]
        for g in groups:
            h = g.headers
            samples_bad = bad_samples(g.data) if topic == "raw" else np.zeros(len(h), dtype=bool)
            for j, pos, seq, ts in zip(range(len(h)), g.index.tolist(), h.seq.tolist(), h.timestamp_ns.tolist()):
                i = idx[pos]
                if samples_bad[j]:
                    refused.append(Refused(i, "refused_shape", "invalid_frames",
                                           f"frame {seq} from {keys[pos]}: a sample is not finite or beyond "
                                           f"{MAX_SAMPLE:g} full scale"))
                elif not _time_ok(ts):
                    refused.append(Refused(i, "refused_time", "invalid_frames",
                                           f"frame {seq} from {keys[pos]}: timestamp_ns={ts} outside [0, 2**63)"))
                else:
                    admitted.append(Admitted(i, ts, seq, frames=g if topic == "quantized" else None, row=j))

    def _json(self, topic: str, item: QueuedFrame, sensor: str, i: int, admitted: list[Admitted],
              refused: list[Refused]) -> None:
        try:
            msg = self._decode(topic, item.payload, item.key)
        except (WireError, ValueError, RecursionError) as exc:
            refused.append(Refused(i, "refused_shape", "decode_errors", str(exc)))
            return
        if msg.sensor_id != sensor:
            refused.append(Refused(i, "refused_shape", "decode_errors",
                                   f"{topic} from {item.key}: sensor id {msg.sensor_id!r} does not match the key"))
            return
        for name in ("timestamp_ns", "published_ns"):
            value = getattr(msg, name, 0)
            if not _time_ok(value):
                refused.append(Refused(i, "refused_time", "invalid_frames",
                                       f"{topic} from {item.key}: {name}={value!r} outside [0, 2**63)"))
                return
        seq = getattr(msg, "seq", 0)
        admitted.append(Admitted(i, msg.timestamp_ns, seq, msg))


class RefusalCounts:
    """Messages refused by sender and kind: one count per live sensor (and one for the
    unknown senders, NO_SENSOR), the expired ones' summed (:meth:`retire`), so the state
    lives as long as the sensors. Not locked: its owner holds its own lock around it."""

    def __init__(self) -> None:
        self._by_sender: dict[str, dict[str, int]] = {}
        self._retired = dict.fromkeys(REFUSED_KINDS, 0)

    def add(self, sender: str, kind: str, n: int = 1) -> None:
        counts = self._by_sender.get(sender)
        if counts is None:
            counts = self._by_sender[sender] = dict.fromkeys(REFUSED_KINDS, 0)
        counts[kind] += n

    def retire(self, sender: str) -> None:
        """An expired sender: its counts go into the totals, its entry goes."""
        for kind, n in self._by_sender.pop(sender, {}).items():
            self._retired[kind] += n

    def totals(self) -> dict[str, int]:
        """By kind, expired senders included."""
        out = dict(self._retired)
        for counts in self._by_sender.values():
            for kind, n in counts.items():
                out[kind] += n
        return out

    def of(self, sender: str) -> dict[str, int]:
        return dict(self._by_sender.get(sender) or dict.fromkeys(REFUSED_KINDS, 0))

    def listed(self, limit: int, unknown: str) -> dict[str, dict[str, int]]:
        """The ``limit`` live senders with the most refused (NO_SENSOR named ``unknown``),
        the rest summed under ``others``."""
        ranked = sorted(((s, c) for s, c in self._by_sender.items() if any(c.values())),
                        key=lambda sc: -sum(sc[1].values()))
        out = {(unknown if s == NO_SENSOR else s): dict(c) for s, c in ranked[:limit]}
        if len(ranked) > limit:
            others = dict.fromkeys(REFUSED_KINDS, 0)
            for _, counts in ranked[limit:]:
                for kind, n in counts.items():
                    others[kind] += n
            out["others"] = others
        return out
