"""The continuous-range maximum likelihood decoder (pipeline.dsp.cml)."""

import numpy as np
import pytest

from pipeline.dsp.cml import BLOCK_FRAMES, CmlOptions, CmlResult, cml, cml_detections, model_frames
from pipeline.errors import ParameterError
from pipeline.dsp.localize import Detections, localize, nearest_estimates, position_error_m
from pipeline.dsp.quantize import auto_delta, batch_unit_dither, dequantize, quantize
from radar_driver.model import (RadarConfig, angle_from_antennas_rad, antenna_phase_rad, polar_to_xy, simulate_frames,
                                velocity_from_phase_step)


def measure(r, a, x, cfg, rng, bits=1, alpha=1.0, noise=0.0):
    """Frames of the scenes (B, K): (Z, xi, delta). ``bits`` None: unquantized. delta is
    the smallest step that does not saturate, 2 max(|Re|, |Im|) / 2^(b-1)."""
    g = simulate_frames(np.asarray(r, float), np.asarray(a, float), np.asarray(x, complex), cfg)
    if noise:
        g = g + noise * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    if bits is None:
        return g, None, None
    delta = auto_delta(g) / 2 ** (bits - 1)
    xi = alpha * delta[:, None, None] * batch_unit_dither(g.shape, rng)
    return dequantize(quantize(g, delta, bits, xi), delta, bits), xi, delta


def random_scenes(b, k, rng, separation_m=1.5):
    """Ranges uniform in [3, 150] m at least ``separation_m`` apart, angles in +-60 deg,
    the strongest amplitude 1, the others U[0.1, 1], random phases."""
    r = rng.uniform(3, 150, (b, k))
    while k > 1 and (bad := (np.diff(np.sort(r, axis=1), axis=1) < separation_m).any(axis=1)).any():
        r[bad] = rng.uniform(3, 150, (bad.sum(), k))
    mag = np.ones((b, k))
    mag[:, 1:] = rng.uniform(0.1, 1, (b, k - 1))
    return r, rng.uniform(-60, 60, (b, k)), mag * np.exp(2j * np.pi * rng.random((b, k)))


def errors(r, a, result: CmlResult, cfg):
    det = result.detections(cfg)
    err, pos = nearest_estimates(r, a, det.range_m, det.angle_deg)
    return err, np.abs(np.abs(pos) - r)  # position error, range error (m)


def test_a_noiseless_target_between_two_bins_is_found_within_centimetres(cfg):
    rng = np.random.default_rng(1)
    b = 16
    r = np.full((b, 1), 31.13)  # 51.88 bins
    a = rng.uniform(-50, 50, (b, 1))
    x = np.exp(2j * np.pi * rng.random((b, 1)))
    z, xi, delta = measure(r, a, x, cfg, rng)
    res = cml(z, xi, delta, 1, cfg, 1)
    pos_err, range_err = errors(r, a, res, cfg)
    assert range_err.max() < 0.01
    assert np.median(pos_err) < 0.05  # the angle limits it: about 0.06 deg
    assert pos_err.max() < 0.3
    np.testing.assert_allclose(res.detections(cfg).amplitude, 1.0, atol=0.02)
    on_grid = position_error_m(r, a, *(lambda d: (d.range_m, d.angle_deg))(localize(z, cfg, 1)))
    assert np.median(on_grid) > 5 * np.median(pos_err)  # PBP is stuck on the grid


def test_a_weak_target_beside_a_strong_off_grid_one_is_found(cfg):
    rng = np.random.default_rng(2)
    b = 8
    r = np.tile([[40.5, 52.3]], (b, 1))  # the strong one half-way between two bins, 11.8 m apart
    a = np.tile([[25.0, -10.0]], (b, 1))
    x = np.exp(2j * np.pi * rng.random((b, 2))) * [1.0, 0.3]
    z, xi, delta = measure(r, a, x, cfg, rng)
    res = cml(z, xi, delta, 1, cfg, 2)
    pos_err, range_err = errors(r, a, res, cfg)
    assert range_err.max() < 0.05
    assert np.median(pos_err, axis=0).max() < 0.5
    assert pos_err.max() < 1.5
    np.testing.assert_allclose(res.range_m[:, 0], 40.5, atol=0.05)  # strongest first
    assert np.all(res.statistic_db[:, 0] > res.statistic_db[:, 1])
    assert np.all(res.statistic_db[:, 1] > 10)


def test_unquantized_frames_give_off_grid_targets_to_a_millimetre(cfg):
    rng = np.random.default_rng(3)
    r = np.array([[31.13, 77.77], [5.05, 140.31], [100.0, 101.9]])
    a = np.array([[10.0, -40.0], [55.0, 0.0], [-20.0, 30.0]])
    x = np.array([[1.0, 0.5j], [0.8, -0.3], [1.0, 0.9]])
    z, _, _ = measure(r, a, x, cfg, rng, bits=None)
    res = cml(z, None, None, None, cfg, 2)
    pos_err, range_err = errors(r, a, res, cfg)
    assert pos_err.max() < 1e-3
    assert range_err.max() < 1e-3
    np.testing.assert_allclose(model_frames(res.range_m, res.amplitudes, cfg, 2), z, atol=1e-6)
    assert res.sigma_eff.max() < 1e-6  # residual RMS


def test_three_bit_frames(cfg):
    rng = np.random.default_rng(4)
    r, a, x = random_scenes(64, 2, rng)
    z, xi, delta = measure(r, a, x, cfg, rng, bits=3)
    res = cml(z, xi, delta, 3, cfg, 2)
    pos_err, range_err = errors(r, a, res, cfg)
    assert np.median(range_err) < 0.01
    assert np.median(pos_err) < 0.1
    assert pos_err[:, 1].mean() < 0.5


def test_one_bit_dithered_monte_carlo_beats_pbp_by_far(cfg):
    rng = np.random.default_rng(5)
    r, a, x = random_scenes(128, 2, rng)
    z, xi, delta = measure(r, a, x, cfg, rng)
    err, _ = errors(r, a, cml(z, xi, delta, 1, cfg, 2), cfg)
    det = localize(z, cfg, 2)
    pbp = position_error_m(r, a, det.range_m, det.angle_deg)
    assert err[:, 1].mean() < 2.0 < pbp[:, 1].mean()  # weakest target
    assert np.median(err) < np.median(pbp) / 5


@pytest.mark.parametrize("k", [1, 2])
def test_noisy_frames_at_small_alpha_are_no_worse_than_pbp(cfg, k):
    rng = np.random.default_rng(6 + k)
    r, a, x = random_scenes(200, k, rng)
    z, xi, delta = measure(r, a, x, cfg, rng, alpha=0.1, noise=0.1)
    det = localize(z, cfg, k)
    pbp = np.median(position_error_m(r, a, det.range_m, det.angle_deg))
    for noise_sigma in (None, 0.1):
        err, _ = errors(r, a, cml(z, xi, delta, 1, cfg, k, noise_sigma=noise_sigma), cfg)
        assert np.median(err) <= pbp


def test_the_noise_is_estimated_when_not_given(cfg):
    rng = np.random.default_rng(9)
    r, a, x = random_scenes(64, 1, rng)
    z, xi, delta = measure(r, a, x, cfg, rng, noise=0.1)
    estimated = cml(z, xi, delta, 1, cfg, 1).sigma_eff
    assert 0.08 < np.median(estimated) < 0.12
    given = cml(z, xi, delta, 1, cfg, 1, noise_sigma=0.1).sigma_eff
    np.testing.assert_allclose(given, 0.1)
    clean, xi, delta = measure(r, a, x, cfg, rng)
    assert np.median(cml(clean, xi, delta, 1, cfg, 1).sigma_eff) < 0.01  # down to ~delta / M


def test_detections_follow_the_conventions(cfg):
    rng = np.random.default_rng(10)
    r = np.array([[20.0, 61.3]])
    a = np.array([[30.0, -45.0]])  # positive: antenna 2 leads
    x = np.array([[1.0, 0.4]])
    z, _, _ = measure(r, a, x, cfg, rng, bits=None)
    res = cml(z, None, None, None, cfg, 2)
    det = cml_detections(res, cfg)
    assert isinstance(det, Detections)
    np.testing.assert_allclose(det.angle_deg, a, atol=1e-6)
    np.testing.assert_allclose(det.x_m + 1j * det.y_m, r * np.exp(1j * np.deg2rad(a)), atol=1e-5)
    np.testing.assert_allclose(det.amplitude, np.abs(x), atol=1e-9)
    np.testing.assert_array_equal(det.bin, [[33, 102]])
    gain = np.exp(1j * antenna_phase_rad(np.deg2rad(a), cfg))
    np.testing.assert_allclose(res.amplitudes, np.stack([x, x * gain], axis=-1), atol=1e-8)
    assert det.frame(0)[0]["range_m"] == pytest.approx(20.0, abs=1e-6)


def reference_detections(result: CmlResult, config: RadarConfig) -> Detections:
    """cml_detections from the model's functions (:func:`angle_from_antennas_rad`,
    :func:`polar_to_xy`) and :meth:`Detections.masked`, as written before it was inlined."""
    a = result.amplitudes
    angle = angle_from_antennas_rad(a[..., 0], a[..., 1], config)
    x, y = polar_to_xy(result.range_m, angle)
    amp = np.sqrt((np.abs(a) ** 2).sum(axis=-1) / 2.0)
    r = result.range_m
    bins = np.rint(np.where(np.isnan(r), 0.0, r) / config.range_resolution_m).astype(np.int64) % \
        config.samples_per_ramp
    v = velocity_from_phase_step(result.phase_step_rad, config)
    v = np.minimum(v, 0.5 * config.velocity_ambiguity_mps * (1.0 - 1e-12))  # phi = -pi: in [-V/2, V/2)
    det = Detections(result.range_m, np.rad2deg(angle), x, y, amp, bins, result.statistic_db, None, radial_velocity_mps=v)
    return det if result.present.all() else det.masked(result.present)


@pytest.mark.parametrize("spacing_m", [None, 0.011])  # 0.011 m: beyond half a wavelength, the arcsin clipped
def test_detections_are_the_model_functions_to_the_bit(cfg, spacing_m):
    config = RadarConfig(antenna_spacing_m=spacing_m)
    rng = np.random.default_rng(12)
    b, k = 500, 3
    present = rng.random((b, k)) < 0.7
    present[: b // 2] = True  # frames with every target (one Detections) and without (masked)
    r = np.where(present, rng.uniform(0, config.max_range_m, (b, k)), np.nan)
    r[0, 0] = config.max_range_m - 1e-9  # the last bin wraps to 0
    amp = (rng.standard_normal((b, k, 2)) + 1j * rng.standard_normal((b, k, 2))) * 10.0 ** rng.uniform(-4, 2, (b, k, 1))
    amp[1, 0, 1] = -amp[1, 0, 0]  # a phase difference of pi
    amp = np.where(present[..., None], amp, 0.0)
    stat = np.where(present, rng.uniform(5, 60, (b, k)), np.nan)
    phi = np.where(present, rng.uniform(-np.pi, np.pi, (b, k)), np.nan)
    phi[2, 0] = -np.pi  # the end of the ambiguity interval: +V/2, kept below it
    phi[3] = np.nan  # the static model's frames
    for sl in (slice(0, 1), slice(0, b // 2), slice(b // 2, b // 2 + 1), slice(0, b)):
        res = CmlResult(r[sl], amp[sl], stat[sl], np.ones(sl.stop - sl.start), present[sl], phi[sl])
        got, want = cml_detections(res, config), reference_detections(res, config)
        for name in Detections.__dataclass_fields__:
            g, w = getattr(got, name), getattr(want, name)
            assert g.dtype == w.dtype and g.shape == w.shape, name
            np.testing.assert_array_equal(np.ascontiguousarray(g).view(np.uint8),
                                          np.ascontiguousarray(w).view(np.uint8), err_msg=name)


def test_frames_are_decoded_independently_of_the_batch(cfg):
    rng = np.random.default_rng(11)
    b = BLOCK_FRAMES + 6
    r, a, x = random_scenes(b, 2, rng)
    z, xi, delta = measure(r, a, x, cfg, rng)
    whole = cml(z, xi, delta, 1, cfg, 2)
    tail = cml(z[-6:], xi[-6:], delta[-6:], 1, cfg, 2)
    assert whole.range_m.shape == (b, 2) and whole.amplitudes.shape == (b, 2, 2) and whole.sigma_eff.shape == (b,)
    np.testing.assert_allclose(whole.range_m[-6:], tail.range_m, atol=1e-9)
    np.testing.assert_allclose(whole.amplitudes[-6:], tail.amplitudes, atol=1e-9)
    empty = cml(z[:0], xi[:0], delta[:0], 1, cfg, 2)
    assert empty.range_m.shape == (0, 2) and empty.amplitudes.shape == (0, 2, 2)


def test_other_radar_configurations():
    cfg = RadarConfig(f0_hz=24.05e9, samples_per_ramp=128, ramps_per_frame=4)  # a carrier term that is not 1
    rng = np.random.default_rng(12)
    r = np.array([[13.37, 50.11]])
    a = np.array([[-12.0, 33.0]])
    x = np.array([[1.0, 0.6j]])
    z, _, _ = measure(r, a, x, cfg, rng, bits=None)
    pos_err, _ = errors(r, a, cml(z, None, None, None, cfg, 2), cfg)
    assert pos_err.max() < 1e-3


@pytest.mark.parametrize("change, match", [
    (dict(z=np.zeros((2, 512))), r"shape \(B, M, 2\)"),
    (dict(z=np.zeros((2, 512, 3))), r"shape \(B, M, 2\)"),
    (dict(z=np.full((2, 300, 2), 0.5 + 0.5j), xi=np.zeros((2, 300, 2))), "whole number of ramps"),
    (dict(k=0), r"k=0 must be an integer in \[1, N/2 = 128\]"),
    (dict(k=1.5), "k=1.5"),
    (dict(k=True), "k=True"),
    (dict(k=200), "k=200"),
    (dict(xi=np.zeros((2, 256, 2))), "dither shape"),
    (dict(delta=-1.0), "delta must be a finite value > 0"),
    (dict(delta=np.ones(3)), r"delta must be .* \(2,\)"),
    (dict(delta=0.25), "not a 1-bit quantized frame"),
    (dict(delta=np.array([1.0, np.nan])), "delta must be a finite value > 0"),  # (B,) floats: the fast check
    (dict(delta=np.array([0.0, 1.0])), "delta must be a finite value > 0"),
    (dict(delta=np.array([1.0, np.inf])), "delta must be a finite value > 0"),
    (dict(noise_sigma=np.array([0.1, np.inf])), "noise_sigma must be a finite value >= 0"),
    (dict(noise_sigma=np.array([-0.1, 0.1])), "noise_sigma must be a finite value >= 0"),
    (dict(bits=0), "bits=0"),
    (dict(noise_sigma=-0.1), "noise_sigma"),
    (dict(oversample=0), "oversample=0"),
    (dict(iters=-1), "iters=-1"),
    (dict(oversample=1.5), "oversample=1.5"),
    (dict(iters=True), "iters=True"),
])
def test_bad_inputs_are_parameter_errors(cfg, change, match):
    args = dict(z=np.full((2, 512, 2), 0.5 - 0.5j), xi=np.zeros((2, 512, 2)), delta=1.0, bits=1, k=2,
                noise_sigma=None, oversample=8, iters=3)
    args.update(change)
    with pytest.raises(ParameterError, match=match):
        cml(args["z"], args["xi"], args["delta"], args["bits"], cfg, args["k"], noise_sigma=args["noise_sigma"],
            options=CmlOptions(oversample=args["oversample"], iters=args["iters"]))


def test_non_finite_frames_are_parameter_errors(cfg):
    z = np.full((1, 512, 2), 0.5 + 0.5j)
    z[0, 3, 1] = np.nan
    with pytest.raises(ParameterError, match="not finite"):
        cml(z, None, None, None, cfg, 1)
