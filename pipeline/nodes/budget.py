"""What one sender may put into a node: budgets checked where each message arrives.

A processing node checks each message, in zenoh's callback before it copies anything,
against two budgets (token buckets refilled continuously, each holding ``burst_s`` of its
rate):

- per key (``<prefix>/<sensor>/<topic>``): ``rate_hz`` messages and ``bytes_per_s``
  payload bytes a second. A K-MD2 sends 20 frames a second; the default allows five
  times that (and 64 MB/s: a 1 MB range-Doppler cube 64 times a second), with a burst of
  one second of it;
- per node: ``new_sensors_per_s`` sensor ids it has no state for (a burst of
  ``new_sensors_burst``, enough for a fleet that starts at once).

A message over a budget is dropped at once and counted: against its sensor
(``over_budget``), or, for an id not admitted, in the aggregate of unknown senders
(``refused``). So a flooding sender costs a node a few microseconds a message and a
bounded share of its worker, and the messages of honest sensors never wait behind its
excess (in zenoh's transport, in the callback, or in the queue).
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.errors import ParameterError
from radar_driver.options import nonneg_float, option

#: defaults (see the module's docstring): 5 x a K-MD2's 20 frames/s; 64 MB/s (a 1 MB range-Doppler
#: cube at 64 frames/s); one second
DEFAULT_RATE_HZ = 100.0
DEFAULT_BYTES_PER_S = 64e6
DEFAULT_BURST_S = 1.0
DEFAULT_NEW_SENSORS_PER_S = 100.0
DEFAULT_NEW_SENSORS_BURST = 1000
#: the most topics of one sensor with a bucket of their own (more share one)
MAX_TOPIC_BUCKETS = 16


@dataclass(frozen=True)
class IntakeBudget:
    """A node's intake budgets. rate_hz: messages/s per key; bytes_per_s: payload bytes/s
    per key; burst_s: seconds of budget a bucket holds; new_sensors_per_s, new_sensors_burst:
    admission of sensor ids the node has no state for. 0 turns a budget off."""

    rate_hz: float = option(DEFAULT_RATE_HZ, f"messages a second per key <prefix>/<sensor>/<topic> (default "
                            f"{DEFAULT_RATE_HZ:g}: 5 x a K-MD2's 20 frames/s), with a burst of one second",
                            flag="--budget-rate", metavar="HZ", parse=nonneg_float)
    bytes_per_s: float = option(DEFAULT_BYTES_PER_S, "payload megabytes a second per key", flag="--budget-mb",
                                metavar="MB", parse=nonneg_float, scale=1e6)
    burst_s: float = DEFAULT_BURST_S
    new_sensors_per_s: float = option(DEFAULT_NEW_SENSORS_PER_S, f"new sensor ids admitted a second (after a burst "
                                      f"of {DEFAULT_NEW_SENSORS_BURST}); the frames of ids not admitted count as "
                                      "refused", flag="--admit-rate", metavar="N", parse=nonneg_float)
    new_sensors_burst: int = DEFAULT_NEW_SENSORS_BURST

    def __post_init__(self) -> None:
        for name in ("rate_hz", "bytes_per_s", "new_sensors_per_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 <= v < float("inf")):
                raise ParameterError(f"intake budget {name}={v!r} must be a finite number >= 0 (0: no limit)")
        if not (isinstance(self.burst_s, (int, float)) and 0.01 <= self.burst_s <= 60):
            raise ParameterError(f"intake budget burst_s={self.burst_s!r} must be in [0.01, 60] s")
        if not (isinstance(self.new_sensors_burst, int) and self.new_sensors_burst >= 1):
            raise ParameterError(f"intake budget new_sensors_burst={self.new_sensors_burst!r} must be an integer >= 1")

    @classmethod
    def unlimited(cls) -> "IntakeBudget":
        return cls(rate_hz=0.0, bytes_per_s=0.0, new_sensors_per_s=0.0)

    def describe(self) -> str:
        def lim(v, unit):
            return "no limit" if not v else f"{v:g} {unit}"
        return (f"{lim(self.rate_hz, 'messages/s')} and {lim(self.bytes_per_s / 1e6, 'MB/s')} per key "
                f"(burst {self.burst_s:g} s), {lim(self.new_sensors_per_s, 'new sensor ids/s')} "
                f"(burst {self.new_sensors_burst})")


class TokenBucket:
    """``rate`` tokens a second up to ``capacity``; starts full. Not thread-safe (the
    node's lock guards it)."""

    __slots__ = ("rate", "capacity", "tokens", "t")

    def __init__(self, rate: float, capacity: float, now: float):
        self.rate, self.capacity, self.tokens, self.t = rate, capacity, capacity, now

    def take(self, now: float, n: float = 1.0) -> bool:
        """Take ``n`` tokens if there are (True), else take none (False)."""
        tokens = self.tokens + (now - self.t) * self.rate
        self.t = now
        if tokens > self.capacity:
            tokens = self.capacity
        if tokens < n:
            self.tokens = tokens
            return False
        self.tokens = tokens - n
        return True


class KeyBudget:
    """The message and byte buckets of one key."""

    __slots__ = ("frames", "nbytes")

    def __init__(self, budget: IntakeBudget, now: float):
        self.frames = TokenBucket(budget.rate_hz, budget.rate_hz * budget.burst_s, now) if budget.rate_hz else None
        self.nbytes = (TokenBucket(budget.bytes_per_s, budget.bytes_per_s * budget.burst_s, now)
                       if budget.bytes_per_s else None)

    def admit(self, now: float, n_bytes: int) -> str | None:
        """None when the message fits the budget (its tokens taken), else why not."""
        if self.frames is not None and not self.frames.take(now):
            return "messages/s"
        if self.nbytes is not None and not self.nbytes.take(now, n_bytes):
            if self.frames is not None:
                self.frames.tokens += 1  # not taken after all
            return "bytes/s"
        return None
