import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from pipeline.errors import ParameterError
from pipeline.dsp.localize import (
    back_project_dense,
    back_project_ramps,
    joint_support,
    localize,
    localize_frame,
    pbp,
    position_error_m,
)
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from radar_driver.model import RadarConfig, simulate_frames


def _scene(rng, cfg, b, k):
    bins = np.stack([rng.choice(np.arange(1, 256), k, replace=False) for _ in range(b)])
    r = bins * cfg.range_resolution_m
    a = rng.uniform(-85, 85, (b, k))
    x = rng.uniform(0.2, 1, (b, k)) * np.exp(2j * np.pi * rng.random((b, k)))
    return bins, r, a, x


@pytest.mark.parametrize("k", [1, 2])
def test_full_resolution_full_ramp_recovery_is_exact(k, rng):
    cfg = RadarConfig(ramps_per_frame=1)
    bins, r, a, x = _scene(rng, cfg, 50, k)
    g = simulate_frames(r, a, x, cfg)
    xhat, support = pbp(g, cfg, k)
    assert_array_equal(np.sort(support, axis=1), np.sort(bins, axis=1))
    expected = np.zeros_like(xhat)
    for i in range(50):
        for j in range(k):
            expected[i, bins[i, j]] = [x[i, j], x[i, j] * np.exp(1j * np.pi * np.sin(np.deg2rad(a[i, j])))]
    assert_allclose(xhat, expected, atol=1e-9)
    det = localize(g, cfg, k)
    assert_allclose(position_error_m(r, a, det.range_m, det.angle_deg), 0.0, atol=1e-6)


def test_fft_and_dense_paths_agree(cfg, rng):
    _, r, a, x = _scene(rng, cfg, 40, 2)
    g = simulate_frames(r, a, x, cfg)
    z = quantize_frames(g, QuantizerConfig(alpha=1.0, dither_seed=1), np.arange(40)).values()
    for data in (g, z):
        fast = back_project_ramps(data, cfg)
        dense = back_project_dense(data, cfg)
        assert np.abs(fast - dense).max() <= 1e-5 * np.abs(dense).max()
    # also with a carrier term that is not 1 (f0 / B not an integer)
    odd = RadarConfig(f0_hz=24.1e9, ramps_per_frame=3)
    g = simulate_frames(r, a, x, odd)
    assert np.abs(back_project_ramps(g, odd) - back_project_dense(g, odd)).max() <= 1e-5 * np.abs(g).max()


def test_dense_path_with_per_frame_subsets(cfg, rng):
    _, r, a, x = _scene(rng, cfg, 6, 1)
    idx = np.sort(np.argsort(rng.random((6, 256)), axis=1)[:, :16], axis=1)
    g = simulate_frames(r, a, x, cfg, indices=idx)
    det = localize(g, cfg, 1, indices=idx)
    assert_allclose(position_error_m(r, a, det.range_m, det.angle_deg), 0.0, atol=1e-6)


@pytest.mark.parametrize("f0_hz", [24e9, 24.1e9], ids=["carrier-1", "carrier-not-1"])
def test_per_frame_subsets_back_project_as_the_explicit_matrix(rng, f0_hz):
    """Per-frame subsets (B, M) go through one inverse FFT of the samples put at their
    frequencies: the explicit Phi^H Z / M of the sensing matrix, to its rounding (the dense
    phases are ~1e5 rad, 1e-11 relative), a frequency twice in a frame summed; indices out of
    [0, N) and a shape that does not match are refused as before."""
    from radar_driver.errors import InputError
    from radar_driver.model import sensing_matrix

    cfg = RadarConfig(f0_hz=f0_hz)
    for m in (16, 100, 600):  # 600 > N: frequencies taken twice
        k = rng.integers(0, cfg.samples_per_ramp, (7, m))
        z = rng.standard_normal((7, m, 2)) + 1j * rng.standard_normal((7, m, 2))
        want = np.einsum("bmn,bmp->bnp", np.conj(sensing_matrix(cfg, k)), z) / m
        assert np.abs(back_project_dense(z, cfg, k) - want).max() <= 1e-9 * np.abs(want).max()
    with pytest.raises(InputError, match=r"lie in \[0, 256\)"):
        back_project_dense(np.zeros((1, 2, 2), complex), cfg, np.array([[0, 256]]))
    with pytest.raises(ParameterError, match="does not match"):
        back_project_dense(np.zeros((2, 3, 2), complex), cfg, np.zeros((2, 4), dtype=int))
    with pytest.raises(ParameterError, match="no frequency"):
        back_project_dense(np.zeros((2, 0, 2), complex), cfg, np.zeros((2, 0), dtype=int))
    k = rng.integers(0, cfg.samples_per_ramp, (3, 16))
    z = rng.standard_normal((3, 16, 2)) + 1j * rng.standard_normal((3, 16, 2))
    for dtype in (np.uint8, np.uint64, np.int16):  # any integer indices, as the dense path took
        np.testing.assert_array_equal(back_project_dense(z, cfg, k.astype(dtype)), back_project_dense(z, cfg, k))


def test_plus_minus_30_degrees_come_back_with_their_sign(cfg):
    g = simulate_frames([[30.0, 90.0]], [[30.0, -30.0]], [[1.0, 0.8]], cfg)
    for z in (g, quantize_frames(g, QuantizerConfig(dither_seed=9), [0]).values()):
        targets = localize_frame(z[0], cfg, 2)
        by_range = {round(t["range_m"], 1): t for t in targets}
        assert by_range[30.0]["angle_deg"] == pytest.approx(30.0, abs=3.0)
        assert by_range[90.0]["angle_deg"] == pytest.approx(-30.0, abs=3.0)
        t = by_range[30.0]
        assert t["x_m"] == pytest.approx(30.0 * np.cos(np.deg2rad(t["angle_deg"])))
        assert t["y_m"] == pytest.approx(30.0 * np.sin(np.deg2rad(t["angle_deg"])))
        assert t["y_m"] > 0 > by_range[90.0]["y_m"]


def test_joint_support_uses_both_antennas():
    u = np.zeros((1, 8, 2), complex)
    u[0, 2] = [0.9, 0.0]  # joint norm 0.9
    u[0, 5] = [0.7, 0.7]  # joint norm 0.99: stronger jointly, weaker on antenna 1
    u[0, 6] = [0.0, 0.5]
    assert joint_support(u, 2).tolist() == [[5, 2]]


def test_position_error_takes_the_closest_estimate():
    err = position_error_m(np.array([[10.0, 20.0]]), np.array([[0.0, 90.0]]),
                           np.array([[20.0, 10.0]]), np.array([[90.0, 0.0]]))
    assert_allclose(err, [[0.0, 0.0]], atol=1e-12)


def test_bad_inputs(cfg):
    with pytest.raises(ParameterError, match="whole number of ramps"):
        back_project_ramps(np.zeros((1, 300, 2), complex), cfg)
    with pytest.raises(ParameterError, match="K=0"):
        joint_support(np.zeros((1, 256, 2)), 0)
    with pytest.raises(ParameterError, match="single frame"):
        localize_frame(np.zeros((1, 512, 2)), cfg, 1)
    with pytest.raises(ParameterError, match="does not match"):
        back_project_dense(np.zeros((1, 16, 2), complex), cfg, np.arange(20))
