"""The noise estimate at the quantizer and ``--alpha auto`` (issue 24): the estimator on
simulated frames with targets off the grid (ideal sensor, real front end, a moving
target), the rule, the per-sensor tracker, and a real ``qradar quantize --alpha auto``."""

from __future__ import annotations

import json
import subprocess
import time

import numpy as np
import pytest
import zenoh

from pipeline.errors import ParameterError
from experiments.montecarlo import SceneSpec, draw_scenes
from pipeline.dsp.noise import (AUTO_ALPHA_BEST, AUTO_ALPHA_RHO, NOISE_SMOOTHING_FRAMES, NoiseTracker, auto_alpha,
                            estimate_noise_sigma)
from pipeline.dsp.quantize import QuantizerConfig, quantize, quantize_frames, unit_dither
from pipeline.wire import RawFrameMsg, decode_health, decode_quantized, encode_raw
from radar_driver.model import RadarConfig, simulate_frames
from radar_driver.scene import resolve_scene
from zenoh_helpers import QRADAR, Collector, run_until, wait_until

N = 256


def offgrid_frames(n_frames: int, k: int, sigma: float, ramps: int, seed: int, front_end=None) -> np.ndarray:
    """Continuous-range scenes (K targets, strongest amplitude 1) plus white noise of
    ``sigma`` per I and Q, optionally through a front end: (n_frames, ramps N, 2)."""
    cfg = RadarConfig()
    rng = np.random.default_rng(seed)
    _, _, r, a, x = draw_scenes(n_frames, k, rng, cfg, scene=SceneSpec(ranges="continuous", max_angle_deg=60))
    g = simulate_frames(r, a, x, cfg, ramps=ramps)
    if front_end is not None:
        g = front_end.apply(g.reshape(-1, N, 2), cfg).reshape(g.shape)
    return g + sigma * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))


@pytest.mark.parametrize("ramps", [1, 2])
@pytest.mark.parametrize("k", [1, 3])
@pytest.mark.parametrize("sigma", [0.003, 0.1, 0.3])
def test_the_estimate_recovers_the_noise_of_frames_with_targets_off_the_grid(ramps, k, sigma):
    """One frame: within 8 % of sigma in 9 frames of 10 (median within 3 %) over 300 frames of K targets up
    to 330 times the noise."""
    est = estimate_noise_sigma(offgrid_frames(300, k, sigma, ramps, seed=k), N) / sigma
    assert abs(np.median(est) - 1) < 0.03, np.median(est)
    assert np.percentile(np.abs(est - 1), 90) < 0.08, np.percentile(np.abs(est - 1), 90)


@pytest.mark.parametrize("ramps", [1, 2])
def test_the_estimate_is_not_fooled_by_the_front_end(ramps):
    """The chamber's front end (DC offset, leakage stronger than the targets, receiver
    imbalance, I/Q ghosts) adds no noise: the estimate stays within the same bounds."""
    fe = resolve_scene("chamber").front_end
    sigma = 0.02
    est = estimate_noise_sigma(offgrid_frames(300, 2, sigma, ramps, seed=7, front_end=fe), N) / sigma
    assert abs(np.median(est) - 1) < 0.03, np.median(est)
    assert np.percentile(np.abs(est - 1), 90) < 0.08


def test_the_estimate_of_a_moving_target_scene():
    """walker: a target moving 3.75 cm between ramps (its ramps differ: no cancellation)."""
    scene = resolve_scene("walker")
    rng = np.random.default_rng(3)
    frames = np.stack([scene.ramps(np.array([2 * i, 2 * i + 1]) / 40.0, rng).reshape(2 * N, 2) for i in range(100)])
    est = estimate_noise_sigma(frames, N) / scene.noise_std
    assert abs(np.median(est) - 1) < 0.03 and np.percentile(np.abs(est - 1), 90) < 0.08


def test_the_estimate_checks_its_input():
    with pytest.raises(ParameterError, match="whole ramps"):
        estimate_noise_sigma(np.zeros((1, 300, 2), complex), N)
    with pytest.raises(ParameterError, match=r"\(B, M, 2\)"):
        estimate_noise_sigma(np.zeros((300, 2), complex), N)
    assert np.array_equal(estimate_noise_sigma(np.zeros((2, 512, 2), complex), N), [0.0, 0.0])


def test_auto_alpha_follows_the_rule():
    rho = np.asarray(AUTO_ALPHA_RHO)
    np.testing.assert_allclose(auto_alpha(rho * 2.0, 2.0), AUTO_ALPHA_BEST)  # the table's points
    mid = (rho[:-1] + rho[1:]) / 2  # halfway: the mean of the neighbours (linear in rho)
    best = np.asarray(AUTO_ALPHA_BEST)
    np.testing.assert_allclose(auto_alpha(mid, 1.0), (best[:-1] + best[1:]) / 2)
    assert auto_alpha(0.0, 1.0) == best[0] and auto_alpha(10 * rho[-1], 1.0) == best[-1]  # flat beyond
    a = auto_alpha(np.linspace(0, 2 * rho[-1], 50), 1.0)
    assert np.all((a >= 0) & (a <= 1)) and np.all(np.diff(a) <= 1e-12)  # more noise, less dither
    with pytest.raises(ParameterError, match="noise_sigma"):
        auto_alpha(-0.1, 1.0)
    with pytest.raises(ParameterError, match="delta"):
        auto_alpha(0.1, 0.0)


def test_the_tracker_smooths_per_sensor_and_forgets():
    t = NoiseTracker(N)
    for i in range(3 * NOISE_SMOOTHING_FRAMES):
        frames = np.concatenate([offgrid_frames(1, 1, 0.05, 2, seed=i), offgrid_frames(1, 2, 0.2, 2, seed=1000 + i)])
        sigma = t.update(["a", "b"], frames)
    np.testing.assert_allclose(sigma, [0.05, 0.2], rtol=0.05)  # smoothed: far tighter than one frame
    assert t.health("a")["noise_frames"] == 3 * NOISE_SMOOTHING_FRAMES and "alpha" not in t.health("a")
    t.set_alpha(["a", "b"], np.array([0.3, 0.25]))
    assert t.health("b")["alpha"] == 0.25
    t.forget("a")
    assert len(t) == 1 and t.health("a") == {}
    with pytest.raises(ParameterError):
        NoiseTracker(N, smoothing_frames=0)


def test_quantize_frames_with_alpha_auto():
    frames = offgrid_frames(4, 1, 0.1, 2, seed=2)
    sigma = np.array([0.0, 0.01, 0.1, 0.3])
    q = quantize_frames(frames, QuantizerConfig(alpha="auto"), np.arange(4), noise_sigma=sigma)
    expect = auto_alpha(sigma, q.delta).astype(np.float32).astype(float)
    assert np.array_equal(q.alpha, expect) and q.alpha.shape == (4,)
    u = unit_dither(0, np.arange(4), 512)
    again = quantize(frames, q.delta, 1, (expect * q.delta)[:, None, None] * u)
    assert np.array_equal(again, q.codes)  # the dither of each frame's own alpha
    with pytest.raises(ParameterError, match="noise_sigma"):
        quantize_frames(frames, QuantizerConfig(alpha="auto"), np.arange(4))
    with pytest.raises(ParameterError, match="'auto' or a number"):
        QuantizerConfig(alpha="often")


def _spawn(args):
    return subprocess.Popen([*QRADAR, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def test_qradar_quantize_alpha_auto_publishes_the_noise_and_quantizes_with_its_alpha(free_port,
                                                                                       connect_when_ready):
    """A real ``qradar quantize --alpha auto`` fed frames of two sensors with different
    noise: each sensor's health carries its estimate (within 5 % after 40 frames) and the
    alpha of the rule; each quantized frame carries that alpha and its codes are the
    quantizer's with it."""
    ep = f"tcp/127.0.0.1:{free_port}"
    proc = _spawn(["quantize", "--listen", ep, "--alpha", "auto", "--duration", "60"])
    try:
        session = connect_when_ready(ep, timeout_s=30, mode="client")
        col = Collector(session, "radar/**")
        wait_until(lambda: any(r.ok is not None for r in session.liveliness().get("radar/alive/quantize/**",
                                                                                    timeout=1.0)),
                   30, "the quantize node alive")
        noise = {"quiet": 0.01, "noisy": 0.2}
        cid = RadarConfig().config_id()
        raws = {}
        pubs = {s: session.declare_publisher(f"radar/{s}/raw", congestion_control=zenoh.CongestionControl.BLOCK)
                for s in noise}
        for i in range(40):
            for s, sigma in noise.items():
                frame = offgrid_frames(1, 2, sigma, 2, seed=i + (0 if s == "quiet" else 500))[0].astype(np.complex64)
                raws[(s, i)] = frame
                pubs[s].put(encode_raw(RawFrameMsg(s, i, time.time_ns(), cid, frame)))
            time.sleep(0.01)
        wait_until(lambda: len(col.of("/quantized")) == 80, 30, "80 quantized frames")

        def last_health(s):
            hs = [decode_health(p) for p in col.of(f"{s}/health")]
            hs = [h for h in hs if h.node == "quantize" and h.extra.get("noise_frames") == 40]
            return hs[-1] if hs else None

        wait_until(lambda: all(last_health(s) for s in noise), 20, "health with 40 frames' noise")
        for s, sigma in noise.items():
            extra = last_health(s).extra
            assert abs(extra["noise_sigma"] / sigma - 1) < 0.05, extra
            msgs = sorted((decode_quantized(p) for p in col.of(f"{s}/quantized")), key=lambda m: m.seq)
            last = msgs[-1]
            assert extra["alpha"] == pytest.approx(last.alpha)
            assert last.alpha == pytest.approx(float(auto_alpha(extra["noise_sigma"], last.delta)), abs=2e-3)
            for m in msgs[::13]:
                u = unit_dither(m.dither_seed, m.seq, 512)
                again = quantize(raws[(s, m.seq)][None].astype(complex), m.delta, 1, m.alpha * m.delta * u)
                assert np.array_equal(again[0], m.codes)
        alphas = {s: decode_quantized(col.of(f"{s}/quantized")[-1]).alpha for s in noise}
        assert alphas["noisy"] < alphas["quiet"]  # more noise, less dither (the rule)
        session.close()
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])  # its summary lists the sensors' noise too
    assert set(summary["noise"]) == set(noise)
    assert all(abs(summary["noise"][s]["noise_sigma"] / sigma - 1) < 0.05 for s, sigma in noise.items())


@pytest.mark.parametrize("cmd", [["quantize"], ["run"], ["drive", "--quantize"], ["source", "--quantized"]])
def test_a_bad_alpha_is_one_line(cmd, cli):
    code, _, err = cli(*cmd, "--alpha", "1.5")
    assert code == 2
    assert "--alpha: alpha='1.5' must be 'auto' or a number in [0, 1]" in err.strip().splitlines()[-1]


def test_the_monte_carlo_auto_alpha_scheme():
    from experiments.montecarlo import MonteCarloConfig, Scheme, measure

    cfg = RadarConfig()
    s = Scheme.parse("dither_aauto_m512", cfg)
    assert s.adaptive and s.bits == 1
    with pytest.raises(ParameterError, match="whole ramps"):
        Scheme.parse("dither_aauto_m16", cfg)
    with pytest.raises(ParameterError, match="decoder_noise"):
        MonteCarloConfig(runs=1, decoder_noise="oracle")
    rng = np.random.default_rng(4)
    _, _, r, a, x = draw_scenes(64, 1, rng, cfg, scene=SceneSpec(ranges="continuous"))
    sigma = np.where(np.arange(64) < 32, 0.0, 0.3)  # (the Monte Carlo adds one sigma; here two halves)
    gamma = simulate_frames(r, a, x, cfg)
    noisy = gamma + sigma[:, None, None] * (rng.standard_normal(gamma.shape) + 1j * rng.standard_normal(gamma.shape))
    z, idx, xi, delta, est = measure(s, lambda _: noisy, 64, np.random.default_rng(1), cfg)
    alpha = auto_alpha(est, delta)
    assert np.all(alpha[:32] == 1.0) and np.all(alpha[32:] < 0.5)
    half = np.maximum(np.abs(xi.real), np.abs(xi.imag)).max(axis=(1, 2)) / delta
    assert np.all(half <= alpha / 2) and np.all(half > 0.9 * alpha / 2)  # each run's dither spans its alpha


def test_the_edge_quantizer_publishes_the_noise_and_forgets_an_expired_sensor(bus, zenoh_session):
    """drive --quantize's path in process: a source node quantizing with alpha auto puts the
    estimate in its sensor's health (the walker scene's noise_std, within 5 %), and a
    quantize node forgets a sensor's noise when the sensor expires."""
    from pipeline.nodes.stream import QuantizeNode, SourceNode
    from radar_driver.source import SimSourceConfig, SimulatedSource

    session = zenoh_session
    col = Collector(session, "radar/**")
    scene = resolve_scene("walker")
    src = SourceNode(bus, SimulatedSource(SimSourceConfig(scene, sensors=1, rate_hz=200, frames=60)),
                     session=session, quantizer=QuantizerConfig(alpha="auto"), health_period_s=0.2)
    def noise_known() -> bool:
        return len(col.of("/quantized")) >= 60 and any(
            h.node == "source" and h.extra.get("noise_frames", 0) >= 40 for h in map(decode_health, col.of("/health")))

    run_until([src], noise_known)
    hs = [decode_health(p) for p in col.of("/health")]
    hs = [h for h in hs if h.node == "source" and h.extra.get("noise_frames", 0) >= 40]
    assert hs, "no health with the noise estimate"
    extra = hs[-1].extra
    assert abs(extra["noise_sigma"] / scene.noise_std - 1) < 0.05 and 0 < extra["alpha"] <= 1, extra
    qs = [decode_quantized(p) for p in col.of("/quantized")]
    assert len(qs) == 60 and qs[-1].alpha == pytest.approx(extra["alpha"], abs=0.02)

    q = QuantizeNode(bus, QuantizerConfig(alpha="auto"), session=session, health_period_s=0.1,
                     sensor_expiry_s=0.3).start()
    try:
        frame = offgrid_frames(1, 1, 0.05, 2, seed=1)[0].astype(np.complex64)
        session.put("radar/gone/raw", encode_raw(RawFrameMsg("gone", 0, time.time_ns(), RadarConfig().config_id(),
                                                             frame)))
        wait_until(lambda: len(q.noise) == 1, 10, "the sensor's noise tracked")
        wait_until(lambda: len(q.noise) == 0 and q.sensors_expired == 1, 10, "the expired sensor forgotten")
    finally:
        q.stop()
