"""The range gate: the interval of ranges ``[min_range_m, max_range_m]`` a decoder
searches for targets (issue 23).

A real FMCW front end puts its strongest return within the first range bin or two:
TX-to-RX coupling and the radome, at a few tens of centimetres (docs/design.md, "A real front
end is not the paper's model"). A decoder that searches the whole range axis reports it
as a target, and with a fixed K it takes a real target's place. The gate keeps it out:

* PBP and ``qiht`` (:mod:`pipeline.dsp.localize`, :mod:`pipeline.dsp.decode`) pick their support
  among the range bins inside the gate only (a mask on the range axis), and their
  detection statistic and ``K auto`` test are taken over those bins;
* ``cml`` (:mod:`pipeline.dsp.cml`) detects on the oversampled grid inside the gate only, and
  its Levenberg--Marquardt steps are clamped to it: a target may not leave the gate.

The default (:meth:`RangeGate.default`) keeps out the first ``LEAKAGE_BINS`` range bins,
``[0, 2 c / (2B))`` (1.2 m for the K-MD2's 250 MHz sweep), and, because the range axis of
complex samples is circular (bin N - 1 is next to bin 0: a return at 0.3 m leaks into the
top bins as much as into bin 2), as many at its top end: ``[2 dR, N dR - 2 dR]``, that is
1.2 m to 152.4 m for the K-MD2. The live localizer, ``qradar run`` and ``qradar
reprocess`` use it; the library functions and the Monte Carlo search the whole axis unless
given a gate (the paper's protocol has no leakage; docs/science.md, "The range gate").

Only the gate's ends are stored, in metres; :meth:`RangeGate.check` tests them against a
radar configuration (``0 <= min < max <= N dR``, at least one range bin inside).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.errors import ParameterError

#: range bins the default gate keeps out at each end of the range axis (TX-to-RX leakage at
#: a few tens of centimetres fills bin 0 and bin 1, and, the axis being circular, the top bins)
LEAKAGE_BINS = 2
#: ranges this close to a gate's end count as on it (floating-point rounding of n dR), m
EDGE_TOLERANCE_M = 1e-9


def check_range_m(name: str, value) -> float:
    """``value`` as a float if it is a finite number of metres >= 0, else a ParameterError."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not np.isfinite(value) or value < 0:
        shown = f"{value:g}" if isinstance(value, (int, float, np.integer, np.floating)) else repr(value)
        raise ParameterError(f"{name}={shown} must be a finite number of metres >= 0")
    return float(value)


@dataclass(frozen=True)
class RangeGate:
    """Ranges ``[min_range_m, max_range_m]`` (m, both ends included) a decoder searches."""

    min_range_m: float
    max_range_m: float

    def __post_init__(self) -> None:
        lo = check_range_m("min_range_m", self.min_range_m)
        hi = check_range_m("max_range_m", self.max_range_m)
        if not lo < hi:
            raise ParameterError(f"range gate: min_range_m={lo:g} must be below max_range_m={hi:g}")
        object.__setattr__(self, "min_range_m", lo)
        object.__setattr__(self, "max_range_m", hi)

    @classmethod
    def default(cls, radar: RadarConfig) -> "RangeGate":
        """``[LEAKAGE_BINS dR, N dR - LEAKAGE_BINS dR]``: the leakage bins kept out at both
        ends of the circular range axis (the whole axis when it is too short for that)."""
        dr, top = radar.range_resolution_m, radar.max_range_m
        if radar.samples_per_ramp <= 4 * LEAKAGE_BINS:
            return cls(0.0, top)
        return cls(LEAKAGE_BINS * dr, top - LEAKAGE_BINS * dr)

    @classmethod
    def full(cls, radar: RadarConfig) -> "RangeGate":
        """The whole range axis, ``[0, N dR]``."""
        return cls(0.0, radar.max_range_m)

    @classmethod
    def resolve(cls, min_range_m: float | None, max_range_m: float | None, radar: RadarConfig) -> "RangeGate":
        """The gate of two options (None: the end of :meth:`default`), checked against ``radar``."""
        default = cls.default(radar)
        lo = default.min_range_m if min_range_m is None else check_range_m("min_range_m", min_range_m)
        hi = default.max_range_m if max_range_m is None else check_range_m("max_range_m", max_range_m)
        for name, value in (("min_range_m", min_range_m), ("max_range_m", max_range_m)):
            if value is not None and value > radar.max_range_m + EDGE_TOLERANCE_M:
                raise ParameterError(f"range gate: {name}={value:g} is beyond the radar's unambiguous range "
                                     f"N c/(2B) = {radar.max_range_m:g} m")
        if not lo < hi:
            raise ParameterError(f"range gate: min_range_m={lo:g} must be below max_range_m={hi:g}"
                                 + (" (the default max)" if max_range_m is None else
                                    " (the default min)" if min_range_m is None else ""))
        return cls(lo, hi).check(radar)

    def check(self, radar: RadarConfig) -> "RangeGate":
        """This gate if it fits ``radar``'s range axis ``[0, N dR]`` and holds a range bin,
        else a one-line ParameterError."""
        top = radar.max_range_m
        if self.max_range_m > top + EDGE_TOLERANCE_M:
            raise ParameterError(f"range gate: max_range_m={self.max_range_m:g} is beyond the radar's unambiguous "
                                 f"range N c/(2B) = {top:g} m")
        if not _bin_mask(self, radar).any():
            raise ParameterError(f"range gate [{self.min_range_m:g}, {self.max_range_m:g}] m holds no range bin "
                                 f"(bins every {radar.range_resolution_m:g} m)")
        return self

    def bins(self, radar: RadarConfig) -> tuple[float, float]:
        """The gate's ends in range bins, ``(min / dR, max / dR)``."""
        dr = radar.range_resolution_m
        return self.min_range_m / dr, self.max_range_m / dr

    def bin_mask(self, radar: RadarConfig) -> np.ndarray | None:
        """(N,) bool, True for the range bins ``n dR`` inside the gate; None when every bin
        is (nothing to mask). Read-only."""
        mask = _bin_mask(self, radar)
        return None if mask.all() else mask

    def to_dict(self) -> dict[str, float]:
        return {"min_range_m": self.min_range_m, "max_range_m": self.max_range_m}

    def holds(self, range_m):
        """Whether ranges ``range_m`` (m, scalar or array) lie inside the gate (its ends
        EDGE_TOLERANCE_M wider)."""
        return (range_m >= self.min_range_m - EDGE_TOLERANCE_M) & (range_m <= self.max_range_m + EDGE_TOLERANCE_M)


@lru_cache(maxsize=64)
def _bin_mask(gate: RangeGate, radar: RadarConfig) -> np.ndarray:
    r = radar.range_grid_m()
    mask = gate.holds(r)
    mask.flags.writeable = False
    return mask


def check_gate(gate) -> RangeGate | None:
    """``gate`` if it is None or a :class:`RangeGate`, else a ParameterError."""
    if gate is not None and not isinstance(gate, RangeGate):
        raise ParameterError(f"gate={gate!r} must be a RangeGate or None (the whole range axis)")
    return gate


def boundary_skirts(energy: np.ndarray, mask: np.ndarray, ends_bins: tuple[float, float]) -> np.ndarray:
    """The range bins inside a gate that are the skirt of a return outside it: (B, N) bool.

    ``energy`` (B, N) the joint energy of the range bins (a back projection), ``mask`` (N,)
    bool the bins inside the gate (one run on the circular axis), ``ends_bins`` the gate's
    ends in bins (:meth:`RangeGate.bins`). From each end of the gate inward: the end bin is on
    the skirt of a peak whose maximum lies outside when its neighbour outside is higher, or
    when it is the top of a peak whose maximum, interpolated by the parabola through the
    magnitudes of the bin and its two neighbours, lies beyond the gate's end (an off-grid
    tone at 1.5 bins fills bins 1 and 2 alike); then the bins after it while the energy keeps
    falling inward are that peak's slope (an off-grid tone's energy on the bins falls
    monotonically away from it, ``|sin(pi nu)| / |N sin(pi (n - nu) / N)|``), not a target
    inside. A target inside is a maximum inside; the slope stops at the first bin that rises."""
    e = np.asarray(energy, dtype=float)
    b, n = e.shape
    out = np.zeros((b, n), dtype=bool)
    inside = np.flatnonzero(mask)
    if inside.size < 2 or inside.size == n:
        return out
    first = inside[np.flatnonzero(~mask[inside - 1])[0]]  # the run of inside bins starts after an outside one
    run = (first + np.arange(inside.size)) % n
    lo, hi = ends_bins
    for order, step, end in ((run, -1, lo), (run[::-1], 1, hi)):
        ends = e[:, order]  # (B, W), inward from this end
        m_out, m_in, m_next = (np.sqrt(np.maximum(x, 0.0)) for x in (e[:, (order[0] + step) % n], ends[:, 0],
                                                                        ends[:, 1]))
        curv = m_out - 2.0 * m_in + m_next
        with np.errstate(divide="ignore", invalid="ignore"):
            offset = np.where(curv < 0, 0.5 * (m_out - m_next) / curv, 0.0)  # towards the outside neighbour
        top = order[0] - step * offset  # the interpolated maximum, bins (order[0] unwrapped near the end)
        beyond = (top < end) if step < 0 else (top > end)
        outer = (m_out > m_in) | ((m_in >= m_out) & (m_in >= m_next) & beyond)
        falling = np.concatenate([outer[:, None], ends[:, 1:] <= ends[:, :-1]], axis=1)
        out[:, order] |= np.cumprod(falling, axis=1).astype(bool)
    return out


def gate_warning(truth, gate) -> str | None:
    """What a run or a re-processing says of true targets (``truth``: a SimScene, or None) that
    stand still outside its range gate (a :class:`RangeGate`): they cannot be found, and the
    score counts them missed; None when there is none."""
    out = [t.range_m for t in (truth.targets if truth is not None else [])
           if not t.velocity_m_s and not gate.holds(t.range_m)]
    if not out:
        return None
    return (f"true target(s) at {', '.join(f'{r:g} m' for r in out)} outside the range gate "
            f"[{gate.min_range_m:g}, {gate.max_range_m:g}] m: the localizer cannot find them, and the score counts "
            "them missed (--min-range-m, --max-range-m)")
