"""Targets that move between the ramps of a frame (issue 40): the frames of a moving target
computed by hand, cml's model with a phase step between ramps (radial velocity) on them, the
blind speeds of the static model gone, and the velocity's ambiguity."""

import numpy as np
import pytest
from test_cml import measure

from pipeline.dsp.cml import CmlOptions, cml, model_frames
from pipeline.defaults import DEFAULT_ALPHA
from pipeline.dsp.localize import nearest_estimates
from radar_driver.model import (RadarConfig, phase_step_rad, simulate_frames, velocity_from_phase_step,
                                wrap_velocity)

CFG = RadarConfig()


def hand_frames(r0, angle_deg, x, v, cfg=CFG):
    """One frame (M, 2) of one target written out sample by sample: ramp q at ``t_q = (q -
    1/2) dt`` sees the target at ``r0 + v t_q``; sample m of it at ``f0 + B m / N`` is ``x
    exp(-i 4 pi f (r0 + v t_q) / c)`` on antenna 1 and that times ``exp(i pi sin(theta))``
    (half-wavelength spacing) on antenna 2."""
    n, dt, c = cfg.samples_per_ramp, cfg.ramp_interval_s, cfg.c_m_s
    out = np.empty((2 * n, 2), complex)
    for q in range(2):
        r = r0 + v * (q - 0.5) * dt
        for m in range(n):
            f = cfg.f0_hz + cfg.bandwidth_hz * m / n
            s = x * np.exp(-1j * 4 * np.pi * f * r / c)
            out[q * n + m] = s, s * np.exp(1j * np.pi * np.sin(np.deg2rad(angle_deg)))
    return out


def test_the_simulated_frames_of_a_moving_target_are_the_hand_computed_ones():
    for v in (0.0, 0.125, -1.3):
        want = hand_frames(40.3, 20.0, 0.7 - 0.2j, v)
        got = simulate_frames(np.array([[40.3]]), np.array([[20.0]]), np.array([[0.7 - 0.2j]]), CFG,
                              velocity_mps=np.array([[v]]))[0]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_the_phase_step_and_the_blind_speed():
    """At mid-sweep the phase turns by ``-4 pi f_c v dt / c`` from ramp to ramp: 0.125 m/s
    turns it by about pi (V / 2, V = 0.249 m/s), and the two ramps' sum, the static model's
    view, all but cancels."""
    n = CFG.samples_per_ramp
    assert CFG.velocity_ambiguity_mps == pytest.approx(3e8 / (2 * (24e9 + 250e6 * 255 / 512) * 0.025))
    frame = hand_frames(40.3, 20.0, 1.0, 0.125)
    step = np.angle(frame[n + n // 2 - 1, 0] * np.conj(frame[n // 2 - 1, 0]))  # sample N/2 - 1: close to f_c
    want = phase_step_rad(0.125, CFG)
    assert abs(np.angle(np.exp(1j * (step - want)))) < 0.02
    assert abs(np.angle(np.exp(1j * want))) > 0.99 * np.pi
    ramps = frame.reshape(2, n, 2)
    assert np.abs(ramps.sum(axis=0)).max() < 0.02 * np.abs(ramps).sum(axis=0).max()  # 0.0164 at f_c
    assert velocity_from_phase_step(want, CFG) == pytest.approx(0.125)
    assert wrap_velocity(0.125 + 3 * CFG.velocity_ambiguity_mps, CFG) == pytest.approx(0.125 - CFG.velocity_ambiguity_mps)


@pytest.mark.parametrize("bits", [None, 1, 3])
def test_cml_finds_a_target_at_a_blind_speed_and_its_velocity(bits):
    """Hand-computed frames of targets at the static model's blind speeds (and between):
    cml gives the range to 2 cm and the radial velocity modulo V to 2 mm/s; the static model
    (``motion=False``) loses the targets at 0.125 m/s (quantized: its range is noise's;
    unquantized it sees the 1.6 % of the target the two ramps' sum leaves)."""
    rng = np.random.default_rng(3)
    v = np.array([0.125, -0.125, 0.375, 1.125, 0.06, 0.0, 2.9, -0.7])
    r0 = rng.uniform(5, 140, v.size)
    ang = rng.uniform(-50, 50, v.size)
    x = np.exp(2j * np.pi * rng.random(v.size))
    g = np.stack([hand_frames(r, a, xx, vv) for r, a, xx, vv in zip(r0, ang, x, v)])
    g = g + 0.02 * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    if bits is None:
        z, xi, delta = g, None, None
    else:
        from pipeline.dsp.quantize import auto_delta, batch_unit_dither, dequantize, quantize
        delta = auto_delta(g) / 2 ** (bits - 1)
        xi = DEFAULT_ALPHA * delta[:, None, None] * batch_unit_dither(g.shape, rng)
        z = dequantize(quantize(g, delta, bits, xi), delta, bits)
    res = cml(z, xi, delta, bits, CFG, 1)
    det = res.detections(CFG)
    assert np.abs(det.range_m[:, 0] - r0).max() < 0.02
    dv = wrap_velocity(det.radial_velocity_mps[:, 0] - v, CFG)
    assert np.abs(dv).max() < 0.002
    static = cml(z, xi, delta, bits, CFG, 1, options=CmlOptions(motion=False))
    assert np.isnan(static.phase_step_rad).all() and np.isnan(static.detections(CFG).radial_velocity_mps).all()
    if bits is None:
        np.testing.assert_allclose(det.amplitude[:, 0], 1.0, atol=0.05)
        assert static.detections(CFG).amplitude[:2, 0].max() < 0.05
    else:
        assert np.abs(static.range_m[:2, 0] - r0[:2]).min() > 0.6  # blind: the static model's range is noise's


def test_the_model_frames_are_the_simulated_ones():
    """``model_frames`` with the phase steps is what the simulator makes of those targets, but
    for the range the target moves between the ramps (v dt, a few hundredths of a bin at
    walking speeds), which the model leaves out: at |v| <= 0.3 m/s below 0.05 of the
    amplitude (at 3 m/s, 7.5 cm between the ramps, 0.24)."""
    rng = np.random.default_rng(4)
    r, v = rng.uniform(5, 140, (4, 2)), rng.uniform(-0.3, 0.3, (4, 2))
    ang = rng.uniform(-50, 50, (4, 2))
    x = np.exp(2j * np.pi * rng.random((4, 2)))
    g = simulate_frames(r, ang, x, CFG, velocity_mps=v)
    res = cml(g, None, None, None, CFG, 2)
    got = model_frames(res.range_m, res.amplitudes, CFG, 2, res.phase_step_rad)
    assert np.abs(got - g).max() < 0.05


def test_one_static_and_one_moving_target_are_both_found():
    """K = 2 and K auto with one static target and one at a blind speed of the static model
    (the issue's figure: both in >= 95 % of the frames; 1 bit at the default alpha, sigma 0.1)."""
    rng = np.random.default_rng(5)
    b = 64
    r = np.stack([rng.uniform(3, 70, b), rng.uniform(80, 150, b)], axis=1)
    a = rng.uniform(-60, 60, (b, 2))
    x = np.exp(2j * np.pi * rng.random((b, 2)))
    v = np.stack([np.zeros(b), np.full(b, 0.125)], axis=1)
    g = simulate_frames(r, a, x, CFG, velocity_mps=v)
    g = g + 0.1 * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    from pipeline.dsp.quantize import auto_delta, batch_unit_dither, dequantize, quantize
    delta = auto_delta(g)
    xi = DEFAULT_ALPHA * delta[:, None, None] * batch_unit_dither(g.shape, rng)
    z = dequantize(quantize(g, delta, 1, xi), delta, 1)
    for kw in ({"k": 2}, {"k": 4, "pfa": 1e-3}):
        det = cml(z, xi, delta, 1, CFG, kw["k"], pfa=kw.get("pfa")).detections(CFG)
        found = np.abs(np.where(np.isnan(det.range_m), np.inf, det.range_m)[:, None, :] - r[:, :, None]).min(axis=2)
        assert (found <= 0.6).mean(axis=0).min() >= 0.95, kw
        err, _ = nearest_estimates(r, a, det.range_m, det.angle_deg)
        assert np.nanmedian(err) < 1.0


def test_the_targets_json_carries_the_radial_velocity():
    """cml's detections written as the localizer writes them carry ``radial_velocity_mps``
    (modulo V, in [-V/2, V/2)); a static decoder's (PBP, or ``motion=False``) none."""
    from pipeline.wire.messages import FrameHeaders, decode_targets, encode_targets_batch

    v = np.array([0.125, -0.03, 1.0])
    g = np.stack([hand_frames(20.0 + 30 * i, 10.0, 1.0, vv) for i, vv in enumerate(v)])
    heads = FrameHeaders(["s0"] * 3, [0, 1, 2], [0, 0, 0], [CFG.config_id()] * 3)
    for motion in (True, False):
        det = cml(g, None, None, None, CFG, 1, options=CmlOptions(motion=motion)).detections(CFG)
        for i, payload in enumerate(encode_targets_batch(heads, det, "cml", 1, "raw", 0)):
            target = decode_targets(payload).targets[0]
            if motion:
                assert -CFG.velocity_ambiguity_mps / 2 <= target["radial_velocity_mps"] < CFG.velocity_ambiguity_mps / 2
                assert abs(wrap_velocity(target["radial_velocity_mps"] - v[i], CFG)) < 1e-3
            else:
                assert "radial_velocity_mps" not in target


def test_a_count_test_with_the_phase_step_decodes_in_smaller_blocks_to_the_same_digits(monkeypatch):
    """The count test's back projections with two model ramps are twice the static model's, so
    such a batch goes in blocks of 32 frames (pipeline.dsp.cml.decoder.block_frames: at 64 the
    block's temporaries were mapped afresh at each call, 11 100 page faults a 256-frame call);
    the frames are decoded one by one alike, so the targets are the same to the last bit as in
    blocks of 64."""
    import pipeline.dsp.cml.decoder as decoder
    from pipeline.dsp.decode import Decoder, DecoderConfig
    from pipeline.dsp.quantize import QuantizerConfig, quantize_frames

    n = CFG.samples_per_ramp
    assert [decoder.block_frames(n, rm, s) for rm in (1, 2) for s in (1, 2)] == [64, 64, 64, 32]
    rng = np.random.default_rng(4)
    b = 80
    r, a = rng.uniform(3, 150, (b, 2)), rng.uniform(-60, 60, (b, 2))
    x = np.exp(2j * np.pi * rng.random((b, 2))) * rng.uniform(0.3, 1.0, (b, 2))
    frames = simulate_frames(r, a, x, CFG, velocity_mps=rng.uniform(0, 3, (b, 2)))
    q = quantize_frames(frames, QuantizerConfig(alpha=DEFAULT_ALPHA), np.arange(b))
    dec = Decoder(DecoderConfig(algo="cml", auto_k=True, uncertainty=False))
    blocks = dec.decode_batch(q, CFG, 4)
    monkeypatch.setattr(decoder, "block_frames", lambda *args: 64)
    whole = dec.decode_batch(q, CFG, 4)
    for field in ("range_m", "angle_deg", "present"):
        np.testing.assert_array_equal(getattr(blocks, field), getattr(whole, field))
    assert blocks.present.sum() >= 1.9 * b
