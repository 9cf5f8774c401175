"""Cramer-Rao bounds of pipeline.dsp.crb against closed forms, finite differences of the radar
model, and the empirical covariance of the score of simulated 1-bit codes."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.special import log_ndtr

from pipeline.dsp.crb import (crb, fisher, h_integral, position_bound, position_covariance, signal_jacobian,
                          weights_1bit, weights_1bit_expected, weights_bits, weights_bits_expected,
                          weights_unquantized)
from pipeline.errors import ParameterError
from pipeline.dsp.quantize import quantize
from radar_driver.model import RadarConfig, polar_to_xy, simulate_frames


def _real(frames: np.ndarray) -> np.ndarray:
    """(B, M, 2) complex frames as (B, 4M) real samples in the quantizer's layout."""
    return np.ascontiguousarray(frames).view(float).reshape(frames.shape[0], -1)


def _scene(seed: int, b: int = 3):
    rng = np.random.default_rng(seed)
    r = rng.uniform(3.0, 150.0, (b, 1))
    th = rng.uniform(-1.2, 1.2, (b, 1))
    a = rng.uniform(0.3, 1.5, (b, 1)) * np.exp(2j * np.pi * rng.random((b, 1)))
    return r, th, a


def test_signal_and_derivatives_match_the_radar_model():
    cfg = RadarConfig(samples_per_ramp=64, ramps_per_frame=2)
    rng = np.random.default_rng(1)
    r = np.stack([rng.uniform(3, 70, 3), rng.uniform(3, 70, 3)], axis=1)  # K = 2
    th = rng.uniform(-1.2, 1.2, (3, 2))
    a = np.exp(2j * np.pi * rng.random((3, 2)))
    s, ds = signal_jacobian(r, th, a, cfg)
    base = simulate_frames(r, np.rad2deg(th), a, cfg)
    assert_allclose(s, _real(base), atol=1e-12)
    for k in range(2):
        for p, step in enumerate([(1e-6, 0, 0), (0, 1e-7, 0), (0, 0, 1e-7), (0, 0, 1e-7j)]):
            def frames(sign):
                e = np.zeros((3, 2))
                e[:, k] = 1.0
                return _real(simulate_frames(r + sign * step[0] * e, np.rad2deg(th + sign * step[1] * e),
                                             a + sign * step[2] * e, cfg))
            fd = (frames(1) - frames(-1)) / (2 * abs(sum(step)))
            assert_allclose(ds[:, :, 4 * k + p], fd, atol=2e-5 * np.abs(fd).max())


def test_unquantized_range_bound_is_the_closed_form_of_a_tone_frequency():
    # per antenna and ramp the range is the frequency of a complex tone over k = 0..N-1:
    # var(omega) >= 6 s2 / (|A|^2 N (N^2 - 1)), s2 the complex noise variance (2 sigma^2 here),
    # each of the 2 antennas x R ramps an independent look; omega = 4 pi B R / (c N)
    n, ramps, sigma = 32, 3, 0.2
    cfg = RadarConfig(samples_per_ramp=n, ramps_per_frame=ramps)
    r, th, a = _scene(2)
    _, ds = signal_jacobian(r, th, a, cfg)
    cov = crb(fisher(ds, weights_unquantized(sigma)))
    var_omega = 6 * 2 * sigma**2 / (np.abs(a[:, 0]) ** 2 * n * (n * n - 1)) / (2 * ramps)
    scale = cfg.c_m_s * n / (4 * np.pi * cfg.bandwidth_hz)
    assert_allclose(cov[:, 0, 0], var_omega * scale**2, rtol=1e-6)
    # the angle: the phase of antenna 2 against antenna 1, psi = kappa sin(theta), is the
    # difference of two independent phase estimates each of variance s2 / (2 |A|^2 L), L = R N
    # (the tone's slope estimate is uncorrelated with the phase at the mean index)
    var_psi = 2 * (2 * sigma**2) / (2 * np.abs(a[:, 0]) ** 2 * ramps * n)
    kappa = 2 * np.pi * cfg.f0_hz * cfg.d_m / cfg.c_m_s
    assert_allclose(cov[:, 1, 1], var_psi / (kappa * np.cos(th[:, 0])) ** 2, rtol=1e-6)


def test_position_covariance_maps_through_the_polar_jacobian():
    r, th, _ = _scene(3)
    rng = np.random.default_rng(4)
    m = rng.standard_normal((3, 4, 4))
    cov = m @ np.swapaxes(m, 1, 2) * 1e-4
    eps = 1e-6
    jac = np.empty((3, 2, 2))
    for j, (dr, dt) in enumerate([(eps, 0), (0, eps)]):
        xp, yp = polar_to_xy(r[:, 0] + dr, th[:, 0] + dt)
        xm, ym = polar_to_xy(r[:, 0] - dr, th[:, 0] - dt)
        jac[:, :, j] = np.stack([xp - xm, yp - ym], -1) / (2 * eps)
    want = jac @ cov[:, :2, :2] @ np.swapaxes(jac, 1, 2)
    assert_allclose(position_covariance(cov, r, th)[:, 0], want, rtol=1e-6)


def test_one_bit_information_is_the_covariance_of_the_score_of_simulated_codes():
    cfg = RadarConfig(samples_per_ramp=16, ramps_per_frame=1)
    r, th, a = np.array([[20.0]]), np.array([[0.4]]), np.array([[0.8 * np.exp(0.7j)]])
    sigma, delta, alpha, draws = 0.3, 2.0, 0.6, 4000
    rng = np.random.default_rng(5)
    s, ds = signal_jacobian(r, th, a, cfg)
    m = cfg.n_measurements
    dither = alpha * delta * ((rng.random((1, m, 2)) - 0.5) + 1j * (rng.random((1, m, 2)) - 0.5))
    fim = fisher(ds, weights_1bit(s, _real(dither), sigma))[0]
    clean = simulate_frames(r, np.rad2deg(th), a, cfg)
    noise = sigma * (rng.standard_normal((draws, m, 2)) + 1j * rng.standard_normal((draws, m, 2)))
    codes = quantize(clean + noise, delta, 1, np.broadcast_to(dither, noise.shape)).reshape(draws, -1)

    def loglik(dr=0.0, dt=0.0, da=0.0):  # log-likelihood of every draw's codes, (draws,)
        z = (_real(simulate_frames(r + dr, np.rad2deg(th + dt), a + da, cfg)) + _real(dither)) / sigma
        return codes @ log_ndtr(z)[0] + (1 - codes) @ log_ndtr(-z)[0]

    steps = [dict(dr=1e-5), dict(dt=1e-5), dict(da=1e-5), dict(da=1e-5j)]
    score = np.stack([(loglik(**st) - loglik(**{k: -v for k, v in st.items()})) / (2e-5) for st in steps], 1)
    # whitened by the Fisher matrix, the score's mean is 0 and its covariance the identity,
    # within the sampling error of 4000 draws (std 1/sqrt(4000) = 0.016 for the mean and
    # sqrt(2/4000) = 0.022 for a diagonal entry): 5 standard errors
    evals, evecs = np.linalg.eigh(fim)
    white = score @ evecs / np.sqrt(evals)
    assert np.abs(white.mean(axis=0)).max() < 0.08
    assert np.abs(np.cov(white, rowvar=False) - np.eye(4)).max() < 0.11
    # and the 1-bit information is far from the unquantized one's 2/pi share here
    unq = fisher(ds, weights_unquantized(sigma))[0]
    assert np.trace(np.linalg.solve(unq, fim)) / 4 < 0.5


def test_one_bit_tends_to_two_over_pi_of_unquantized_for_small_signal_and_dither():
    cfg = RadarConfig(samples_per_ramp=32, ramps_per_frame=2)
    r, th, _ = _scene(6)
    sigma = 1.0
    for amp in (1e-4, 1e-3):
        a = np.full((3, 1), amp * np.exp(0.3j))
        s, ds = signal_jacobian(r, th, a, cfg)
        unq = fisher(ds, weights_unquantized(sigma))
        for w in (weights_1bit(s, None, sigma), weights_1bit_expected(s, 1e-3 * sigma, sigma),
                  weights_1bit_expected(s, 0.2 * amp, sigma)):
            assert_allclose(fisher(ds, w), 2 / np.pi * unq, rtol=1e-5, atol=1e-6 * np.abs(unq).max())
    # away from the limit the share drops: a signal of 2 sigma keeps less than 2/pi
    a = np.full((3, 1), 2.0 * sigma)
    s, ds = signal_jacobian(r, th, a, cfg)
    ratio = crb(fisher(ds, weights_unquantized(sigma)))[:, 0, 0] / crb(fisher(ds, weights_1bit(s, None, sigma)))[:, 0, 0]
    assert np.all(ratio < 0.5)


def test_expected_one_bit_weight_is_the_mean_over_the_dither():
    rng = np.random.default_rng(7)
    s = rng.uniform(-1.5, 1.5, (2, 50))
    sigma = np.array([0.05, 0.3])
    width = np.array([2.4, 0.7])
    u = (np.arange(20000) + 0.5) / 20000 - 0.5
    brute = np.mean([weights_1bit(s, width[:, None] * ui, sigma) for ui in u], axis=0)
    assert_allclose(weights_1bit_expected(s, width, sigma), brute, rtol=1e-4, atol=1e-6 * brute.max())
    # a wide dither spreads the information: h_integral / (a sigma) per sample near 0
    assert_allclose(weights_1bit_expected(np.zeros((1, 1)), 200.0, 1.0), h_integral() / 200.0, rtol=1e-6)


def test_multibit_weights_agree_with_one_bit_and_tend_to_unquantized():
    rng = np.random.default_rng(8)
    s = rng.uniform(-1, 1, (2, 40))
    d = rng.uniform(-0.5, 0.5, (2, 40))
    assert_allclose(weights_bits(s, d, 0.2, 2.0, 1), weights_1bit(s, d, 0.2), rtol=1e-10)
    # a fine 10-bit quantizer (step sigma / 20) keeps all but ~ step^2 / (12 sigma^2) of it
    w = weights_bits(s, d, 0.2, 0.01, 10)
    assert_allclose(w * 0.2**2, 1.0, atol=2e-3)
    # 2 bits carry more than 1 bit, less than unquantized
    w2 = weights_bits_expected(s, 1.0, 0.2, 1.0, 2, nodes=32)
    w1 = weights_1bit_expected(s, 1.0, 0.2)
    assert np.all(w2.mean(axis=1) > w1.mean(axis=1)) and np.all(w2 < 1 / 0.2**2)


def test_position_bound_orders_the_schemes_and_rejects_bad_input():
    cfg = RadarConfig()
    r, th, a = _scene(9)
    unq = position_bound(r, th, a, cfg, 0.1)
    one = position_bound(r, th, a, cfg, 0.1, alpha=0.7, delta=2.7, bits=1)
    three = position_bound(r, th, a, cfg, 0.1, alpha=0.7, delta=2.7 / 4, bits=3)
    tr = [np.trace(c, axis1=-2, axis2=-1) for c in (unq, three, one)]
    assert np.all(tr[0] < tr[1]) and np.all(tr[1] < tr[2])
    with pytest.raises(ParameterError, match="sigma"):
        position_bound(r, th, a, cfg, 0.0)
    with pytest.raises(ParameterError, match="alpha and delta"):
        position_bound(r, th, a, cfg, 0.1, bits=1)
    with pytest.raises(ParameterError, match="dither_width"):
        weights_1bit_expected(np.zeros((1, 4)), -1.0, 0.1)


def test_the_docs_one_bit_information_figures_are_h_integrals():
    """docs/science.md's "Why" of the 1-bit gap: c = 1.806, the error ratio ≈ 0.93 √(|A|/σ),
    5.4, 2.95 and 1.70 × at σ = 0.03, 0.1 and 0.3, and 2 × from σ = 0.22 |A|, recomputed."""
    import re
    from pathlib import Path

    text = " ".join((Path(__file__).resolve().parents[1] / "docs" / "science.md").read_text().split())
    c = h_integral()
    assert f"dz = {c:.3f}`" in text
    ratio = lambda sigma: np.sqrt(np.pi / (2 * c * sigma))  # noqa: E731 (|A| = 1)
    assert f"≈ {np.sqrt(np.pi / (2 * c)):.2f} √(|A|/σ)" in text
    m = re.search(r"`: ([0-9.]+), ([0-9.]+) and ([0-9.]+) × at σ = 0\.03, 0\.1 and 0\.3", text)
    assert m, "the ratios' sentence"
    assert_allclose([float(v) for v in m.groups()], ratio(np.array([0.03, 0.1, 0.3])), rtol=0.01)
    assert f"σ ≥ {np.pi / (8 * c):.2f} |A|" in text  # ratio 2
