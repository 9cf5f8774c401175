"""cml's detection grid: ``oversample`` points a range bin over the circular range axis, the
range gate on it (:class:`SearchGrid`), and the tables of the coarse grid the compiled search
reads the fine one from (:func:`run_tables`, :func:`twiddles`)."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.gate import RangeGate, check_gate

#: a detection keeps at least this far from the targets already found, range bins
MIN_SEPARATION_BINS = 1.0
#: with a range gate, greedy stages a frame may spend beyond its count on targets that leave the
#: gate (a strong return outside it, whose skirt or sidelobe inside seeded them: modelled, not
#: reported; the leakage, its I/Q mirror)
NUISANCE_STAGES = 2
#: ranges this close to a gate's end (bins) count as inside it
INSIDE_TOLERANCE_BINS = 1e-9
#: detection and the count test take their inverse FFT on a grid of this many points a bin,
#: coarser than ``oversample``, and find the same fine-grid peak by summing the fine energy
#: directly around the coarse points that could hold it
#: (:func:`pipeline.dsp.cml.kernels.search.coarse_peak`); the count test's mean, the fine
#: energy summed over the points not masked, by sums over runs of fine points from the
#: coarse energies (:func:`pipeline.dsp.cml.kernels.search.open_sum`; measured against the
#: full grid: within 5e-15 relative; K auto on 80 040 frames: the same counts as the full grid)
COARSE_PER_BIN = 2
#: ... those whose energy reaches this fraction of the best fine energy found: the fine peak's
#: nearest coarse point (at most 1 / (2 COARSE_PER_BIN) bin away) holds more (a maximum of the
#: energy: over cos^2(pi / 4) = 1/2, Riesz; a tone's: 0.81; a peak against the guard or the gate:
#: its coarse neighbours count too). Measured against the full grid on 288 000 detections of
#: 1-bit and unquantized frames (K = 1..3, alpha 1 and 0.45, noise 0 and 0.1, gated or not,
#: targets 0.3 or 1.5 m apart): the same fine point every time, ranges within 3e-14 bins
COARSE_RHO = 0.5


class SearchGrid:
    """The detection grid of ``oversample`` points a bin of ``config`` and the range ``gate``
    on it (None: the whole, circular, axis; checked against ``config`` by its user,
    :meth:`RangeGate.check <pipeline.dsp.gate.RangeGate.check>`): ``lo``, ``hi`` its ends in
    bins, ``outside`` (L,) bool the grid points beyond it (None without a gate), ``width_bins``
    the bins the search spans (the count test's cells).

    A gate bounds where targets are sought (detection's seeds and the count test's peak are
    points inside it) and which are reported (those whose refined range lies inside it); it
    does not bound the refinement: a seed on the skirt or a sidelobe of a strong return just
    outside walks out to it, and stays in the model (its energy explained, not reported)."""

    def __init__(self, gate: RangeGate | None, config: RadarConfig, oversample: int):
        n = config.samples_per_ramp
        self.gate = check_gate(gate)
        self.n = n
        self.oversample = oversample
        self.size = oversample * n
        #: the grid allows the coarse FFT (a multiple of COARSE_PER_BIN points a bin, beyond it)
        self.coarse = oversample % COARSE_PER_BIN == 0 and oversample > COARSE_PER_BIN
        if self.gate is None:
            self.lo = self.hi = 0.0
            self.outside = None
            self.width_bins = float(n)
            return
        self.lo, self.hi = self.gate.bins(config)
        grid = np.arange(self.size) / oversample
        eps = 1e-9
        self.outside = (grid < self.lo - eps) | (grid > self.hi + eps)
        if self.outside.all():  # a gate narrower than the grid's step: its nearest point
            self.outside[np.argmin(np.abs(grid - 0.5 * (self.lo + self.hi)))] = False
        self.width_bins = min(float(n), max(self.hi - self.lo, 1.0 / oversample))

    @property
    def use(self) -> bool:
        """Whether a gate restricts the search."""
        return self.gate is not None

    @property
    def stages(self) -> int:
        """Greedy stages a frame may spend beyond its count (:data:`NUISANCE_STAGES` with a gate)."""
        return NUISANCE_STAGES if self.use else 0

    def inside(self, nu: np.ndarray) -> np.ndarray:
        """Whether ranges ``nu`` (bins, any shape) lie inside the gate, on the circular axis
        (all True without a gate)."""
        if not self.use:
            return np.ones(np.shape(nu), dtype=bool)
        v = np.mod(nu, self.n)
        return (v >= self.lo - INSIDE_TOLERANCE_BINS) & (v <= self.hi + INSIDE_TOLERANCE_BINS)


def run_tables(n: int, size: int, lc: int) -> np.ndarray:
    """(ratio, 2 Lc) float, ratio = ``size`` / ``lc``: ``tables[phi, j] = G(phi + ((-j) mod Lc)
    ratio)``, where ``G(x) = F(x) - x / Lc``, ``F(x) = sum_{j < x} f(j)`` and ``f(j) = (1 / Lc)
    sin((2N - 1) pi j / L) / sin(pi j / L)`` interpolates the fine energy (L = ``size``
    points) from the coarse one: ``E_fine[l] = sum_k E_coarse[k] f(l - k ratio)``; G is
    L-periodic (f sums to L / Lc over a period). The prefix sums in extended precision
    (``np.longdouble``; where it is a double, G to ~1e-14). About 0.7 ms: kept by its user."""
    j = np.arange(size)
    pi = np.longdouble("3.14159265358979323846264338327950288")
    num = np.sin(pi * ((2 * n - 1) * j % (2 * size)) / size)  # arguments reduced exactly, then scaled
    den = np.sin(pi * j / size)
    f = np.divide(num, den, out=np.full(size, np.longdouble(2 * n - 1)), where=j > 0) / lc
    g = (np.concatenate([np.zeros(1, dtype=np.longdouble), np.cumsum(f)[:-1]]) - j / np.longdouble(lc))
    ratio, k = size // lc, np.arange(2 * lc)
    return np.ascontiguousarray(g[(np.arange(ratio)[:, None] + ((-k) % lc)[None, :] * ratio) % size], dtype=float)


def twiddles(size: int) -> np.ndarray:
    """``exp(2 pi i k / size)`` (size,) complex."""
    return np.exp(2j * np.pi * np.arange(size) / size)
