"""PBP's count test on residuals (pipeline.dsp.residual): the tone model of the targets found
removes an off-grid target's sidelobes and a 1-bit quantizer's harmonics of it, leaves a
target that one of those harmonics aliases onto, and the first test is PBP's own."""

import numpy as np
import pytest

from radar_driver.model import RadarConfig
from pipeline.dsp.localize import cfar_threshold, fold_ramps, gated_energy, grid_statistic_db, joint_energy, \
    joint_support, back_project
from pipeline.dsp.residual import DYNAMIC_RANGE_DB, dirichlet, fit_residual, fitted_inside, kept_tones, merged_near, \
    product_floor_db, refine_bins, refine_jointly, residual_support, tone_combinations, tones

N = 256


def tone(nu: float, amp=(1.0, 0.8j)) -> np.ndarray:
    """One frame (1, N, 2): a tone at continuous bin ``nu`` on both antennas."""
    return tones(np.array([[nu]]), N)[..., 0][..., None] * np.asarray(amp)[None, None, :]


def one_bit(y: np.ndarray) -> np.ndarray:
    return np.sign(y.real) + 1j * np.sign(y.imag)


def spectrum(y: np.ndarray) -> np.ndarray:
    """The joint energy of each bin of ``y`` (1, N, 2): (N,)."""
    return np.square(np.abs(np.fft.ifft(y, axis=1))).sum(axis=-1)[0]


def away(e: np.ndarray, nu: float) -> np.ndarray:
    """The bins of ``e`` farther than 1.5 bins from ``nu``."""
    return e[np.abs((np.arange(N) - nu + N / 2) % N - N / 2) > 1.5]


def test_the_gram_in_closed_form_is_the_tones_inner_products():
    f = np.random.default_rng(0).random((3, 6)) * 400
    a = tones(f, N)
    assert np.allclose(np.conj(a).transpose(0, 2, 1) @ a, dirichlet(f[:, :, None] - f[:, None, :], N), atol=1e-9)


def test_the_quantizer_tones_follow_its_symmetry():
    one = tone_combinations(1)[:, 0]
    assert one[0] == 1 and set(one) == {1, -3, 5, -7, 9, -11, 13, -15}  # sum = 1 (mod 4), odd orders
    two = tone_combinations(2)
    assert (two[:2] == np.eye(2)).all() and all(c.sum() % 4 == 1 for c in two)
    assert {tuple(c) for c in two} >= {(2, -1), (-1, 2), (-2, -1), (-1, -2)}


def test_an_off_grid_tone_and_its_one_bit_harmonics_are_removed():
    nu = 71.37
    y = tone(nu)
    est = refine_bins(y, np.array([71]))
    assert abs(est[0] - nu) < 0.002
    e, r = spectrum(y), spectrum(fit_residual(y, est[:, None]))
    assert away(e, nu).max() > 1e-2 * e.max() and away(r, nu).max() < 1e-5 * e.max()  # sidelobes -15 dB -> < -50 dB
    q = one_bit(y + 0.3 * np.random.default_rng(1).standard_normal((1, N, 2)))  # noise as a dither (alpha 0: docs)
    est = refine_bins(q, np.array([71]))
    e, r = spectrum(q), spectrum(fit_residual(q, est[:, None]))
    assert abs(est[0] - nu) < 0.01 and away(e, nu).max() > 10 * np.median(e)  # the -3rd harmonic stands out
    assert away(r, nu).max() < 10 ** 0.9 * r.mean()  # under a CFAR threshold at pfa 1e-3 (8.9 dB)


def test_a_target_where_a_harmonic_aliases_is_kept():
    """-11 x 217.9 = 163.1 (mod 256): the strong target's 11th harmonic falls on a real target
    at 163.1, which the fit of the first (bounded to 1/11 of it) leaves."""
    y = one_bit(tone(217.9) + tone(163.1, (0.9, 0.9)))
    est = refine_bins(y, np.array([218]))
    res = spectrum(fit_residual(y, est[:, None]))
    assert res.argmax() in (163, 164) and 10 * np.log10(res.max() / np.median(res)) > 15


def test_the_first_statistic_is_pbps_and_a_noise_frame_stops_at_once():
    cfg = RadarConfig()
    rng = np.random.default_rng(2)
    z = one_bit(rng.standard_normal((4, cfg.n_measurements, 2)) + 1j * rng.standard_normal((4, cfg.n_measurements, 2)))
    u = back_project(z, cfg)
    pick, stat, cells = gated_energy(joint_energy(u), None, 3)
    support, statistic = residual_support(fold_ramps(z, cfg), joint_energy(u), pick, np.ones(N, bool), 3,
                                          cfar_threshold(1e-3, cells))
    first = grid_statistic_db(u, joint_support(u, 1, pick), stat, cells)
    assert support[:, 0] == pytest.approx(joint_support(u, 1)[:, 0])
    assert statistic[:, 0] == pytest.approx(first[:, 0], abs=1e-6)
    assert (statistic[:, 1:] == statistic[:, :1]).all()  # stopped at the first test: the later slots repeat it


def test_a_gate_too_narrow_for_more_targets_ends_the_test():
    """Three bins inside the gate: after the first target and its neighbours none is left, and
    no bin outside the gate is ever tested."""
    y = tone(100.3) + tone(140.0)
    pick = np.full((1, N), -1.0)
    pick[0, 99:102] = 1.0
    inside = pick[0] > 0
    support, statistic = residual_support(y, spectrum(y)[None], pick, inside, 3, cfar_threshold(1e-3, 3))
    assert support[0, 0] == 100 and (statistic[0, 1:] == -300.0).all()  # the later slots fail (masked)


def test_the_tone_fit_takes_one_bin_of_noise_a_tone_and_the_test_counts_them():
    """Two strong targets in white noise: the residual of their model's tones keeps (cells -
    fitted) / cells of the noise's mean energy over the gate's bins (the least-squares fit
    takes the noise along each tone it fits; the targets strong enough that no tone is held at
    its amplitude bound, where it takes less: the count is then conservative), so the count
    test's mean divides by the degrees of freedom left; a tone whose bin is beyond the gate
    takes none of the gate's."""
    rng = np.random.default_rng(3)
    b = 1000  # the ratio within 0.001 of its value on five seeds
    noise = rng.standard_normal((b, N, 2)) + 1j * rng.standard_normal((b, N, 2))
    nu = np.tile([[40.3, 97.8]], (b, 1))
    y = noise + 50.0 * (tone(40.3) + tone(97.8, (0.7j, -0.9)))
    inside = np.zeros(N, dtype=bool)
    inside[4:200] = True
    freq, keep = kept_tones(nu, None, N)
    bins = np.rint(freq[0, keep[0]]).astype(int) % N
    fitted = fitted_inside(nu, None, N, inside)
    assert (fitted == inside[bins].sum()).all() and 0 < fitted[0] < keep[0].sum()  # some tones fall beyond it
    kept = spectrum_mean(fit_residual(y, nu), inside) / spectrum_mean(noise, inside)
    assert kept == pytest.approx((inside.sum() - fitted[0]) / inside.sum(), abs=0.003)
    assert fitted_inside(np.zeros((3, 0)), None, N, inside).tolist() == [0, 0, 0]


def spectrum_mean(y: np.ndarray, inside: np.ndarray) -> float:
    """The mean joint energy over frames and the bins ``inside`` of ``y`` (B, N, 2)."""
    return float(np.square(np.abs(np.fft.ifft(y, axis=1))).sum(axis=-1)[:, inside].mean())


def test_the_floor_is_the_strongest_product_of_the_quantizer_the_model_leaves():
    """Without dither a hard limiter: its 17th harmonic (the first the model leaves) is 1/17
    of its target (24.6 dB under), the 5th-order intermodulation of two equal targets 1/5
    (14.0 dB); with dither the products fall, at alpha 1 (no clipping) to none: the 45 dB
    floor; not known (NaN): 45 dB. Per frame, never above 45 dB; between two of the dither
    scales it is computed at, the lower of their two floors."""
    single, mixed = product_floor_db(np.array([0.0, 0.45, 1.0, np.nan]))
    assert single[0] == pytest.approx(20 * np.log10(17), abs=0.2) and mixed[0] == pytest.approx(20 * np.log10(5), abs=0.2)
    assert 40.0 < single[1] <= DYNAMIC_RANGE_DB and 25.0 < mixed[1] < 35.0
    assert single[2] == mixed[2] == single[3] == mixed[3] == DYNAMIC_RANGE_DB
    grid = np.stack(product_floor_db(np.linspace(0.0, 1.0, 21)))  # (2, 21)
    assert np.all(grid <= DYNAMIC_RANGE_DB) and np.all(grid[:, :10] < DYNAMIC_RANGE_DB)
    between = np.stack(product_floor_db(np.linspace(0.025, 0.975, 20)))
    assert np.array_equal(between, np.minimum(grid[:, :-1], grid[:, 1:]))


def test_what_is_left_of_a_merged_tone_is_no_target():
    """Targets at bins 20.0 and 100.3: the quantizer's -3 nu_1 (196) and 2 nu_1 - nu_2 (195.7)
    are 0.3 bins apart, one to the fit (the first kept); the bins within a bin of the merged
    one are the model's residue, not targets (as those around the 5th harmonic 5 nu_1 = 100,
    merged into the second target, and one more pair's)."""
    near = merged_near(np.array([[20.0, 100.3]]), np.ones((1, 2), dtype=bool), N)[0]
    assert near[195] and near[196] and not near[194] and not near[197]
    assert near[99:102].all() and near.sum() == 8
    # a tone made of a target a frame lacks is no tone of its model
    assert not merged_near(np.array([[20.0, 100.3]]), np.array([[True, False]]), N)[0].any()


def test_bins_refined_together_are_the_tones_bins_where_each_alone_is_pulled_by_the_other():
    """Two strong tones 6.6 bins apart, noiseless: the first's bin refined alone (the power's
    peak) is off by the second's skirt, and its residual holds it; refined together (variable
    projection, amplitudes solved, all bins moved) both come back to 1e-6 bins from starts 0.3
    bins off, and the residual is gone. A target a frame lacks keeps its bin."""
    nu = np.array([[40.27, 46.87]])
    y = tone(40.27, (1.0, 0.7j)) + tone(46.87, (0.6, -0.5))
    alone = refine_bins(y, np.array([40]))
    assert abs(alone[0] - 40.27) > 1e-3  # pulled by the other's skirt
    got = refine_jointly(y, nu + [[0.3, -0.3]], np.ones((1, 2), dtype=bool))
    np.testing.assert_allclose(got, nu, atol=1e-6)
    assert np.abs(fit_residual(y, got)).max() < 1e-6 * np.abs(y).max()
    for scale in (1e-8, 1e6):  # frames in any unit
        np.testing.assert_allclose(refine_jointly(scale * y, nu + [[0.3, -0.3]], np.ones((1, 2), dtype=bool)), nu,
                                   atol=1e-6)
    off = refine_jointly(tone(40.27), np.array([[40.0, 100.0]]), np.array([[True, False]]))
    assert off[0, 1] == 100.0 and abs(off[0, 0] - 40.27) < 1e-6


def test_unquantized_frames_hold_the_targets_tones_alone():
    """The quantizer's tones (-3 nu, 5 nu, 2 nu_1 - nu_2, ...) are in the count test's model of
    quantized frames only (``quantized``; PBP's decode passes it: frames of 2-16 bits keep them,
    without which 3-bit frames beside two targets made 1 800 times the false-alarm rate): fitted
    to unquantized frames' noise they took a target's neighbour bins, and a false target stood
    1-3 bins beside a true one. The same 300 unquantized frames beside two targets (sigma 0.03):
    false targets with the quantizer's model, none without."""
    from experiments.false_alarms import AlarmCase, case_frames
    from pipeline.dsp.localize import localize

    assert tone_combinations(2, one_bit=False).tolist() == [[1.0, 0.0], [0.0, 1.0]]
    assert len(tone_combinations(2)) > 2
    nu, active, inside = np.array([[40.3, 80.6]]), np.ones((1, 2), dtype=bool), np.ones(N, dtype=bool)
    assert fitted_inside(nu, active, N, inside, one_bit=False)[0] == 2 < fitted_inside(nu, active, N, inside)[0]
    cfg = RadarConfig()
    r, _, g = case_frames(AlarmCase(2, 0.03, bits=None, frames=300, seed=20), cfg)

    def false_targets(quantized):
        det = localize(g, cfg, 4, pfa=1e-3, quantized=quantized)
        far = np.abs(det.range_m[:, :, None] - r[:, None, :]).min(axis=2) > cfg.range_resolution_m
        return int((det.present & far).sum())

    assert false_targets(True) >= 3 and false_targets(False) == 0


@pytest.mark.parametrize("bits, alpha", [(1, 0.45), (2, 0.0), (2, 0.45), (3, 1.0), (4, 0.3)])
def test_the_mean_code_is_the_dithered_quantizers_mean(bits, alpha):
    """residual.mean_code against the quantizer itself: the mean of b-bit codes (in steps from
    the middle) of values over the frame's peak at the step of delta auto, dithered uniformly
    over alpha steps (2 000 draws a value)."""
    from pipeline.dsp.quantize import auto_delta, dequantize, quantize
    from pipeline.dsp.residual import mean_code

    rng = np.random.default_rng(bits)
    x = np.linspace(-1.0, 1.0, 41)
    frames = np.repeat((x + 0j)[None, :, None], 2, axis=2).repeat(2000, axis=0)  # (2000, 41, 2), peak 1
    delta = auto_delta(frames, bits=bits)
    dither = alpha * delta[:, None, None] * (rng.random(frames.shape) - 0.5)
    codes = dequantize(quantize(frames, delta, bits, dither), delta, bits).real / delta[:, None, None]
    scale = 0.5 if bits == 1 else 1.0  # one bit: mean_code is in half steps (+-1 at the two levels)
    assert np.allclose(codes[:, :, 0].mean(axis=0) / scale, mean_code(x, alpha, bits), atol=0.04)
