"""The JSON messages of one process decoded once for all of its readers.

In ``qradar run`` one zenoh session hands each targets, tracks and health message to
several readers of the same process: the recorder (which checks what it writes), the live
monitor and the views. Each reader is given the run's :class:`DecodedOnce` and asks it for
the message of a payload; the first asker parses and checks it (the readers' one edge:
:func:`pipeline.wire.load_json` and the format's checks), the others get the same message
object while its payload is among the last ``capacity`` ones (a reader far behind parses
again: slower, never wrong). A payload that does not decode raises the same WireError for
each of them. Messages handed out are shared: readers do not change them. A reader given
none (a node alone in its process) decodes for itself."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Callable

from pipeline.errors import WireError
from pipeline.wire.messages import HealthMsg, TargetsMsg, TracksMsg, decode_health, decode_targets, decode_tracks

#: the decoder of each JSON topic
JSON_DECODERS: dict[str, Callable] = {"targets": decode_targets, "tracks": decode_tracks, "health": decode_health}

Message = TargetsMsg | TracksMsg | HealthMsg


class DecodedOnce:
    """``decode(topic, payload, source)``: the message of a JSON payload, parsed once per
    process while among the last ``capacity`` payloads (thread-safe). ``parses``: payloads
    parsed; ``hits``: messages handed out without parsing."""

    def __init__(self, capacity: int = 512):
        if not (isinstance(capacity, int) and capacity >= 1):
            raise ValueError(f"capacity={capacity!r} must be an integer >= 1")
        self.capacity = capacity
        self._done: OrderedDict[tuple[str, bytes], Message | str] = OrderedDict()  # str: why it does not decode
        self._lock = threading.Lock()
        self.parses = 0
        self.hits = 0

    def decode(self, topic: str, payload: bytes, source: str) -> Message:
        """The message of ``payload`` on ``topic`` (targets, tracks or health); a WireError
        naming ``source`` when it does not decode."""
        key = (topic, bytes(payload))
        with self._lock:
            got = self._done.get(key)
            if got is not None:
                self._done.move_to_end(key)
                self.hits += 1
        if got is None:
            try:
                got = JSON_DECODERS[topic](payload, source)
            except WireError as exc:
                got = str(exc)
            with self._lock:
                self.parses += 1
                self._done[key] = got
                if len(self._done) > self.capacity:
                    self._done.popitem(last=False)
        if isinstance(got, str):
            raise WireError(got)
        return got


def decoder(shared: DecodedOnce | None) -> Callable[[str, bytes, str], Message]:
    """``shared.decode``, or the topic's own decoder for a reader alone in its process."""
    if shared is not None:
        return shared.decode
    return lambda topic, payload, source: JSON_DECODERS[topic](payload, source)
