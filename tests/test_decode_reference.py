"""The fast qiht decoder (issue 13) against the implementation it replaced, kept here as
the reference: QIHT gives the same supports and amplitudes, the likelihood stage the
same amplitudes to floating-point rounding."""

import numpy as np
import pytest

from pipeline.dsp.decode import DecoderConfig, decode, ml_refine, ml_temperatures, qiht
from pipeline.dsp.localize import back_project, back_project_ramps, detections_from_support, grid_statistic_db, \
    project_theta_k
from experiments.montecarlo import SceneSpec, draw_scenes
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from radar_driver.model import RadarConfig, carrier, simulate_frames


# -- the reference: pipeline/dsp/decode.py before issue 13 ------------------------------------
def _requantize(lam, d, bits):
    half = 1 << (bits - 1)
    return (np.clip(np.floor(lam / d), -half, half - 1) + 0.5) * d


def reference_qiht(z, xi, delta, bits, config, k, iters=10, mu=1.0):
    n = config.samples_per_ramp
    b, m, _ = z.shape
    ramps = m // n
    car = carrier(config)[None, :, None]
    zr = np.ascontiguousarray(z).view(float).reshape(b, ramps, n, 2, 2)
    xr = np.ascontiguousarray(xi).view(float).reshape(b, ramps, n, 2, 2)
    d = delta[:, None, None, None, None]
    scale = mu * (n / m)
    x, support = project_theta_k(back_project_ramps(z, config), k)
    prev_sup, prev_bad, stable, done = np.sort(support, axis=1), None, 0, 0
    z_pos, z_twice = zr > 0, 2 * zr
    for it in range(iters):
        g = np.fft.fft(x * car, axis=1).view(float).reshape(b, 1, n, 2, 2)
        lam = g + xr
        if bits == 1:
            wrong = (lam >= 0) != z_pos
            resid = np.where(wrong, z_twice, 0.0)
            bad = np.count_nonzero(wrong.reshape(b, -1), axis=1)
        else:
            resid = zr - _requantize(lam, d, bits)
            bad = np.count_nonzero(resid.reshape(b, -1), axis=1)
        folded = resid.sum(axis=1).reshape(b, n, 4).view(complex)
        step = np.fft.ifft(folded, axis=1) * np.conj(car) * scale
        x, support = project_theta_k(x + step, k)
        sup_sorted = np.sort(support, axis=1)
        same = prev_bad is not None and np.array_equal(sup_sorted, prev_sup) and np.array_equal(bad, prev_bad)
        stable = stable + 1 if same else 0
        prev_sup, prev_bad, done = sup_sorted, bad, it + 1
        if stable >= 3:
            break
    return x, support, done


def reference_ml_refine(z, xi, delta, support, x0, config):
    b, m, _ = z.shape
    n = config.samples_per_ramp
    k = support.shape[1]
    kk = np.arange(n)
    phi = np.exp(-2j * np.pi * np.outer(kk, kk) / n)[:, support] * carrier(config)[support][None]
    phi = np.transpose(phi, (1, 0, 2))
    ramps = m // n
    a_re = np.concatenate([phi.real, -phi.imag], axis=2)
    a_im = np.concatenate([phi.imag, phi.real], axis=2)
    a = np.tile(np.concatenate([a_re, a_im], axis=1), (1, ramps, 1))
    out = np.empty((b, k, 2), dtype=complex)
    for p in range(2):
        zp = z[:, :, p].reshape(b, ramps, n)
        xp = xi[:, :, p].reshape(b, ramps, n)
        s = np.sign(np.concatenate([zp.real, zp.imag], axis=2)).reshape(b, -1)
        o = np.concatenate([xp.real, xp.imag], axis=2).reshape(b, -1)
        th = np.concatenate([x0[:, :, p].real, x0[:, :, p].imag], axis=1)
        for t in ml_temperatures(m):
            sig = (t * delta)[:, None]
            u = s * (np.einsum("bmj,bj->bm", a, th) + o) / sig
            q = 0.5 * (1.0 - np.tanh(0.5 * u))
            grad = np.einsum("bmj,bm->bj", a, s * q / sig)
            w = q * (1.0 - q) / sig**2
            hess = np.matmul(np.transpose(a * w[:, :, None], (0, 2, 1)), a)
            hess += np.eye(2 * k)[None] * (1e-9 * np.trace(hess, axis1=1, axis2=2)[:, None, None] + 1e-300)
            step = np.linalg.solve(hess, grad[..., None])[..., 0]
            norm = np.linalg.norm(step, axis=1, keepdims=True)
            th = th + step * np.minimum(1.0, delta[:, None] / np.maximum(norm, 1e-300))
        out[:, :, p] = th[:, :k] + 1j * th[:, k:]
    return out


# -- the comparisons -----------------------------------------------------------------------
def frames(b, k, seed, config=RadarConfig(), bits=1, alpha=1.0, ramps=2):
    scene = SceneSpec(ranges="continuous", max_angle_deg=60.0, min_amplitude=0.1)
    _, _, r, a, x = draw_scenes(b, k, np.random.default_rng(seed), config, scene=scene)
    q = quantize_frames(simulate_frames(r, a, x, config, ramps=ramps), QuantizerConfig(bits=bits, alpha=alpha),
                        np.arange(b) + 100 * seed)
    return q.values(), q.dither(), q.delta


def close_per_frame(got, want, rtol):
    """Largest difference of each frame within ``rtol`` of the frame's largest value."""
    axes = tuple(range(1, want.ndim))
    err = np.abs(got - want).max(axis=axes) / np.abs(want).max(axis=axes)
    assert err.max() <= rtol, f"frames {np.flatnonzero(err > rtol).tolist()} differ by up to {err.max():.2e}"


@pytest.mark.parametrize("k, bits, config, ramps", [
    (2, 1, RadarConfig(), 2),
    (1, 1, RadarConfig(f0_hz=24.05e9), 2),  # a carrier term that is not 1
    (10, 1, RadarConfig(), 2),  # beyond the sparse forward: FFTs and a partition
    (2, 3, RadarConfig(), 2),
    (3, 1, RadarConfig(), 4),
])
def test_qiht_gives_the_reference_supports_and_amplitudes(k, bits, config, ramps):
    z, xi, delta = frames(24, k, seed=k + bits, config=config, bits=bits, ramps=ramps)
    x_ref, sup_ref, it_ref = reference_qiht(z, xi, delta, bits, config, k)
    x, sup, it = qiht(z, xi, delta, bits, config, k)
    assert it == it_ref
    np.testing.assert_array_equal(sup, sup_ref)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-12 * np.abs(x_ref).max())
    if ramps == 2:  # two ramps: the residual sums are exact, so is the whole iteration
        np.testing.assert_array_equal(x, x_ref)


@pytest.mark.parametrize("k, config, ramps", [(2, RadarConfig(), 2), (1, RadarConfig(f0_hz=24.05e9), 2),
                                              (3, RadarConfig(), 4)])
def test_likelihood_stage_gives_the_reference_amplitudes(k, config, ramps):
    z, xi, delta = frames(32, k, seed=10 + k, config=config, ramps=ramps)
    x, sup, _ = reference_qiht(z, xi, delta, 1, config, k)
    x0 = np.take_along_axis(x, sup[:, :, None], axis=1)
    close_per_frame(ml_refine(z, xi, delta, sup, x0, config), reference_ml_refine(z, xi, delta, sup, x0, config),
                    rtol=1e-9)


def test_decode_gives_the_reference_detections():
    cfg = RadarConfig()
    z, xi, delta = frames(40, 2, seed=21)
    x, sup, _ = reference_qiht(z, xi, delta, 1, cfg, 2)
    amp = reference_ml_refine(z, xi, delta, sup, np.take_along_axis(x, sup[:, :, None], axis=1), cfg)
    x = np.zeros_like(x)
    np.put_along_axis(x, sup[:, :, None], amp, axis=1)
    want = detections_from_support(x, sup, cfg, grid_statistic_db(back_project(z, cfg), sup))
    got = decode(z, xi, delta, 1, cfg, 2, DecoderConfig(algo="qiht"))
    for field in ("range_m", "bin", "statistic_db"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)
    for field in ("angle_deg", "x_m", "y_m", "amplitude"):
        np.testing.assert_allclose(getattr(got, field), getattr(want, field), rtol=1e-9, atol=1e-12, err_msg=field)
