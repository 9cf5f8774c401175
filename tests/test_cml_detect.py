"""Detection on a coarse inverse FFT (pipeline.dsp.cml.kernels.search.coarse_peak: the
FFT on COARSE_PER_BIN N points, the fine energy summed directly around the coarse points
that could hold the peak) against the full fine grid (``peak``, the kernel the count test
keeps) and the numpy reference (pipeline.dsp.cml.reference.detect).

Tolerance: the same fine-grid point and parabola, from energies summed in another order
(an FFT of another size, direct sums): ranges agree to 1e-9 bins (measured: 3e-14)."""

import itertools

import numpy as np
import pytest
from test_cml import measure, random_scenes
from test_cml_kernels import detection_agrees

from pipeline.dsp.cml import CmlDecoder, CmlOptions, cml
from pipeline.dsp.cml.count import COUNT_GUARD_BINS
from pipeline.dsp.cml.grid import COARSE_PER_BIN, COARSE_RHO, twiddles
from pipeline.dsp.cml.kernels import detect as kernels, search as count_kernels
from pipeline.dsp.cml.kernels.layout import Gate, Grid
from pipeline.dsp.gate import RangeGate

TOL_BINS = 1e-9


def peaks(x, oversample, nu=(), live=(), outside=None, guard_bins=1.0, gate=(0.0, 0.0)):
    """The peak (bins) of the sources ``x`` (2, N) complex by the full fine grid and by the
    coarse grid, the same guard (targets ``nu`` bins, ``live``) and gate (``outside`` (L,))."""
    n = x.shape[1]
    size, small = oversample * n, COARSE_PER_BIN * n
    nu, live = np.asarray(nu, dtype=float), np.asarray(live, dtype=bool)
    edges = np.zeros(small, dtype=bool)
    if outside is not None:
        count_kernels.gate_edge(outside, small, edges)
    kgate = Gate(outside is not None, gate[0], gate[1], np.zeros(1, dtype=bool) if outside is None else outside, edges)
    table = twiddles(size)
    grid = Grid(oversample, COUNT_GUARD_BINS, guard_bins, COARSE_RHO, table, np.zeros((0, 0)), np.zeros(1), 0)
    full = kernels.peak(np.fft.ifft(x, n=size, axis=1)[None], nu, live, oversample, guard_bins, kgate,
                        kernels.scratch(n, size, 0, table, 1))
    fast = kernels.coarse_range(np.fft.ifft(x, n=small, axis=1)[None], np.ascontiguousarray(x[None]), n, nu, live,
                                grid, kgate, kernels.scratch(n, size, small, table, 1), False)
    return full, fast


def tones(rng, n, nu, amp):
    """(2, N) complex: tones at ``nu`` (bins), amplitudes ``amp`` (K, 2), as the back
    projection sees a target (``exp(2 pi i nu k / N)`` peaks at ``nu``)."""
    k = np.arange(n)
    return sum(np.exp(-2j * np.pi * v * k / n)[None, :] * np.asarray(a)[:, None] for v, a in zip(nu, amp))


@pytest.mark.parametrize("oversample", [4, 8, 16])
def test_coarse_peak_is_the_fine_grids_on_tones_and_noise(oversample):
    rng = np.random.default_rng(oversample)
    n = 64
    for trial in range(300):
        k = 1 + trial % 3
        nu = rng.uniform(0, n, k)
        amp = rng.standard_normal((k, 2)) + 1j * rng.standard_normal((k, 2))
        noise = rng.standard_normal((2, n)) + 1j * rng.standard_normal((2, n))
        x = tones(rng, n, nu, amp) + rng.uniform(0, 2) * noise
        full, fast = peaks(x, oversample)
        assert abs(full - fast) <= TOL_BINS, (trial, full, fast)
        # the strongest tone found: the next peak away from it (a guard of 1 bin), some not live
        full, fast = peaks(x, oversample, nu[:1], [trial % 4 != 0])
        assert abs(full - fast) <= TOL_BINS, (trial, full, fast)


def test_coarse_peak_against_the_guard_and_the_gate():
    """A peak whose top is masked (a tone 0.5 bin inside the guard of a target found, or
    just beyond the gate) leaves the largest energy outside on its flank: the fine grid's
    point there, not a coarse point's."""
    rng = np.random.default_rng(1)
    n, oversample = 64, 8
    size = n * oversample
    for trial in range(200):
        found = rng.uniform(10, 50)
        side = 1 if trial % 2 else -1
        nu = [found, found + side * rng.uniform(0.3, 1.2)]
        x = tones(rng, n, nu, [[0.05, 0.05j], [1.0, 0.5]]) + 0.01 * rng.standard_normal((2, n))
        full, fast = peaks(x, oversample, [found], [True])
        assert abs(full - fast) <= TOL_BINS, (trial, full, fast)
        lo, hi = found - rng.uniform(5, 9), found + rng.uniform(-1.0, 0.3)  # the tone near or beyond the top
        grid = np.arange(size) / oversample
        outside = (grid < lo) | (grid > hi)
        full, fast = peaks(tones(rng, n, [found + rng.uniform(-0.3, 0.3)], [[1, 1j]]), oversample, outside=outside,
                           gate=(lo, hi))
        assert abs(full - fast) <= TOL_BINS, (trial, full, fast)


def test_coarse_peak_of_nothing_is_the_full_grids():
    """No energy: the first point inside the gate (argmax's first of equal values); all beyond it: point 0."""
    n, oversample = 32, 8
    x = np.zeros((2, n), dtype=complex)
    assert peaks(x, oversample) == (0.0, 0.0)
    outside = np.ones(n * oversample, dtype=bool)
    outside[37:90] = False
    full, fast = peaks(x, oversample, outside=outside, gate=(37 / 8, 89 / 8))
    assert full == fast == 37 / 8
    full, fast = peaks(x, oversample, outside=np.ones(n * oversample, dtype=bool), gate=(1.0, 2.0))
    assert full == fast == 1.0


def test_fine_energy_is_the_zero_padded_ffts():
    rng = np.random.default_rng(2)
    n, size = 48, 48 * 8
    x = rng.standard_normal((2, n)) + 1j * rng.standard_normal((2, n))
    u = np.fft.ifft(x, n=size, axis=1)
    ref = np.abs(u[0]) ** 2 + np.abs(u[1]) ** 2
    vals = np.empty((2, 2), dtype=complex)
    got = np.array([count_kernels.fine_energy(x[None], n, p, twiddles(size), vals) for p in range(size)])
    np.testing.assert_allclose(got, ref, rtol=1e-12)
    # two ramps: the peak over the phase step phi of sum_p |U_0p exp(i phi / 2) + U_1p exp(-i phi / 2)|^2
    x2 = np.stack([x, rng.standard_normal((2, n)) + 1j * rng.standard_normal((2, n))])
    u2 = np.fft.ifft(x2, n=size, axis=2)
    phis = np.linspace(-np.pi, np.pi, 4001)
    turn = np.exp(-1j * np.outer(phis, [-0.5, 0.5]))  # (D, 2 ramps)
    ref2 = (np.abs(np.einsum("dr,rpl->dpl", turn, u2)) ** 2).sum(axis=1).max(axis=0)
    got2 = np.array([count_kernels.fine_energy(x2, n, p, twiddles(size), vals) for p in range(size)])
    assert np.all(got2 >= ref2 * (1 - 1e-12)) and np.all(got2 <= ref2 * (1 + 1e-6))  # the grid of phi: 1e-6 below


@pytest.mark.parametrize("oversample", [3, 4, 16])
def test_compiled_detection_agrees_with_numpy_on_other_grids(cfg, oversample):
    """Grids of 4 and 16 points a bin (coarse ratios 2 and 8) and 3 (not a multiple of
    COARSE_PER_BIN: the full grid) against the numpy reference."""
    rng = np.random.default_rng(50 + oversample)
    r, a, x = random_scenes(8, 2, rng)
    z, xi, delta = measure(r, a, x, cfg, rng)
    detection_agrees(z, xi, delta, 1, cfg, oversample=oversample)


def test_compiled_detection_agrees_with_numpy_on_close_targets_and_a_gate(cfg):
    rng = np.random.default_rng(60)
    r, a, x = random_scenes(12, 3, rng, separation_m=0.4)
    r = 21.0 + (r - 3.0) * (78.0 / 147.0)
    z, xi, delta = measure(r, a, x, cfg, rng, noise=0.05)
    detection_agrees(z, xi, delta, 1, cfg, RangeGate(min_range_m=20.0, max_range_m=100.0))


def test_decoder_with_k_fixed_matches_the_full_grids(cfg, monkeypatch):
    """cml with k fixed (the coarse grid) gives the same targets as with the coarse grid
    switched off (the full fine grid) to the last bits' run-to-run variation; with the phase
    step between ramps (the default) the coarse grid searches the static channel or the
    residual steered to its best coarse point's phase step, the full grid each point's peak
    over it: the detections differ by a small part of a bin and the refinement's last steps
    do not close it: ranges agree to 1e-5 m, amplitudes to 5e-3 (measured 2.1e-6 m and 2.2e-3,
    the noise 0.1). A frame whose second target lies beyond the gate (frame 1's at 144.9 m)
    takes extra stages to report K = 2 inside it (a range gate bounds what is reported, not
    what is modelled): that second target is a noise peak, which with the phase step the
    two searches need not pick alike (measured: 117.8 m against 64.8 m); its target inside the
    gate, fitted jointly with another second one, agrees to 2e-4 m (measured 7.8e-5 m) and its
    amplitudes' magnitudes to 2e-2 (measured 1.2e-2; their common phase turns by 0.09 rad)."""
    from pipeline.dsp.cml import grid
    rng = np.random.default_rng(70)
    r, a, x = random_scenes(16, 2, rng)
    z, xi, delta = measure(r, a, x, cfg, rng, alpha=0.45, noise=0.1)
    gate = RangeGate(min_range_m=2.0, max_range_m=140.0)
    for kw, motion in itertools.product(({}, {"gate": gate}), (False, True)):
        tol_m, tol = (1e-5, 5e-3) if motion else (1e-9, 1e-9)
        options = CmlOptions(motion=motion)
        got = cml(z, xi, delta, 1, cfg, 2, options=options, **kw)
        monkeypatch.setattr(grid, "COARSE_PER_BIN", 8)  # = oversample: no coarse grid
        full = CmlDecoder(cfg, options)
        assert not full.grid(kw.get("gate")).coarse
        ref = full.decode(z, xi, delta, 1, 2, **kw)
        monkeypatch.undo()
        rows = np.ones(len(r), dtype=bool)
        if motion and kw:  # a frame with a target beyond the gate: its noise fill aside (the docstring)
            rows = ((r >= gate.min_range_m) & (r <= gate.max_range_m)).all(axis=1)
            assert 0 < (~rows).sum() <= 2
            np.testing.assert_allclose(got.range_m[~rows, 0], ref.range_m[~rows, 0], rtol=0, atol=2e-4)
            np.testing.assert_allclose(np.abs(got.amplitudes[~rows, 0]), np.abs(ref.amplitudes[~rows, 0]), rtol=0,
                                       atol=2e-2)
        np.testing.assert_allclose(got.range_m[rows], ref.range_m[rows], rtol=0, atol=tol_m)
        np.testing.assert_allclose(got.amplitudes[rows], ref.amplitudes[rows], rtol=0, atol=tol)
