"""The count test of cml on the coarse grid (pipeline.dsp.cml.kernels.search, the detect
kernels' ``coarse_ratio``) against the numpy reference (pipeline.dsp.cml.reference.peak_ratio,
count_statistic) on the full fine grid: the mean of the joint energy by sums over runs of
fine points from the coarse energies, the peak by the coarse search.

Tolerances: a run's sum to 1e-12 of the energy's total (measured: 6e-16); the statistic
to 1e-9 relative (measured: 5e-15); the decided statistic (a threshold given) reaches the
threshold exactly when the exact one does, thresholds 1e-9 either side of it included."""

from types import SimpleNamespace

import numpy as np
import pytest
from test_cml import measure, random_scenes
from test_cml_kernels import RANGE_TOL_M, agree

from pipeline.dsp.cml import CmlOptions, cml, reference
from pipeline.dsp.cml.compiled import CompiledBlocks
from pipeline.dsp.cml.grid import COARSE_PER_BIN, SearchGrid, run_tables
from pipeline.dsp.cml.kernels import detect as kernels, search as count_kernels
from pipeline.dsp.cml.kernels.layout import Gate, Grid
from pipeline.dsp.gate import RangeGate
from radar_driver.model import RadarConfig

N, OVERSAMPLE = 256, 8
SIZE, SMALL = N * OVERSAMPLE, N * COARSE_PER_BIN
STAT_RTOL = 1e-9


def energies(x):
    """The fine grid's joint energy (L,) of ``x`` (2, N) and the coarse one's, as the kernel keeps it."""
    fine = (np.abs(np.fft.ifft(x, n=SIZE, axis=1)) ** 2).sum(axis=0)
    s = kernels.scratch(N, SIZE, SMALL, np.exp(2j * np.pi * np.arange(SIZE) / SIZE), 1)
    total = count_kernels.coarse_energies(np.fft.ifft(x, n=SMALL, axis=1)[None], SIZE, s)
    return fine, s.coarse.copy(), total


def search(gate=None, n=N, oversample=OVERSAMPLE):
    """The kernels' Grid and Gate of a grid of ``n`` samples a ramp, ``oversample`` points a bin and
    ``gate`` (a SearchGrid or None), as the compiled engine builds them."""
    grid = gate if gate is not None else SearchGrid(None, RadarConfig(samples_per_ramp=n), oversample)
    found = CompiledBlocks(RadarConfig(samples_per_ramp=n), CmlOptions(oversample=oversample)).search(grid)
    return Grid(*found.kernel), Gate(*found.gate)


def coarse_ratio(x, nu, live, gate=None, threshold=-1.0, n=N, oversample=OVERSAMPLE):
    """The coarse grid's count statistic of ``x`` (2, n) (targets ``nu`` bins, ``live``;
    ``gate`` a SearchGrid or None), decided at ``threshold`` (< 0: exact)."""
    size, small = n * oversample, n * COARSE_PER_BIN
    grid, kgate = search(gate, n, oversample)
    s = kernels.scratch(n, size, small, grid.table, 1)
    ratio, _ = kernels.coarse_ratio(np.fft.ifft(x, n=small, axis=1)[None], np.ascontiguousarray(x[None]), n,
                                    np.asarray(nu, dtype=float), np.asarray(live, dtype=bool), grid, kgate, s,
                                    threshold, 0.0)
    return ratio


def reference_ratio(x, nu, live, gate=None, oversample=OVERSAMPLE):
    """numpy's (pipeline.dsp.cml.reference.peak_ratio) on the full fine grid."""
    grid = gate if gate is not None else SearchGrid(None, RadarConfig(samples_per_ramp=x.shape[1]), oversample)
    fit = SimpleNamespace(nu=np.asarray(nu, dtype=float)[None], live=np.asarray(live, dtype=bool)[None], grid=grid)
    return reference.peak_ratio(x.T[None, None], fit, oversample)[0]


def tones(nu, amp, noise, rng):
    """(2, N) complex: tones at ``nu`` (bins), amplitudes ``amp`` (K, 2), white noise of std ``noise``."""
    k = np.arange(N)
    x = noise * (rng.standard_normal((2, N)) + 1j * rng.standard_normal((2, N)))
    for v, a in zip(nu, amp):
        x = x + np.exp(-2j * np.pi * v * k / N)[None, :] * np.asarray(a)[:, None]
    return x


def gate_of(lo_m, hi_m, cfg):
    return SearchGrid(RangeGate(min_range_m=lo_m, max_range_m=hi_m), cfg, OVERSAMPLE)


def test_run_sums_are_the_fine_grids():
    """The fine energy summed over runs of points (any start, wrapping, 1 to 300 points)
    from the coarse energies, against the zero-padded FFT's."""
    rng = np.random.default_rng(0)
    tables = run_tables(N, SIZE, SMALL)
    for trial in range(40):
        x = tones(rng.uniform(0, N, 2), [[30.0, 3j], [0.3, 0.1]], 1.0 if trial % 2 else 0.0, rng)
        fine, coarse, total = energies(x)
        for a in rng.integers(-SIZE, SIZE, 25):
            m = int(rng.integers(1, 300))
            got = count_kernels.run_sum(coarse, total, tables, a, a + m - 1, SIZE)
            assert abs(got - fine[np.arange(a, a + m) % SIZE].sum()) <= 1e-12 * fine.sum()


def test_run_tables_match_the_prefix_sums_of_the_interpolating_kernel():
    n, size, small = 16, 128, 32
    j = np.arange(size)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(j == 0, 2 * n - 1, np.sin((2 * n - 1) * np.pi * j / size) / np.sin(np.pi * j / size)) / small
    g = np.concatenate([[0.0], np.cumsum(f)[:-1]]) - j / small  # F(x) - x / Lc
    tables = run_tables(n, size, small)
    ratio = size // small
    for phi in range(ratio):
        for k in range(2 * small):
            assert abs(tables[phi, k] - g[(phi + ((-k) % small) * ratio) % size]) < 1e-13


@pytest.mark.parametrize("case", ["empty", "guard", "overlapping_guards", "dead_overwrites", "wrapping"])
def test_statistic_matches_numpy_without_a_gate(case):
    rng = np.random.default_rng(1)
    for trial in range(60):
        found = rng.uniform(0, N, 3)
        if case == "empty":
            nu, live = np.zeros(0), np.zeros(0, dtype=bool)
        elif case == "guard":
            nu, live = found[:2], [True, True]
        elif case == "overlapping_guards":  # guards overlap: each point counted once
            nu, live = [found[0], found[0] + rng.uniform(0.1, 3.5)], [True, True]
        elif case == "dead_overwrites":  # a later target not live clears an earlier one's guard
            nu, live = [found[0], found[0] + rng.uniform(-2.0, 2.0), found[1]], [True, False, True]
        else:
            nu, live = [rng.uniform(-1.0, 0.5), N - rng.uniform(0, 1.5)], [True, True]
        # tones at the targets (their residual), one beyond the guard or inside it, noise or none
        near = np.r_[np.asarray(nu, dtype=float), [found[2], found[0] + rng.choice([-1, 1]) * rng.uniform(1.5, 2.5)]]
        amp = rng.standard_normal((near.size, 2)) + 1j * rng.standard_normal((near.size, 2))
        x = tones(near, amp * rng.uniform(0.01, 3.0, (near.size, 1)), (0.0, 0.1, 1.0)[trial % 3], rng)
        ref = reference_ratio(x, nu, live)
        assert coarse_ratio(x, nu, live) == pytest.approx(ref, rel=STAT_RTOL), (trial, ref)


def test_statistic_matches_numpy_with_a_gate(cfg):
    """Gates of a few bins to nearly all of them, targets and tones near their ends and
    guards reaching beyond them."""
    rng = np.random.default_rng(2)
    for trial in range(80):
        lo = rng.uniform(1.0, 60.0)
        hi = lo + (rng.uniform(0.3, 3.0) if trial % 4 == 0 else rng.uniform(5.0, 80.0))
        gate = gate_of(lo, hi, cfg)
        lo_b, hi_b = gate.lo, gate.hi
        nu = [lo_b + rng.uniform(-1.0, 1.0), hi_b + rng.uniform(-1.0, 1.0), rng.uniform(lo_b, hi_b)][:trial % 4]
        live = [True, trial % 3 != 0, True][:len(nu)]
        near = np.r_[np.asarray(nu, dtype=float), [lo_b - 0.3, hi_b + 0.2, rng.uniform(lo_b, hi_b)]]
        amp = rng.standard_normal((near.size, 2)) + 1j * rng.standard_normal((near.size, 2))
        x = tones(near, amp, (0.0, 0.1)[trial % 2], rng)
        ref = reference_ratio(x, nu, live, gate)
        assert coarse_ratio(x, nu, live, gate) == pytest.approx(ref, rel=STAT_RTOL), (trial, lo, hi, ref)


def test_statistic_of_nothing_and_of_a_gate_all_guarded_is_numpys(cfg):
    x = np.zeros((2, N), dtype=complex)
    assert coarse_ratio(x, [], []) == reference_ratio(x, [], []) == 0.0
    gate = gate_of(30.0, 30.5, cfg)  # a gate narrower than the guard: every point inside it masked
    x = tones([gate.lo + 0.1], [[1.0, 1.0j]], 0.1, np.random.default_rng(3))
    nu = [0.5 * (gate.lo + gate.hi)]
    assert coarse_ratio(x, nu, [True], gate) == reference_ratio(x, nu, [True], gate) == 0.0


def test_decided_statistic_reaches_the_threshold_exactly_when_the_exact_one_does(cfg):
    """Thresholds at, just above and just below the exact statistic, and far either side:
    the same decision; and the decision of a statistic near a threshold by a few cells only."""
    rng = np.random.default_rng(4)
    gate = gate_of(10.0, 120.0, cfg)
    for trial in range(60):
        g = gate if trial % 2 else None
        nu = rng.uniform(30.0, 100.0, trial % 3)
        live = np.ones(nu.size, dtype=bool)
        x = tones(np.r_[nu, rng.uniform(20.0, 110.0)], rng.standard_normal((nu.size + 1, 2)) * rng.uniform(0.02, 2.0),
                  1.0, rng)
        exact = coarse_ratio(x, nu, live, g)
        assert exact == pytest.approx(reference_ratio(x, nu, live, g), rel=STAT_RTOL)
        for thr in (exact * (1 - 1e-9), exact * (1 + 1e-9), 0.5 * exact, 2.0 * exact, 8.2):
            assert (coarse_ratio(x, nu, live, g, thr) >= thr) == (exact >= thr), (trial, exact, thr)


def test_gate_weights_count_the_points_inside(cfg):
    tables = run_tables(N, SIZE, SMALL)
    for lo, hi in ((0.0, 1.0), (5.0, 150.0), (100.0, 100.2), (0.0, 200.0)):
        gate = gate_of(lo, hi, cfg)
        weights = np.empty(SMALL + 1)
        assert count_kernels.gate_weights(gate.outside, tables, SMALL, weights) == (~gate.outside).sum()


@pytest.mark.parametrize("bits,alpha,noise", [(1, 1.0, 0.0), (1, 0.45, 0.1), (None, 1.0, 0.0), (None, 1.0, 0.1)])
def test_k_auto_counts_agree_with_numpy(cfg, bits, alpha, noise):
    """K auto (pfa 1e-3, at most 4) on scenes of 0 to 4 targets inside the gate, gated or
    not: the compiled decoder (the count test on the coarse grid, decided) against the numpy
    reference, the same counts and ranges (noiseless unquantized frames: the same counts,
    phantoms fitted to the rounding of an exact fit whose ranges the engines need not
    share). Amplitudes: as main's compiled path (alpha 0.45 with noise: the engines' differ
    by up to 5e-3, before this change too)."""
    rng = np.random.default_rng(5)
    gate = RangeGate(min_range_m=20.0, max_range_m=100.0)
    for k in range(5):
        r, a, x = random_scenes(6, max(k, 1), rng)
        r = 21.0 + (r - 3.0) * (78.0 / 147.0)
        if k == 0:
            x[:] = 0.0
        z, xi, delta = measure(r, a, x, cfg, rng, bits=bits, alpha=alpha, noise=noise if k else max(noise, 0.1))
        for kw in ({}, {"gate": gate}):
            ref = cml(z, xi, delta, bits, cfg, 4, options=CmlOptions(engine="numpy"), pfa=1e-3, **kw)
            got = cml(z, xi, delta, bits, cfg, 4, options=CmlOptions(engine="numba"), pfa=1e-3, **kw)
            np.testing.assert_array_equal(got.present, ref.present)
            if not (bits is None and noise == 0.0):
                np.testing.assert_allclose(got.range_m[ref.present], ref.range_m[ref.present], atol=RANGE_TOL_M)


def test_warm_start_misfit_decisions_agree_with_numpy(cfg):
    """The warm start's count test (decided at the warm threshold): a target that appeared
    sends a frame back to the full search in both engines."""
    rng = np.random.default_rng(6)
    r, a, x = random_scenes(12, 2, rng)
    z, xi, delta = measure(r, a, x, cfg, rng, noise=0.05)
    init = r.copy()
    init[::3, 1] = np.nan  # the second target not known: it appeared
    for kw in ({}, {"pfa": 1e-3}):
        agree(z, xi, delta, 1, cfg, 2, init_range_m=init, **kw)


#: a residual whose count-test peak (fine point 72 of 120) lies against a target's guard and
#: keeps under 1/2 of its energy at every coarse neighbour: no maximum of |U|^2, so the Riesz
#: bound does not hold there; the cells by the guard are summed whatever their coarse energy
_AGAINST_THE_GUARD = dict(
    re=[[10.42971669230878, 5.699607263948142, 0.7864940282695958, 8.038789922541213, 9.536818127486855,
         1.369139264291988, 1.8857552698054207, 6.962020129311256, 1.9252859100633235, -1.9199834547307408,
         0.27441475318381925, 5.551651018873782],
        [11.297410600850764, 4.125520403832286, 0.13085796709413167, 7.814264561961785, 9.243613153357936,
         0.33889510373313136, 0.851423969261901, 8.268298042287753, 3.0015225692214718, -3.011667602717704,
         2.344085011875901, 4.910137420643878]],
    im=[[0.09903565165818023, 5.23292566493944, 1.3294572500228994, -1.568865310902789, 5.197964580223889,
         4.934118776016033, -0.08690421394825609, 3.3900673128549093, 10.829813079836136, 6.935009971519387,
         1.4654935343812001, 5.252990145557256],
        [-0.6914413542950504, 4.432374008706869, 0.6881836624249951, -3.3275167236881242, 4.583867487501922,
         6.651890155674467, -2.1977074695835666, 1.7593826511642767, 9.339331443815615, 2.913326761888907,
         -1.5677524485721088, 6.7470467226636]],
    nu=[-0.36223964380241824, -2.8179057054362913])


def test_decided_statistic_finds_a_peak_against_the_guard():
    """A peak against a target's guard that no coarse neighbour holds half of is still found
    when the count test is decided at a threshold just below it (N = 12, oversample 10)."""
    case = _AGAINST_THE_GUARD
    x = np.asarray(case["re"]) + 1j * np.asarray(case["im"])
    live = [True, True]
    exact = reference_ratio(x, case["nu"], live, oversample=10)
    assert coarse_ratio(x, case["nu"], live, n=12, oversample=10) == pytest.approx(exact, rel=STAT_RTOL)
    for below in (1e-9, 1e-3, 0.05):
        bar = exact * (1 - below)
        assert coarse_ratio(x, case["nu"], live, threshold=bar, n=12, oversample=10) >= bar
    assert coarse_ratio(x, case["nu"], live, threshold=exact * (1 + 1e-9), n=12, oversample=10) < exact * (1 + 1e-9)


def test_decided_statistic_agrees_with_numpy_on_small_random_grids():
    """Random residuals of two tones in noise on small grids (N 8-16, oversample 4-10),
    0-3 targets (some dead, some 0-3 bins apart): the decided statistic
    reaches thresholds 1e-9 below the exact one and stays below thresholds 1e-9 above."""
    rng = np.random.default_rng(11)
    for _ in range(300):
        n, oversample = int(rng.choice([8, 12, 16])), int(rng.choice([4, 6, 8, 10]))
        k = np.arange(n)
        x = rng.standard_normal((2, n)) + 1j * rng.standard_normal((2, n))
        for v in rng.uniform(0, n, 2):
            x = x + 5 * np.exp(-2j * np.pi * v * k / n)[None]
        t = int(rng.integers(0, 4))
        nu = rng.uniform(-2, n + 2, t)
        if t >= 2:
            nu[1] = nu[0] + rng.uniform(-3, 3)
        live = rng.random(t) < 0.7
        exact = reference_ratio(x, nu, live, oversample=oversample)
        assert coarse_ratio(x, nu, live, n=n, oversample=oversample) == pytest.approx(exact, rel=STAT_RTOL, abs=1e-12)
        if exact > 0:
            lo, hi = exact * (1 - 1e-9), exact * (1 + 1e-9)
            assert coarse_ratio(x, nu, live, threshold=lo, n=n, oversample=oversample) >= lo
            assert coarse_ratio(x, nu, live, threshold=hi, n=n, oversample=oversample) < hi


@pytest.mark.parametrize("phase_step", [0.0, 0.9, np.pi])
def test_two_ramps_steered_channel_from_the_cross_term_is_the_direct_one(phase_step):
    """Two model ramps: the steered channel's coarse energies, taken from the cross term the
    coarse pass keeps (``total + 2 Re(cross e^-i phi)``), are the steered residual's own
    (``|sum_r exp(-i c_r phi) U_r|^2`` summed over the antennas) at every coarse point, to
    1e-12 of the largest (measured: 1e-16), for a static tone, a moving one and one at a blind
    speed (pi: its static energy cancels); the steered residual is the ramps turned and summed."""
    rng = np.random.default_rng(61)
    k = np.arange(N)
    x = np.empty((2, 2, N), dtype=complex)
    for r, c in enumerate((-0.5, 0.5)):
        x[r] = 0.05 * (rng.standard_normal((2, N)) + 1j * rng.standard_normal((2, N)))
        x[r] += np.exp(-2j * np.pi * 40.3 * k / N)[None] * np.exp(1j * c * phase_step) * np.array([[1.0], [0.6j]])
    grid, gate = search()
    s = kernels.scratch(N, SIZE, SMALL, grid.table, 2)
    s.near[:] = False
    uc = np.fft.ifft(x, n=SMALL, axis=2)
    count_kernels.coarse_energies(uc, SIZE, s)
    out = count_kernels.steer(uc, x, N, gate, s)
    phi = s.phis[0]
    if phase_step:
        assert abs(np.angle(np.exp(1j * (phi - phase_step)))) < 0.05  # steered to the tone's phase step
    turns = np.exp(-1j * np.array([-0.5, 0.5]) * phi)
    direct = (np.abs(np.einsum("r,rpl->pl", turns, uc) * (SMALL / SIZE)) ** 2).sum(axis=0)
    np.testing.assert_allclose(s.chan, direct, rtol=0, atol=1e-12 * direct.max())
    np.testing.assert_allclose(out[0], np.einsum("r,rpn->pn", turns, x), rtol=1e-15, atol=1e-15)
