"""cml's inner kernels compiled into numba's cache as the tests call them on their own
(``make test``'s set-up runs :func:`compile_all` once, as ``make`` compiles the entry kernels
a node uses; again when their source changes).

``tests/test_cml_detect.py``, ``test_cml_count.py`` and ``test_cml_kernels.py`` call inner
kernels (``peak``, ``coarse_ratio``, ``run_sum``, the likelihood's ``exp_neg``, ...) directly,
against numpy: numba compiles each of them on its first call in a process, ~40 s of CPU on a
fresh clone, which the first suite paid in its own time. Each call here goes through the tests'
own helpers (or their exact argument types), so that it compiles the signatures the tests
call (checked: after it, the three modules saved nothing new to the cache, ``NUMBA_DEBUG_CACHE=1``).
A signature it misses costs only time: the first suite compiles it, as before."""

from __future__ import annotations

import numpy as np

import test_cml_count
import test_cml_detect
import test_cml_kernels
from pipeline.dsp.cml.grid import twiddles
from pipeline.dsp.cml.kernels import likelihood as lik, search
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from radar_driver.model import RadarConfig, simulate_frames


def compile_all() -> None:
    """Call each inner kernel the tests call on their own once, with the tests' argument types."""
    rng = np.random.default_rng(0)
    n = 16
    x = rng.standard_normal((2, n)) + 1j * rng.standard_normal((2, n))
    test_cml_detect.peaks(x, 4)  # peak, coarse_range
    test_cml_detect.peaks(x, 4, outside=np.ones(n * 4, dtype=bool), gate=(1.0, 2.0))  # gate_edge
    search.fine_energy(x[None], n, 0, twiddles(n * 8), np.empty((2, 2), dtype=complex))
    xc = test_cml_count.tones([10.5], [[1.0, 1j]], 0.1, rng)
    _, coarse, total = test_cml_count.energies(xc)  # coarse_energies
    test_cml_count.coarse_ratio(xc, [10.5], [True])  # coarse_ratio
    tables = test_cml_count.run_tables(test_cml_count.N, test_cml_count.SIZE, test_cml_count.SMALL)
    a = rng.integers(-4, 4, 1)[0]
    search.run_sum(coarse, total, tables, a, a + 3 - 1, test_cml_count.SIZE)
    gate = test_cml_count.gate_of(5.0, 150.0, RadarConfig())
    search.gate_weights(gate.outside, tables, test_cml_count.SMALL, np.empty(test_cml_count.SMALL + 1))
    lik.exp_neg(np.float32(1.0))
    lik.log1p_small(np.float32(0.5))
    lik.softplus(np.float32(np.inf))
    cfg = RadarConfig()
    (r, amp, xs), _ = test_cml_kernels.off_grid(3, 2, 42)
    for bits in (1, 3):  # codes_arrays, from values and from codes (uint8, and int64 as a test passes them)
        q = quantize_frames(simulate_frames(r, amp, xs, cfg), QuantizerConfig(bits=bits, alpha=1.0), np.arange(3))
        delta = np.broadcast_to(q.delta, (3,)).astype(float)
        for z in (q.values(), q.codes, q.codes.astype(np.int64)):
            for motion in (True, False):
                test_cml_kernels.block_codes(test_cml_kernels.check_frames(z, q.dither(), delta, bits, cfg, 1, None),
                                             cfg.samples_per_ramp, "logistic", motion)


if __name__ == "__main__":
    compile_all()
