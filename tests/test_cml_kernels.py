"""The compiled cml (pipeline.dsp.cml.kernels, engine="numba") against the numpy reference
(pipeline.dsp.cml.reference, engine="numpy") on the scenes of tests/test_cml.py, and the exact
Gaussian likelihood; the compiled detection and count test (pipeline.dsp.cml.kernels.detect)
against the reference's on every kind of scene, and codes against values.

Tolerance: the two engines take the same steps in a different floating-point order (the
reference evaluates the likelihood in float32, the kernels in float64; both sum the
Gauss--Newton Hessian in float32), so a range agrees to 1e-4 m and an amplitude to 1e-3 of
the strongest one (the frames here sit far from a step kept by one engine and refused by
the other; measured over these scenes: at most 1.6e-5 m and 2.6e-4).

Detection and the count test take the same FFT and the same sums but for the count's
mean (numpy sums pairwise, the kernel in order): statistics agree to 1e-9 relative, the
detected ranges to 1e-9 bins and a new target's amplitudes to 1e-9 of the largest."""

import numpy as np
import pytest
from scipy.special import log_ndtr as scipy_log_ndtr
from scipy.special import ndtr
from test_cml import measure, random_scenes

from pipeline.dsp.cml import CmlDecoder, CmlOptions, cml, reference
from pipeline.dsp.cml.checks import check_frames
from pipeline.dsp.cml.compiled import CompiledBlocks
from pipeline.dsp.cml.detect import back_projections, count_floor, settled_score
from pipeline.dsp.cml.grid import SearchGrid
from pipeline.dsp.cml.kernels import KERNELS, entry, likelihood as lik, linalg, model
from pipeline.dsp.cml.kernels.layout import Codes, Decision, Fit
from pipeline.dsp.cml.likelihood import block_codes
from pipeline.dsp.cml.schedule import start
from pipeline.errors import ParameterError
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.quantize import QuantizerConfig, auto_delta, batch_unit_dither, dequantize, quantize, quantize_frames
from radar_driver.model import RadarConfig, simulate_frames

RANGE_TOL_M = 1e-4
AMP_TOL = 1e-3


def agree(z, xi, delta, bits, cfg, k, likelihood="logistic", amp_tol=AMP_TOL, **kw):
    ref = cml(z, xi, delta, bits, cfg, k, options=CmlOptions(engine="numpy", likelihood=likelihood), **kw)
    got = cml(z, xi, delta, bits, cfg, k, options=CmlOptions(engine="numba", likelihood=likelihood), **kw)
    np.testing.assert_array_equal(got.present, ref.present)
    p = ref.present
    np.testing.assert_allclose(got.range_m[p], ref.range_m[p], atol=RANGE_TOL_M)
    np.testing.assert_allclose(got.amplitudes[p], ref.amplitudes[p], atol=amp_tol)
    np.testing.assert_allclose(got.sigma_eff, ref.sigma_eff, rtol=1e-3, atol=1e-9)
    return ref, got


def off_grid(b, k, seed):
    rng = np.random.default_rng(seed)
    return random_scenes(b, k, rng), rng


def reference_codes(z, xi, delta, bits, cfg, likelihood="logistic", motion=True):
    """The numpy reference's codes of checked frames, and the same arrays as the kernels'
    :data:`~pipeline.dsp.cml.kernels.layout.Codes`."""
    frames = check_frames(z, xi, delta, bits, cfg, 1, None)
    codes = reference.Codes(frames, cfg.samples_per_ramp, likelihood, motion)
    b, r, n = z.shape[0], codes.ramps, cfg.samples_per_ramp
    if bits is None:
        a = bb = codes.y.reshape(b, r, n, 4)
        kind = lik.LSQ
    else:
        a, bb = codes.ka.reshape(b, r, n, 4), codes.kb.reshape(b, r, n, 4)
        kind = lik.ONE_BIT if bits == 1 else lik.MULTI_BIT
    kernel = Codes(kind, {"logistic": lik.LOGISTIC, "gaussian": lik.GAUSSIAN}[likelihood], a, bb,
                   np.ascontiguousarray(codes.data).view(float).reshape(b, codes.rm, n, 4))
    return codes, kernel


@pytest.mark.parametrize("likelihood", ["logistic", "gaussian"])
@pytest.mark.parametrize("k", [1, 2])
def test_one_bit_off_grid(cfg, k, likelihood):
    (r, a, x), rng = off_grid(24, k, 5 + k)
    z, xi, delta = measure(r, a, x, cfg, rng)
    agree(z, xi, delta, 1, cfg, k, likelihood=likelihood)


def test_one_bit_on_grid_and_between_bins(cfg):
    rng = np.random.default_rng(1)
    r = np.array([[30.0, 31.13], [60.6, 90.3], [4.8, 40.5]])  # on a bin, between bins
    a = np.array([[10.0, -40.0], [0.0, 30.0], [-20.0, 25.0]])
    x = np.array([[1.0, 0.5j], [0.8, -0.3], [0.15, 1.0]])
    z, xi, delta = measure(r, a, x, cfg, rng)
    agree(z, xi, delta, 1, cfg, 2)


@pytest.mark.parametrize("likelihood", ["logistic", "gaussian"])
def test_multibit(cfg, likelihood):
    (r, a, x), rng = off_grid(16, 2, 4)
    z, xi, delta = measure(r, a, x, cfg, rng, bits=3)
    agree(z, xi, delta, 3, cfg, 2, likelihood=likelihood)


def test_unquantized(cfg):
    (r, a, x), rng = off_grid(8, 2, 3)
    z, _, _ = measure(r, a, x, cfg, rng, bits=None)
    agree(z, None, None, None, cfg, 2)


@pytest.mark.parametrize("noise_sigma", [None, 0.1])
def test_noisy_small_alpha(cfg, noise_sigma):
    (r, a, x), rng = off_grid(16, 2, 8)
    z, xi, delta = measure(r, a, x, cfg, rng, alpha=0.1, noise=0.1)
    # a dither this small leaves a weak target's amplitude ill-conditioned: frame 3's second target
    # moves 1.5e-4 when the dither changes by 1e-10 of itself (reference engine), so the engines'
    # different rounding shows there, by CPU: 1.09e-3 on an AMD EPYC host (avx2, no avx512)
    for likelihood in ("logistic", "gaussian"):
        agree(z, xi, delta, 1, cfg, 2, noise_sigma=noise_sigma, likelihood=likelihood, amp_tol=2 * AMP_TOL)


def test_k_auto_and_gate(cfg):
    (r, a, x), rng = off_grid(16, 2, 12)
    x[::3, 1] = 0.0  # some frames hold one target only
    z, xi, delta = measure(r, a, x, cfg, rng)
    ref, _ = agree(z, xi, delta, 1, cfg, 4, pfa=1e-3)
    assert ref.present.sum(axis=1).min() >= 1
    gate = RangeGate(min_range_m=20.0, max_range_m=100.0)
    # targets inside the gate (beyond it the fit of a phantom is flat and the engines may
    # part by a step: amplitudes then agree to 1e-2 only, measured), one at its far end
    r = 21.0 + (r - 3.0) * (78.0 / 147.0)
    r[0, 0] = 99.9
    z, xi, delta = measure(r, a, x, cfg, rng)
    agree(z, xi, delta, 1, cfg, 2, gate=gate)
    agree(z, xi, delta, 1, cfg, 3, gate=gate, pfa=1e-3)


def test_the_compiled_logistic_likelihood_matches_the_reference(cfg):
    """The kernels' branch-free float32 logistic (a polynomial exp and log1p, vectorized) against
    the numpy reference's exact one, from the greedy stage's scale to the annealing's floor:
    the NLL to 1e-6 relative, its derivatives to 1e-5 of their largest (measured: 2.5e-7, 3.2e-7
    and 6.4e-7); a multi-bit cell's open (infinite) end adds nothing. The NLL alone
    (``nll_frame``, the LM candidates' test) is the same NLL."""
    (r, a, x), rng = off_grid(4, 2, 21)
    n = cfg.samples_per_ramp
    for bits, motion in ((1, True), (3, True), (1, False)):
        z, xi, delta = measure(r, a, x, cfg, rng, bits=bits, noise=0.05)
        codes, kernel = reference_codes(z, xi, delta, bits, cfg, motion=motion)
        rm = codes.rm  # a model of each ramp (motion) or one for all
        for scale in (0.25, 0.03, 1.0 / 512):
            mu = 0.4 * delta[:, None, None, None, None] * rng.standard_normal((4, rm, n, 2, 2))
            sigma = scale * delta
            nll, g, h = codes.evaluate(mu, sigma)
            kg, kh = np.empty((4, rm, n, 4)), np.empty((4, rm, n, 4))
            knll = lik.evaluate(kernel, np.ascontiguousarray(mu).reshape(4, rm, n, 4), sigma, kg, kh)
            np.testing.assert_allclose(knll, nll, rtol=1e-6)
            np.testing.assert_allclose(kg, g.reshape(4, rm, n, 4), rtol=0, atol=1e-5 * np.abs(g).max())
            np.testing.assert_allclose(kh, h.reshape(4, rm, n, 4), rtol=0, atol=1e-5 * np.abs(h).max())
            if bits == 1:
                work = np.empty((3, rm, 4 * n), np.float32)
                alone = [lik.nll_frame(kernel.a[f], kernel.b[f], np.ascontiguousarray(mu[f]).reshape(rm, n, 4),
                                       sigma[f], work) for f in range(4)]
                np.testing.assert_allclose(alone, knll, rtol=1e-6)
    assert lik.softplus(np.float32(np.inf))[0] < 1e-17  # -log F(+inf) = 0


def test_the_likelihoods_polynomial_exp_and_log1p():
    """``exp(-a)`` on [0, 40] (a polynomial squared 5 times) and ``log(1 + e)`` on [0, 1] (a
    polynomial in e, also for e down to exp(-40)) against numpy's in float64, relative
    (measured: 1.0e-5 and 1.1e-7)."""
    a = np.linspace(0.0, lik.SOFTPLUS_REACH, 4001).astype(np.float32)
    got = np.array([lik.exp_neg(v) for v in a])
    np.testing.assert_allclose(got, np.exp(-a.astype(float)), rtol=1.5e-5, atol=0)
    e = np.concatenate([np.linspace(0.0, 1.0, 2001), np.exp(-np.linspace(0.0, 40.0, 401))]).astype(np.float32)
    got = np.array([lik.log1p_small(v) for v in e])
    np.testing.assert_allclose(got, np.log1p(e.astype(float)), rtol=2e-7, atol=0)


def test_the_gaussian_likelihood_is_the_probability_of_the_code(cfg):
    """NLL of the numpy reference and of the kernel against ``-log(Phi(hi) - Phi(lo))``
    computed directly, and its derivatives against finite differences."""
    (r, a, x), rng = off_grid(2, 1, 20)
    for bits in (1, 3):
        z, xi, delta = measure(r, a, x, cfg, rng, bits=bits, noise=0.05)
        n = cfg.samples_per_ramp
        codes, kernel = reference_codes(z, xi, delta, bits, cfg, "gaussian")
        rm, ramps = codes.rm, codes.ramps
        mu = 0.3 * delta[:, None, None, None, None] * rng.standard_normal((2, rm, n, 2, 2))
        sigma = np.array([0.1, 0.3]) * delta  # codes within ~20 sigma: the direct P is finite
        nll, g, h = codes.evaluate(mu, sigma)
        # direct: the cell of lambda = Re/Im(Gamma + xi) - xi, Phi by scipy's log_ndtr (float64, no tricks)
        so = kernel.b.astype(float)  # 1 bit: s xi; lambda >= -xi for s = 1, < -xi for s = -1
        lo = kernel.a.astype(float) if bits > 1 else np.where(kernel.a > 0, -so, -np.inf)
        hi = kernel.b.astype(float) if bits > 1 else np.where(kernel.a > 0, np.inf, so)
        m = np.broadcast_to(mu.reshape(2, rm, n, 4), (2, ramps, n, 4))  # each ramp's model
        s = sigma[:, None, None, None]
        up_, lo_ = (hi - m) / s, (lo - m) / s
        p = np.where(lo_ + up_ > 0, ndtr(-lo_) - ndtr(-up_), ndtr(up_) - ndtr(lo_))  # the tail without cancellation
        np.testing.assert_allclose(nll, -np.log(p).reshape(2, -1).sum(axis=1), rtol=1e-6)
        kg, kh = np.empty((2, rm, n, 4)), np.empty((2, rm, n, 4))
        knll = lik.evaluate(kernel, np.ascontiguousarray(mu).reshape(2, rm, n, 4), sigma, kg, kh)
        np.testing.assert_allclose(knll, nll, rtol=1e-9)
        np.testing.assert_allclose(kg, g.reshape(2, rm, n, 4), rtol=1e-6, atol=1e-9 * np.abs(g).max())
        np.testing.assert_allclose(kh, h.reshape(2, rm, n, 4), rtol=1e-5, atol=1e-9 * np.abs(h).max())
        eps = 1e-6 * delta[:, None, None, None, None]
        up = codes.evaluate(mu + eps, sigma)[1]
        down = codes.evaluate(mu - eps, sigma)[1]
        np.testing.assert_allclose((up - down) / (2 * eps), h, rtol=1e-4, atol=1e-6 * np.abs(h).max())


def test_log_ndtr_in_the_tails():
    v = np.array([-1e3, -200.0, -37.0, -20.5, -19.5, -5.0, 0.0, 3.0, 8.0, 40.0])
    got = np.array([lik.log_ndtr(t) for t in v])
    np.testing.assert_allclose(got, scipy_log_ndtr(v), rtol=1e-9, atol=1e-300)


def test_unknown_engine_or_likelihood_is_a_parameter_error(cfg):
    (r, a, x), rng = off_grid(1, 1, 0)
    z, xi, delta = measure(r, a, x, cfg, rng)
    with pytest.raises(ParameterError, match="engine"):
        cml(z, xi, delta, 1, cfg, 1, options=CmlOptions(engine="fortran"))
    with pytest.raises(ParameterError, match="likelihood"):
        cml(z, xi, delta, 1, cfg, 1, options=CmlOptions(likelihood="cauchy"))


def test_the_kinds_of_frames_are_the_kernels_codes(cfg):
    (r, a, x), rng = off_grid(1, 1, 0)
    for bits, kind in ((None, lik.LSQ), (1, lik.ONE_BIT), (3, lik.MULTI_BIT)):
        z, xi, delta = measure(r, a, x, cfg, rng, bits=bits)
        frames = check_frames(z, xi, delta, bits, cfg, 1, None)
        assert block_codes(frames, cfg.samples_per_ramp, "logistic", True).kernel.kind == kind


def compiled_detect(blocks, codes, ref, grid, count, nu0=None):
    """The compiled count statistic (``count``; else None), detection (unless ``nu0`` (B,) bins is
    given), the amplitudes and the phase step there, on the state of the reference's fit ``ref``."""
    b, n, rm = ref.nu.shape[0], codes.n, codes.rm
    mu = np.ascontiguousarray(ref.mu).reshape(b, rm, n, 4)
    g = np.ascontiguousarray(ref.g).reshape(b, rm, n, 4) if hasattr(ref, "g") else mu
    h = np.ascontiguousarray(ref.h).reshape(b, rm, n, 4) if hasattr(ref, "h") else mu
    fit = Fit(np.ascontiguousarray(ref.nu), np.ascontiguousarray(ref.phi), np.ascontiguousarray(ref.amp),
              np.ascontiguousarray(ref.live), np.ones(b), np.zeros(b), np.ones(b), mu, g, h)
    search = blocks.search(grid)
    src = back_projections(codes, fit, search, count, nu0 is not None, False)
    found = Decision(-1.0, np.ones(b, dtype=bool), np.zeros(b), np.empty(b) if nu0 is None else np.array(nu0, float),
                     np.empty((b, 2), dtype=complex), count_floor(codes, fit, search.grid.oversample), np.zeros(b))
    entry.detect(src, search.kernel, search.gate, search.seed_gate, fit.nu, fit.live, tuple(found))
    return (found.stat if count else None), found.nu0, found.amp0, found.phi0


def detection_agrees(z, xi, delta, bits, cfg, gate=None, oversample=8, motion=True):
    """The compiled detection, count statistic, amplitudes and phase step against the
    reference's, on the empty model and after one and two targets found (the second
    detection on the score)."""
    b = z.shape[0]
    options = CmlOptions(oversample=oversample, motion=motion)
    grid = SearchGrid(gate, cfg, oversample)
    frames = check_frames(z, xi, delta, bits, cfg, 1, None)
    blocks = CompiledBlocks(cfg, options)
    codes = block_codes(frames, cfg.samples_per_ramp, "logistic", motion)
    ref_codes = reference.Codes(frames, cfg.samples_per_ramp, "logistic", motion)
    fit = reference.Fit(ref_codes, grid)
    sigma, _, amp_cap = start(frames)
    fit.evaluate(sigma)
    for t in range(2):
        stat, nu0, amp0, phi0 = compiled_detect(blocks, codes, fit, grid, True)
        np.testing.assert_allclose(stat, reference.count_statistic(fit, ref_codes, oversample), rtol=1e-9)
        ref_nu = reference.detect(fit, ref_codes, oversample)
        np.testing.assert_allclose(nu0, ref_nu, rtol=0, atol=1e-9)
        ref_amp, ref_phi = reference.amplitude_at(ref_codes, fit, ref_nu)
        np.testing.assert_allclose(amp0, ref_amp, rtol=0, atol=1e-9 * np.abs(ref_amp).max())
        np.testing.assert_allclose(phi0, ref_phi, rtol=0, atol=1e-9)
        assert compiled_detect(blocks, codes, fit, grid, False)[0] is None
        np.testing.assert_allclose(compiled_detect(blocks, codes, fit, grid, False)[1], ref_nu, rtol=0, atol=1e-9)
        live = np.ones((b, 1), dtype=bool)
        live[::4] = t == 0  # some frames' second target is not live: its guard band is cleared
        fit.set(np.concatenate([fit.nu, ref_nu[:, None]], axis=1), np.concatenate([fit.phi, ref_phi[:, None]], axis=1),
                np.concatenate([fit.amp, ref_amp[:, None]], axis=1), np.concatenate([fit.live, live], axis=1))
        fit.evaluate(sigma)
        fit.run(np.repeat(sigma[:, None], 2, axis=1), amp_cap)
    given = fit.nu[:, 0] + 0.25
    _, nu_given, amp_given, _ = compiled_detect(blocks, codes, fit, grid, False, given)
    np.testing.assert_array_equal(nu_given, given)
    ref = reference.amplitude_at(ref_codes, fit, given)[0]
    np.testing.assert_allclose(amp_given, ref, rtol=0, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("kind", ["one_bit", "on_grid", "three_bit", "unquantized", "noisy_small_alpha", "gated",
                                  "one_target_frames"])
def test_compiled_detection_and_count_agree_with_numpy(cfg, kind):
    (r, a, x), rng = off_grid(12, 2, 30)
    if kind == "on_grid":
        r[:, 0] = np.round(r[:, 0] / cfg.range_resolution_m) * cfg.range_resolution_m
    if kind == "one_target_frames":
        x[::2, 1] = 0.0
    gate = RangeGate(min_range_m=20.0, max_range_m=100.0) if kind == "gated" else None
    bits = {"three_bit": 3, "unquantized": None}.get(kind, 1)
    z, xi, delta = measure(r, a, x, cfg, rng, bits=bits, **({"alpha": 0.1, "noise": 0.1}
                                                           if kind == "noisy_small_alpha" else {}))
    for motion in (True, False):
        detection_agrees(z, xi, delta, bits, cfg, gate, motion=motion)


@pytest.mark.parametrize("motion", [True, False])
def test_the_settled_score_agrees_with_numpy(cfg, motion):
    """The efficient score the count test reads once the fit settled (the NLL's derivatives
    less what the live targets' own parameters explain, on each model ramp; with a phase step
    its share too): the compiled one (kernels.refine.settled_score) against the reference's
    (Fit.settled_score), on 1-bit frames of two moving targets after a few refinement steps,
    one frame's second target not live. It takes out what the parameters explain: the
    gradient of the live targets' parameters on it is a small part of the one on ``g``."""
    (r, a, x), rng = off_grid(6, 2, 60)
    v = rng.uniform(-2.0, 2.0, r.shape)
    gam = simulate_frames(r, a, x, cfg, velocity_mps=v)
    gam = gam + 0.05 * (rng.standard_normal(gam.shape) + 1j * rng.standard_normal(gam.shape))
    delta = auto_delta(gam)
    xi = 0.45 * delta[:, None, None] * batch_unit_dither(gam.shape, rng)
    z = dequantize(quantize(gam, delta, 1, xi), delta, 1)
    grid = SearchGrid(None, cfg, 8)
    frames = check_frames(z, xi, delta, 1, cfg, 1, None)
    codes = block_codes(frames, cfg.samples_per_ramp, "logistic", motion)
    ref_codes = reference.Codes(frames, cfg.samples_per_ramp, "logistic", motion)
    fit = reference.Fit(ref_codes, grid)
    sigma, _, amp_cap = start(frames)
    nu = r / cfg.range_resolution_m + 0.05
    live = np.ones(r.shape, dtype=bool)
    live[0, 1] = False
    phi = np.zeros(r.shape)
    amp = reference.amplitude_at(ref_codes, fit, nu[:, 0])[0]
    fit.set(nu, phi, np.stack([amp, np.where(live[:, 1:], 0.5 * amp, 0.0)], axis=1), live)
    fit.evaluate(sigma)
    fit.run(np.repeat(sigma[:, None], 3, axis=1), amp_cap)
    fit.settled_score()
    b, n, rm = r.shape[0], codes.n, codes.rm
    ker = Fit(np.ascontiguousarray(fit.nu), np.ascontiguousarray(fit.phi), np.ascontiguousarray(fit.amp),
              np.ascontiguousarray(fit.live), np.ones(b), np.zeros(b), np.ones(b),
              *(np.ascontiguousarray(y).reshape(b, rm, n, 4) for y in (fit.mu, fit.g, fit.h)))
    ge = settled_score(codes, ker)
    want = np.ascontiguousarray(fit.ge).reshape(b, rm, n, 4)
    moved = want - ker.g
    assert np.abs(moved).max() > 0.0
    np.testing.assert_allclose(ge, want, rtol=0, atol=1e-6 * np.abs(moved).max())
    # the live targets' parameters take (almost) none of it up: their Gauss--Newton step on ge
    # is a small part of the one on g (not 0: the system's curvature is the ramps' mean)
    fit.lm = np.zeros(b)
    before = np.abs(fit._solve()[fit.live])
    fit.g = fit.ge
    left = np.abs(fit._solve()[fit.live])
    assert left.max() < 0.05 * before.max()


@pytest.mark.parametrize("bits", [1, 3])
def test_codes_decode_as_their_values(cfg, bits):
    (r, a, x), _ = off_grid(6, 2, 40)
    q = quantize_frames(simulate_frames(r, a, x, cfg), QuantizerConfig(bits=bits, alpha=1.0), np.arange(6))
    for kw in ({}, {"pfa": 1e-3}, {"init_range_m": r[:, :1]}):
        for engine in ("numba", "numpy"):
            by_values = cml(q.values(), q.dither(), q.delta, bits, cfg, 2, options=CmlOptions(engine=engine), **kw)
            by_codes = cml(q.codes, q.dither(), q.delta, bits, cfg, 2, options=CmlOptions(engine=engine), **kw)
            for name in ("range_m", "amplitudes", "statistic_db", "sigma_eff", "present"):
                np.testing.assert_allclose(getattr(by_codes, name), getattr(by_values, name), rtol=1e-12,
                                           atol=1e-12, err_msg=f"{name} {kw} {engine}")


@pytest.mark.parametrize("bits", [1, 3])
def test_compiled_codes_arrays_are_numpys(cfg, bits):
    """The kernels' arrays built by one kernel (from values and from codes) are those of the
    numpy reference, bit for bit; so is Z - xi folded over the ramps."""
    (r, a, x), _ = off_grid(3, 2, 42)
    q = quantize_frames(simulate_frames(r, a, x, cfg), QuantizerConfig(bits=bits, alpha=1.0), np.arange(3))
    n = cfg.samples_per_ramp
    delta = np.broadcast_to(q.delta, (3,)).astype(float)
    per_ramp = q.values().reshape(3, -1, n, 2) - q.dither().reshape(3, -1, n, 2)
    for motion in (True, False):
        _, ref = reference_codes(q.values(), q.dither(), delta, bits, cfg, motion=motion)
        want = per_ramp if motion else per_ramp.sum(axis=1, keepdims=True)
        for z in (q.values(), q.codes):
            got = block_codes(check_frames(z, q.dither(), delta, bits, cfg, 1, None), n, "logistic", motion).kernel
            assert got.kind == ref.kind
            np.testing.assert_array_equal(got.a, ref.a)
            np.testing.assert_array_equal(got.b, ref.b)
            np.testing.assert_allclose(got.data.view(complex).reshape(want.shape), want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_values_off_the_levels_are_a_parameter_error(cfg, engine):
    (r, a, x), rng = off_grid(2, 1, 43)
    z, xi, delta = measure(r, a, x, cfg, rng, bits=3)
    cml(z, xi, delta, 3, cfg, 1, options=CmlOptions(engine=engine))
    for bad in (z * (1 + 1e-3), z * 8):  # between the levels; beyond the top one
        with pytest.raises(ParameterError, match="not a 3-bit quantized frame"):
            cml(bad, xi, delta, 3, cfg, 1, options=CmlOptions(engine=engine))


def test_codes_beyond_the_bits_are_a_parameter_error(cfg):
    (r, a, x), _ = off_grid(2, 1, 41)
    q = quantize_frames(simulate_frames(r, a, x, cfg), QuantizerConfig(alpha=1.0), np.arange(2))
    codes = q.codes.copy()
    codes[1, 3, 0, 1] = 2
    with pytest.raises(ParameterError, match=r"codes must be integers in \[0, 1\]"):
        cml(codes, q.dither(), q.delta, 1, cfg, 1)
    with pytest.raises(ParameterError, match="bits given"):
        cml(q.codes, None, None, None, cfg, 1)


def test_model_is_the_atoms_times_the_amplitudes():
    """The compiled model (blocks of 32 samples by products) against exp() directly, also
    for N not a multiple of the block; with a phase step, ramp q's amplitudes turned by
    ``exp(i (q - (Rm - 1) / 2) phi)``."""
    rng, steps = np.random.default_rng(50), np.random.default_rng(53)
    for n, rm in ((256, 1), (100, 1), (7, 1), (256, 2), (100, 3)):
        kc = np.arange(n) - (n - 1) / 2.0
        nu = rng.uniform(0, n, 3)
        phi = steps.uniform(-np.pi, np.pi, 3)
        amp = rng.standard_normal((3, 2)) + 1j * rng.standard_normal((3, 2))
        w, mu = np.empty((3, 2, n)), np.empty((rm, n, 4))
        cr = model.ramp_offsets(rm)
        model.model(nu, phi, amp, kc, cr, w, mu)
        atoms = np.exp((-2j * np.pi / n) * nu[:, None] * kc)
        np.testing.assert_allclose(w[:, 0] + 1j * w[:, 1], atoms, rtol=0, atol=1e-13)
        for q in range(rm):
            turn = np.exp(1j * cr[q] * phi)[:, None] if rm > 1 else 1.0
            np.testing.assert_allclose(mu[q].view(complex), atoms.T @ (amp * turn), rtol=0, atol=1e-12)


@pytest.mark.parametrize("rm", [1, 2, 3])
def test_normal_equations_are_the_jacobians(rm):
    """The Gauss--Newton system from the weighted sums against ``sum_q sum_j J_qj^T diag(h_j)
    J_qj`` and ``sum_q sum_j J_qj^T g_qj`` with the numpy reference's Jacobians (float64) of
    each model ramp q (the ramps share one curvature h, as :func:`model.sums` takes them):
    the Hessian's sums are float32 (as the reference's), so it agrees to 1e-6 of its largest
    entry."""
    rng = np.random.default_rng(51)
    n, k = 256, 2
    kc = np.arange(n) - (n - 1) / 2.0
    nu = np.array([40.3, 41.9])
    phi = np.array([0.7, -2.9]) if rm > 1 else np.zeros(2)
    amp = rng.standard_normal((k, 2)) + 1j * rng.standard_normal((k, 2))
    g, h1 = rng.standard_normal((rm, n, 4)), rng.uniform(0.0, 2.0, (n, 4))
    h = np.repeat(h1[None], rm, axis=0)
    cr = model.ramp_offsets(rm)
    w, mu = np.empty((k, 2, n)), np.empty((rm, n, 4))
    model.model(nu, phi, amp, kc, cr, w, mu)
    cw = 2.0 * np.pi * kc / n
    gram, proj = np.empty((3, 4, 2 * k, 2 * k)), np.empty((rm, 2, 4, 2 * k))
    model.sums(w, cw, cw.astype(np.float32), g, h, np.empty((4, n), np.float32), np.empty((2 * k, n), np.float32),
               gram, proj)
    npar = model.PARAMS * k
    hess, grad = np.empty((npar, npar)), np.empty(npar)
    model.normal_equations(amp, phi, cr, gram, proj, hess, grad, np.empty((k, 2)), np.empty((rm, 4, 4 * k, 2)),
                           np.empty((4, 4 * k, 4), dtype=np.int64))
    atoms = w[:, 0] + 1j * w[:, 1]
    dw = atoms * (-1j * cw)
    r = np.concatenate([atoms.real, dw.real, atoms.imag, dw.imag])  # the reference's rows (4K, N)
    want_h, want_g = np.zeros((npar, npar)), np.zeros(npar)
    for q in range(rm):
        zc = reference.coefficients(amp[None], phi[None], cr[q])[0]  # (4, 4K, 6K)
        if rm == 1:
            zc[..., 5::model.PARAMS] = 0.0  # the static model has no phase step
        jac = np.einsum("rn,jrq->jnq", r, zc)
        want_h += np.einsum("jnq,nj,jnp->qp", jac, h1, jac)
        want_g += np.einsum("jnq,nj->q", jac, g[q])
    np.testing.assert_allclose(hess, want_h, rtol=0, atol=1e-6 * np.abs(hess).max())
    np.testing.assert_allclose(grad, want_g, rtol=1e-9, atol=1e-12 * np.abs(grad).max())


def test_solve_by_cholesky_and_by_elimination():
    rng = np.random.default_rng(52)
    a = rng.standard_normal((10, 10))
    rhs = rng.standard_normal(10)
    lw, x = np.empty((10, 10)), np.empty(10)
    for m in (a @ a.T + 1e-3 * np.eye(10), a + a.T):  # positive definite; indefinite: the fall-back
        linalg.solve(m.copy(), rhs.copy(), lw, x)
        np.testing.assert_allclose(x, np.linalg.solve(m, rhs), rtol=1e-9, atol=1e-12)


def test_a_decoder_keeps_its_tables_and_buffers_clean(cfg):
    """A decoder held across calls (its grid tables, thresholds and zero-padded buffers kept)
    decodes as a fresh one, bit for bit: after blocks of more frames, another gate, a count
    test; so does one of another N and grid (oversample 16)."""
    (r, a, x), rng = off_grid(8, 2, 44)
    z, xi, delta = measure(r, a, x, cfg, rng)
    held = CmlDecoder(cfg)
    first = held.decode(z[:3], xi[:3], delta[:3], 1, 2)
    held.decode(z, xi, delta, 1, 2)
    held.decode(z, xi, delta, 1, 4, pfa=1e-3, gate=RangeGate(10.0, 120.0))
    again = held.decode(z[:3], xi[:3], delta[:3], 1, 2)
    fresh = cml(z[:3], xi[:3], delta[:3], 1, cfg, 2)
    for name in ("range_m", "amplitudes", "statistic_db", "sigma_eff", "present"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))
        np.testing.assert_array_equal(getattr(fresh, name), getattr(first, name))
    small = RadarConfig(samples_per_ramp=cfg.samples_per_ramp // 2)
    zz, xx = z[:, :small.samples_per_ramp], xi[:, :small.samples_per_ramp]
    ref = cml(zz, xx, delta, 1, small, 2, options=CmlOptions(engine="numpy", oversample=16))
    got = CmlDecoder(small, CmlOptions(oversample=16)).decode(zz, xx, delta, 1, 2)
    np.testing.assert_allclose(got.range_m, ref.range_m, atol=RANGE_TOL_M)


def fresh_process(code: str) -> str:
    """What ``code`` prints, run by this interpreter in a process of its own (numba's
    dispatchers start empty there: what it loads is what ``code`` makes it load)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_load_kernels_loads_1_bit_codes_first():
    """A localizer loads the kernels of 1-bit codes (``common``) before it listens; the other
    kinds after. In a fresh process, from numba's cache: each call adds kernels' signatures."""
    code = ("from pipeline.dsp.cml import load_kernels\n"
            "from pipeline.dsp.cml.kernels import KERNELS\n"
            "from pipeline.dsp.cml.loading import kind_of\n"
            "count = lambda: sum(len(k.signatures) for k in KERNELS)\n"
            "before = count(); load_kernels(kinds=(kind_of(1),)); one_bit = count()\n"
            "load_kernels(common=True); common = count(); load_kernels(); everything = count()\n"
            "load_kernels(kinds=(kind_of(None), kind_of(5))); print(before, one_bit, common, everything, count())")
    before, one_bit, common, everything, again = map(int, fresh_process(code).split())
    # the kind of 1-bit codes alone is the common kind; every kind loads more; loaded kinds add nothing
    assert before == 0 < one_bit == common < everything == again


@pytest.mark.parametrize("auto", [True, False], ids=["K-auto", "K-given"])
def test_the_loaded_kernels_are_every_kernel_a_localizer_decodes_with(auto):
    """After ``load_kernels`` of 1-bit codes, the decodes a localizer makes (K given or K auto,
    in a range gate, cold or warm, a target inside and one outside the gate; its tracker's
    refinement of a static track on stacked frames) need no other
    compiled signature: on a fresh install (``make`` compiles what ``load_kernels`` loads) a
    run's first full search does not compile for a minute while frames wait. A node with K
    given and no warm start loads those decodes alone (``count=False, warm=False``): K given
    in a gate, a return outside it modelled, and its tracker's K given integration."""
    decodes = ("    d.decode(z, q.dither(), q.delta, 1, 4, pfa=1e-3, gate=gate)\n"
               "    d.decode(z, q.dither(), q.delta, 1, 4, pfa=1e-3, gate=gate, init_range_m=warm)\n") if auto else ""
    tracker = "integrate(still, cfg, 4, gate, 1e-3), " if auto else ""
    code = ("import numpy as np\n"
            "from pipeline.dsp.cml import CmlDecoder, load_kernels\n"
            "from pipeline.dsp.cml.kernels import KERNELS\n"
            "from pipeline.dsp.cml.loading import kind_of\n"
            "from pipeline.dsp.gate import RangeGate\n"
            "from pipeline.dsp.quantize import QuantizerConfig, quantize_frames\n"
            "from radar_driver.model import RadarConfig, simulate_frames\n"
            f"load_kernels(kinds=(kind_of(1),), count={auto}, warm={auto})\n"
            "loaded = [len(k.signatures) for k in KERNELS]\n"
            "cfg = RadarConfig()\n"
            "r, a = np.array([[40.0, 150.0], [12.5, 80.3]]), np.array([[10.0, -20.0], [0.0, 30.0]])\n"
            "g = simulate_frames(r, a, np.array([[1.0, 2.0], [0.5, 1.0]], dtype=complex), cfg)\n"
            "g += 0.1 * np.random.default_rng(1).standard_normal(g.shape + (2,)).view(complex)[..., 0]\n"
            "q = quantize_frames(g, QuantizerConfig(alpha=0.45), np.arange(2))\n"
            "d, gate, warm = CmlDecoder(cfg), RangeGate(2.0, 120.0), np.array([[40.0] + [np.nan] * 3] * 2)\n"
            "for z in (q.codes, q.values()):\n"
            "    d.decode(z, q.dither(), q.delta, 1, 2, gate=gate)\n"
            f"{decodes}"
            "from pipeline.dsp.integrate import integrate\n"  # a static track's refinement (the tracker's)
            "still = quantize_frames(np.repeat(g[:1], 10, axis=0), QuantizerConfig(alpha=0.45), np.arange(10))\n"
            f"{tracker}integrate(still, cfg, 2, gate)\n"
            "print([f'{k.py_func.__module__}.{k.py_func.__qualname__}' for k, s in zip(KERNELS, loaded)\n"
            "       if len(k.signatures) != s])\n")
    compiled = fresh_process(code).strip()
    assert compiled == "[]", f"kernels compiled after load_kernels: {compiled}"


def test_a_node_told_its_bits_loads_their_kernels_alone():
    """``qradar run``'s localizer knows its quantizer's bits: it loads that kind's kernels (codes
    of 2-16 bits share the 3-bit kind's) and starts no thread for the others; a standalone one
    loads the others in a thread. A kind cml does not have is refused by name."""
    from pipeline.dsp.cml.loading import KINDS, kind_of, load_kernels
    from pipeline.dsp.cml.options import DEFAULT_LIKELIHOOD
    from pipeline.nodes.stream import LocalizeNode, LocalizerConfig
    from pipeline.bus.session import BusConfig
    from pipeline.nodes.transport import MemoryTransport

    assert kind_of(1) == KINDS[0] and kind_of(None) == (None, DEFAULT_LIKELIHOOD)
    assert kind_of(2) == kind_of(16) == (3, DEFAULT_LIKELIHOOD)
    with pytest.raises(ValueError, match="none of cml's"):
        load_kernels(kinds=((2, DEFAULT_LIKELIHOOD),))
    for bits, thread in ((1, False), ("any", True)):
        node = LocalizeNode(BusConfig(), LocalizerConfig(k=1), session=MemoryTransport(), bits=bits).start()
        try:
            assert (node._loading is not None) == thread, bits
        finally:
            node.stop()
            if node._loading is not None:  # its kernels loaded before the next test counts signatures
                node._loading.join(600)
                assert not node._loading.is_alive()


def test_no_array_layout_makes_a_new_compiled_signature(cfg):
    """Read-only, strided, unaligned or other-dtype inputs (values, codes, dither, delta) decode
    as C-contiguous ones, bit for bit, and reach the kernels' compiled signatures: not one
    kernel compiles a new one (a live node's first frame of a new layout does not wait a minute)."""
    (r, a, x), rng = off_grid(3, 2, 44)
    q = quantize_frames(simulate_frames(r, a, x, cfg), QuantizerConfig(alpha=0.7), np.arange(3))
    decoder = CmlDecoder(cfg)
    kw = dict(pfa=1e-3, gate=RangeGate(2.0, 140.0))
    want = decoder.decode(q.codes, q.dither(), q.delta, 1, 4, **kw)
    signatures = [len(k.signatures) for k in KERNELS]

    def read_only(v):
        v = np.array(v)
        v.flags.writeable = False
        return v

    def unaligned(v):
        buf = np.empty(v.nbytes + 1, dtype=np.uint8)[1:].view(v.dtype).reshape(v.shape)
        buf[...] = v
        return buf

    xi, delta = q.dither(), np.asarray(q.delta, dtype=float)
    for args in ((read_only(q.codes), read_only(xi), read_only(delta)),
                 (q.codes, np.repeat(xi, 2, axis=1)[:, ::2], np.repeat(delta, 2)[::2]),
                 (q.codes.astype(np.int64), unaligned(xi), delta.astype(np.float32).astype(float)),
                 (np.asfortranarray(q.codes), np.asfortranarray(xi), list(delta))):
        got = decoder.decode(*args, 1, 4, **kw)
        for name in ("range_m", "amplitudes", "statistic_db", "sigma_eff", "present"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    new = [k.py_func.__qualname__ for k, before in zip(KERNELS, signatures) if len(k.signatures) != before]
    assert set(new) <= {"codes_arrays"}, new  # int64 codes: codes_arrays' second dtype, loaded by the warm-up
