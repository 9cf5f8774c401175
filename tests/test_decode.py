"""The dither-aware decoder (QIHT + likelihood on the support)."""

import numpy as np
import pytest

from pipeline.dsp.decode import DecoderConfig, DitherUnavailable, consistency, decode, forward_ramps, qiht
from pipeline.errors import ParameterError
from pipeline.dsp.localize import back_project_ramps, localize, position_error_m
from experiments.montecarlo import MonteCarloConfig, draw_scenes, run_montecarlo
from pipeline.dsp.quantize import QuantizerConfig, auto_delta, batch_unit_dither, dequantize, quantize, quantize_frames
from radar_driver.model import RadarConfig, sensing_matrix, simulate_frames

#: the decoder these tests are about (the default decoder is cml: pipeline.defaults)
QIHT = DecoderConfig(algo="qiht")


def dithered_batch(k, b=400, seed=0, ramps=2):
    cfg = RadarConfig()
    rng = np.random.default_rng(seed)
    _, _, r, a, x = draw_scenes(b, k, rng, cfg)
    g = simulate_frames(r, a, x, cfg, ramps=ramps)
    delta = auto_delta(g)
    xi = delta[:, None, None] * batch_unit_dither(g.shape, rng)
    z = dequantize(quantize(g, delta, 1, xi), delta, 1)
    return cfg, r, a, x, g, delta, xi, z


def test_forward_is_the_sensing_matrix_and_its_adjoint_is_the_back_projection(rng):
    cfg = RadarConfig(f0_hz=24.05e9)  # a carrier term that is not 1
    x = rng.standard_normal((3, 256, 2)) + 1j * rng.standard_normal((3, 256, 2))
    phi = sensing_matrix(cfg)
    np.testing.assert_allclose(forward_ramps(x, cfg, 2), np.einsum("mn,bnp->bmp", phi, x), atol=1e-9)
    y = rng.standard_normal((3, 512, 2)) + 1j * rng.standard_normal((3, 512, 2))
    lhs = np.vdot(forward_ramps(x, cfg, 2), y)  # <Phi x, y> = <x, Phi^* y>
    rhs = np.vdot(x, back_project_ramps(y, cfg) * 512)
    assert lhs == pytest.approx(rhs, rel=1e-9)


def test_estimate_is_consistent_with_the_codes():
    cfg, r, a, x, g, delta, xi, z = dithered_batch(2)
    x_qiht, support, iters = qiht(z, xi, delta, 1, cfg, 2, iters=20)
    x_pbp, _ = np.zeros_like(x_qiht), None
    u = back_project_ramps(z, cfg)
    from pipeline.dsp.localize import project_theta_k

    x_pbp, _ = project_theta_k(u, 2)
    c_pbp = consistency(x_pbp, z, xi, delta, 1, cfg)
    c_qiht = consistency(x_qiht, z, xi, delta, 1, cfg)
    assert np.median(c_qiht) > 0.99  # re-quantizing the estimate reproduces nearly every code
    assert np.mean(c_qiht == 1.0) > 0.5 > 0.05 > np.mean(c_pbp == 1.0)  # most frames: every code
    assert (1 - c_qiht).mean() < (1 - c_pbp).mean() / 5
    assert 1 <= iters <= 20  # the default cap is 10 iterations; 20 were asked for here


def test_beats_pbp_on_a_small_monte_carlo():
    for k, target in ((1, 0.15), (2, None)):
        cfg, r, a, x, g, delta, xi, z = dithered_batch(k, b=1500, seed=k)
        e_pbp = position_error_m(r, a, *_ra(localize(z, cfg, k)))
        e_new = position_error_m(r, a, *_ra(decode(z, xi, delta, 1, cfg, k, QIHT)))
        assert np.median(e_new) < np.median(e_pbp) / 5
        assert e_new[:, -1].mean() < e_pbp[:, -1].mean() / 2
        if target:
            assert np.median(e_new) < target


def _ra(det):
    return det.range_m, det.angle_deg


def test_error_falls_faster_than_pbp_with_m():
    med = {}
    for ramps in (2, 8):
        cfg, r, a, x, g, delta, xi, z = dithered_batch(1, b=800, seed=5, ramps=ramps)
        med[("pbp", ramps)] = np.median(position_error_m(r, a, *_ra(localize(z, cfg, 1))))
        med[("qiht", ramps)] = np.median(position_error_m(r, a, *_ra(decode(z, xi, delta, 1, cfg, 1, QIHT))))
    slope = {alg: np.log(med[(alg, 8)] / med[(alg, 2)]) / np.log(4) for alg in ("pbp", "qiht")}
    assert -0.75 < slope["pbp"] < -0.25  # about -1/2
    assert slope["qiht"] < -0.75  # about -1


def test_reproduces_the_quantizers_dither_from_the_seed():
    cfg = RadarConfig()
    g = simulate_frames([[30.0], [60.0]], [[10.0], [-30.0]], [[1.0], [0.7]], cfg)
    q = quantize_frames(g, QuantizerConfig(alpha=1.0, dither_seed=11), seq=[5, 6])
    xi = q.dither()  # regenerated from (seed, seq), delta and alpha
    np.testing.assert_array_equal(quantize(g, q.delta, 1, xi), q.codes)
    det = decode(q.values(), xi, q.delta, 1, cfg, 1, QIHT)
    assert np.all(position_error_m(np.array([[30.0], [60.0]]), np.array([[10.0], [-30.0]]),
                                   det.range_m, det.angle_deg) < 0.3)


def test_bad_inputs_give_clear_errors():
    cfg, r, a, x, g, delta, xi, z = dithered_batch(1, b=4)
    with pytest.raises(DitherUnavailable, match="needs the dither"):
        decode(z, None, delta, 1, cfg, 1, QIHT)
    assert decode(z, None, delta, 1, cfg, 1, DecoderConfig(algo="qiht", fallback_pbp=True)).range_m.shape == (4, 1)
    with pytest.raises(ParameterError, match="dither shape"):
        decode(z, xi[:, :256], delta, 1, cfg, 1, QIHT)
    with pytest.raises(ParameterError, match="delta must be"):
        decode(z, xi, delta[:2], 1, cfg, 1, QIHT)
    with pytest.raises(ParameterError, match="whole number of ramps"):
        decode(z[:, :300], xi[:, :300], delta, 1, cfg, 1, QIHT)
    with pytest.raises(ParameterError, match="algo='omp'"):
        DecoderConfig(algo="omp")
    with pytest.raises(ParameterError, match="nodither_m512.*--fallback-pbp"):
        MonteCarloConfig(algos=("pbp", "qiht"), schemes=("nodither_m512",))


def test_montecarlo_reports_qiht_beside_pbp():
    res = run_montecarlo(MonteCarloConfig(ks=(1,), runs=1500, schemes=("dither_m512",), algos=("pbp", "qiht")),
                         progress=False)
    k1 = res.summary["K1"]
    assert set(k1) == {"dither_m512", "dither_m512@qiht"}
    assert k1["dither_m512@qiht"]["median_m"] < k1["dither_m512"]["median_m"] / 5
    assert "K1_dither_m512@qiht_all" in res.maps


def test_cml_through_the_decode_entry_places_an_off_grid_target():
    cfg = RadarConfig()
    g = simulate_frames([[31.47]], [[17.0]], [[0.8]], cfg)  # between bins 52 (31.2 m) and 53 (31.8 m)
    q = quantize_frames(g, QuantizerConfig(alpha=1.0, dither_seed=4), seq=[0])
    det = decode(q.values(), q.dither(), q.delta, 1, cfg, 1, DecoderConfig(algo="cml"))
    assert abs(det.range_m[0, 0] - 31.47) < 0.05 and abs(det.angle_deg[0, 0] - 17.0) < 2.0
    grid = decode(q.values(), q.dither(), q.delta, 1, cfg, 1, DecoderConfig(algo="qiht"))
    assert abs(grid.range_m[0, 0] - 31.47) > 0.2  # a grid decoder cannot place it between bins
    full = decode(g, None, None, None, cfg, 1, DecoderConfig(algo="cml"))  # unquantized: least squares
    assert abs(full.range_m[0, 0] - 31.47) < 1e-3
    with pytest.raises(DitherUnavailable, match="subset"):
        decode(g[:, :16], None, None, None, cfg, 1, DecoderConfig(algo="cml"), indices=np.arange(16))


def test_montecarlo_decodes_the_32bit_reference_with_the_same_decoder():
    from experiments.montecarlo import SceneSpec

    res = run_montecarlo(MonteCarloConfig(ks=(1,), runs=400, schemes=("dither_m512", "32bit_m512"),
                                          algos=("pbp", "cml"), scene=SceneSpec(ranges="continuous", max_angle_deg=60)),
                         progress=False)
    k1 = res.summary["K1"]
    assert k1["32bit_m512@cml"]["median_m"] < 0.05 < k1["32bit_m512"]["median_m"]  # least squares vs the grid
    assert k1["dither_m512@cml"]["median_m"] < k1["dither_m512"]["median_m"] / 4
    with pytest.raises(ParameterError, match="32bit_m16.*subset"):
        MonteCarloConfig(algos=("cml",), schemes=("32bit_m16",))


def test_pbp_on_the_ramps_mean_of_the_codes_is_pbp_on_every_measurement():
    """decode_batch folds 1-bit codes over the ramps before PBP's back projection; the
    targets are those of PBP on every measurement."""
    from numpy.testing import assert_allclose

    from pipeline.dsp.decode import decode_batch
    from radar_driver.scene import resolve_scene
    scene = resolve_scene("chamber")
    rng = np.random.default_rng(4)
    g = np.stack([np.tile(scene.clean_ramp(0.0), (2, 1))] * 16)
    g = g + scene.noise_std * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    for bits in (1, 3):
        q = quantize_frames(g, QuantizerConfig(bits=bits, alpha=1.0, dither_seed=2), seq=np.arange(16))
        fast = decode_batch(q, scene.radar, 2, DecoderConfig(algo="pbp"))
        full = localize(q.values(), scene.radar, 2)
        assert np.array_equal(fast.bin, full.bin)
        for f in ("range_m", "angle_deg", "amplitude", "statistic_db"):
            assert_allclose(getattr(fast, f), getattr(full, f), rtol=1e-12, atol=1e-12)
