"""Every target says how sure it is (issue 41, item 3): cml's sigma_range_m, sigma_angle_deg
and cov_range_angle (pipeline/dsp/uncertainty.py) are honest, the true position inside the
1-sigma ellipse in 39 +- 3 % of the targets and inside the 2-sigma one in 86 +- 3 %, and
they reach the targets JSON."""

import json

import numpy as np
import pytest

from experiments.coverage import CASES, EXPECTED, coverage
from pipeline.dsp.cml import cml
from pipeline.dsp.decode import Decoder, DecoderConfig
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.dsp.uncertainty import fitted_noise, model_jacobian, target_uncertainty
from pipeline.wire.frames import FrameHeaders
from pipeline.wire.messages import decode_targets, encode_targets_batch
from radar_driver.model import RadarConfig, simulate_frames

CFG = RadarConfig()


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"K{c.k}-{'1bit' if c.bits else 'unq'}-s{c.sigma:g}")
def test_the_true_position_lies_inside_the_ellipses_as_often_as_they_promise(case):
    """3000 targets a case, K = 1 and 2, 1-bit at the default alpha and unquantized, noise
    0.03-0.3 (the table of ``python -m experiments.coverage``, docs/science.md)."""
    one, two, n = coverage(case)
    assert n == 3000
    assert abs(one - 0.39) <= 0.03 and abs(two - 0.86) <= 0.03, (one, two)
    assert EXPECTED[0] == pytest.approx(0.393, abs=1e-3) and EXPECTED[1] == pytest.approx(0.865, abs=1e-3)


def frames(b: int, k: int, sigma: float, seed: int = 1):
    rng = np.random.default_rng(seed)
    r = 5.0 + 130.0 * rng.random((b, k)) + 10.0 * np.arange(k)
    g = simulate_frames(r, rng.uniform(-40, 40, (b, k)), np.exp(2j * np.pi * rng.random((b, k))), CFG)
    return g + sigma * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))


def test_the_noise_of_1bit_codes_is_corrected_for_what_the_fit_explains():
    """At low noise few codes lie near the threshold, and the fit of 2 targets (10
    parameters) explains part of their noise: the decoder's likeliest noise is 0.83 of the
    true one; corrected, within 10 % of it (and unchanged where the fit explains little)."""
    b, sigma = 300, 0.03
    q = quantize_frames(frames(b, 2, sigma), QuantizerConfig(alpha=0.45), np.arange(b))
    res = cml(q.codes, q.dither(), q.delta, 1, CFG, 2)
    s, ds = model_jacobian(res.range_m, res.amplitudes, CFG)
    margin = s[:, None, :] + q.dither().view(float).reshape(b, CFG.ramps_per_frame, -1)
    fixed = fitted_noise(res.sigma_eff, margin, ds, res.present)
    assert np.median(res.sigma_eff) / sigma < 0.9
    assert abs(np.median(fixed) / sigma - 1.0) < 0.1
    assert np.all(fixed >= res.sigma_eff)


def test_the_uncertainty_reaches_the_targets_json_from_cml_only():
    b = 4
    q = quantize_frames(frames(b, 1, 0.1), QuantizerConfig(alpha=0.45), np.arange(b))
    heads = FrameHeaders(["s0"] * b, list(range(b)), [0] * b, [0] * b)
    for algo, has in (("cml", True), ("pbp", False)):
        det = Decoder(DecoderConfig(algo=algo)).decode_batch(q, CFG, 1)
        payload = encode_targets_batch(heads, det, algo, 1, "quantized", 0)[0]
        target = decode_targets(payload, "radar/s0/targets").targets[0]
        for name in ("sigma_range_m", "sigma_angle_deg", "cov_range_angle"):
            assert (name in target) == has, (algo, name)
        if has:
            assert 0 < target["sigma_range_m"] < 0.05 and 0 < target["sigma_angle_deg"] < 3.0
            assert json.loads(payload)["targets"][0]["sigma_range_m"] == target["sigma_range_m"]


@pytest.mark.parametrize("bits", [1, None])
def test_frames_are_grouped_by_the_slots_they_use_with_the_same_figures(bits):
    """A count test's frames hold fewer targets than their slots: the uncertainty takes them
    in groups by the slots they use (each slot a block of the Fisher matrix); a frame's
    figures are those of its targets alone, wherever its slots end, and NaN past them."""
    from pipeline.dsp.uncertainty import target_uncertainty

    g = frames(24, 2, 0.05, seed=3)
    q = quantize_frames(g, QuantizerConfig(alpha=0.45), np.arange(24))
    z, xi, delta = (q.values(), q.dither(), q.delta) if bits == 1 else (g, None, None)
    res = cml(z, xi, delta, bits, CFG, 2)
    args = (CFG, res.sigma_eff, xi, delta, bits)
    alone = target_uncertainty(res.range_m, res.amplitudes, res.present, *args, phase_step_rad=res.phase_step_rad)
    pad = lambda x, v: np.concatenate([x, np.full(x.shape[:1] + (2,) + x.shape[2:], v, dtype=x.dtype)], axis=1)  # noqa: E731
    present = pad(res.present, False)
    present[::3, 1] = False  # every third frame: one target
    padded = target_uncertainty(pad(res.range_m, np.nan), pad(res.amplitudes, 0), present, *args,
                                phase_step_rad=pad(res.phase_step_rad, np.nan))
    one = target_uncertainty(res.range_m[::3, :1], res.amplitudes[::3, :1], res.present[::3, :1], CFG,
                             res.sigma_eff[::3], None if xi is None else xi[::3],
                             None if delta is None else np.asarray(delta)[::3], bits,
                             phase_step_rad=res.phase_step_rad[::3, :1])
    for name in ("sigma_range_m", "sigma_angle_deg", "cov_range_angle"):
        got, want = getattr(padded, name), getattr(alone, name).copy()
        want[::3, 1] = np.nan
        want[::3, :1] = getattr(one, name)
        assert np.isnan(got[:, 2:]).all()
        np.testing.assert_allclose(got[:, :2], want, rtol=1e-7, atol=1e-12, err_msg=name)


@pytest.mark.parametrize("moving", [False, True])
def test_1_bit_frames_with_no_sample_near_the_threshold_get_no_uncertainty_not_an_error(moving):
    """A fit whose noise is ~0 (cml told K = 32 of a two-target frame fits it so) leaves no
    1-bit sample within reach of the threshold: the codes hold no information on the targets,
    so their sigmas are NaN (not known), where a reshape of the empty Jacobian raised and a
    localizer lost the frame's targets."""
    b, k = 2, 2
    rng = np.random.default_rng(0)
    shape = (b, CFG.n_measurements, 2)
    dither = rng.uniform(-0.5, 0.5, shape) + 1j * rng.uniform(-0.5, 0.5, shape)
    for estimated in (True, False):
        u = target_uncertainty(np.array([[4.87, 9.23]] * b), np.full((b, k, 2), 1.0 + 0j), np.ones((b, k), bool), CFG,
                               np.full(b, 1e-9), dither, 0.3, 1, estimated=estimated,
                               phase_step_rad=np.zeros((b, k)) if moving else None)
        assert np.isnan(u.sigma_range_m).all() and np.isnan(u.sigma_angle_deg).all()
