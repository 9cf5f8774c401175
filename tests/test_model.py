import numpy as np
import pytest
from numpy.testing import assert_allclose

from radar_driver import ConfigError, InputError, RadarConfig, RadarError, SimScene, SimTarget
from radar_driver.model import (
    add_noise,
    angle_from_antennas_rad,
    sensing_matrix,
    simulate_frames,
    snap_to_range_grid,
)


def test_paper_defaults(cfg):
    assert cfg.n_measurements == 512
    assert cfg.range_resolution_m == pytest.approx(0.6)
    assert cfg.max_range_m == pytest.approx(153.6)
    assert cfg.d_m == pytest.approx(3e8 / (2 * 24e9))
    f = cfg.frequencies_hz()
    assert f.shape == (512,)
    assert f[0] == 24e9 and f[256] == 24e9
    assert f[255] == pytest.approx(24e9 + 250e6 * 255 / 256)
    assert_allclose(cfg.range_grid_m()[:3], [0.0, 0.6, 1.2])


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        ({"f0_hz": -1.0}, "f0_hz"),
        ({"bandwidth_hz": 0.0}, "bandwidth_hz"),
        ({"samples_per_ramp": 0}, "samples_per_ramp"),
        ({"ramps_per_frame": 1.5}, "ramps_per_frame"),
        ({"antenna_spacing_m": float("nan")}, "antenna_spacing_m"),
        ({"bandwidth_hz": 30e9}, "B << f0"),
    ],
)
def test_config_rejects_bad_values(kwargs, fragment):
    with pytest.raises(ConfigError, match=fragment):
        RadarConfig(**kwargs)


def test_config_from_dict_names_unknown_keys():
    with pytest.raises(ConfigError, match="unknown keys \\['f1'\\]"):
        RadarConfig.from_dict({"f1": 3})
    assert RadarConfig.from_dict({"ramps_per_frame": 4}).n_measurements == 1024
    assert issubclass(ConfigError, RadarError) and issubclass(ConfigError, ValueError)


def test_single_on_grid_target_hand_computed_phases(cfg):
    # R = 10 bins = 6 m: 4 pi f0 R / c = 1920 pi, so the carrier term is exactly 1;
    # Gamma_m1 = exp(-i 2 pi k 10 / 256) with k = m mod 256, and at +30 deg antenna 2
    # leads by pi sin(30 deg) = pi / 2, i.e. Gamma_m2 = i Gamma_m1.
    g = simulate_frames([6.0], [30.0], [1.0], cfg)
    assert g.shape == (1, 512, 2)
    k = np.arange(512) % 256
    expected1 = np.exp(-2j * np.pi * k * 10 / 256)
    assert_allclose(g[0, :, 0], expected1, atol=1e-9)
    assert_allclose(g[0, :, 1], 1j * expected1, atol=1e-9)
    assert_allclose(g[0, [0, 1, 256], 0], [1.0, np.exp(-2j * np.pi * 10 / 256), 1.0], atol=1e-9)


def test_angle_sign_convention(cfg):
    g = simulate_frames([[30.0, 60.0]], [[30.0, -30.0]], [[1.0, 0.0]], cfg)
    # positive angle: antenna 2 leads antenna 1
    assert np.angle(g[0, 0, 1] * np.conj(g[0, 0, 0])) == pytest.approx(np.pi / 2)
    est = angle_from_antennas_rad(np.array(1.0), np.exp(-1j * np.pi / 2), cfg)
    assert np.rad2deg(est) == pytest.approx(-30.0)


def test_model_matches_sensing_matrix_and_batches(cfg, rng):
    b, k = 5, 3
    bins = rng.integers(1, 256, (b, k))
    r = bins * cfg.range_resolution_m
    a = rng.uniform(-80, 80, (b, k))
    x = rng.standard_normal((b, k)) + 1j * rng.standard_normal((b, k))
    g = simulate_frames(r, a, x, cfg)
    phi = sensing_matrix(cfg)
    for i in range(b):
        xv = np.zeros((256, 2), complex)
        for j in range(k):
            xv[bins[i, j], 0] += x[i, j]
            xv[bins[i, j], 1] += x[i, j] * np.exp(1j * np.pi * np.sin(np.deg2rad(a[i, j])))
        assert_allclose(g[i], phi @ xv, atol=1e-9)


def test_subset_and_off_grid(cfg, rng):
    idx = np.sort(rng.choice(256, 16, replace=False))
    g_full = simulate_frames([[10.3]], [[12.0]], [[1.0]], cfg)
    g_sub = simulate_frames([[10.3]], [[12.0]], [[1.0]], cfg, indices=idx)
    assert g_sub.shape == (1, 16, 2)
    assert_allclose(g_sub[0], g_full[0, idx], atol=1e-9)
    per_frame = np.stack([idx, idx])
    assert simulate_frames([[10.3], [20.0]], [[1.0], [2.0]], [[1.0], [1.0]], cfg, indices=per_frame).shape == (2, 16, 2)
    assert_allclose(snap_to_range_grid(np.array([10.3, 0.29, 1000.0]), cfg), [10.2, 0.0, 255 * 0.6])


def test_scene_and_noise(cfg, rng):
    scene = SimScene((SimTarget(4.8, 20.0, 0.15), SimTarget(9.1, -10.0, 1.0)), radar=cfg)
    g = simulate_frames(*scene.arrays(), cfg)
    assert g.shape == (1, 512, 2)
    assert_allclose(g[0], np.tile(scene.clean_ramp(0.0), (2, 1)))  # the scene's ramps are the model's
    noisy = add_noise(g, 10.0, rng)
    noise_power = np.mean(np.abs(noisy - g) ** 2)
    assert noise_power == pytest.approx(np.mean(np.abs(g) ** 2) / 10.0, rel=0.1)
    with pytest.raises(ConfigError, match="rng"):
        SimScene(scene.targets, noise_std=0.1).ramp(0.0)
    with pytest.raises(ConfigError, match="angle_deg"):
        SimTarget(3.0, 95.0, 1.0)
    with pytest.raises(InputError, match="shape"):
        add_noise(np.zeros((4, 2)), 10.0, rng)


def test_bad_scene_arrays(cfg):
    with pytest.raises(InputError, match="share one"):
        simulate_frames([[1.0, 2.0]], [[0.0]], [[1.0, 1.0]], cfg)
    with pytest.raises(InputError, match="range_m"):
        simulate_frames([[-1.0]], [[0.0]], [[1.0]], cfg)
    with pytest.raises(InputError, match="frequency indices"):
        simulate_frames([[1.0]], [[0.0]], [[1.0]], cfg, indices=np.array([0, 256]))


def test_a_scene_gives_its_arrays_at_many_times_in_one_batch():
    """``SimScene.arrays`` of a recording's ``t_s`` (T,): one batch (T, K), each row the
    scene at that time (a (T,) array raised numpy's TypeError); anything else one line."""
    from radar_driver.errors import ConfigError
    from radar_driver.scene import resolve_scene

    walker, t = resolve_scene("walker"), np.array([0.0, 0.5, 2.0])
    batch = walker.arrays(t)
    rows = [walker.arrays(float(x)) for x in t]
    for i, part in enumerate(batch):
        assert part.shape == (3, len(walker.targets))
        assert np.array_equal(part, np.concatenate([r[i] for r in rows]))
    with pytest.raises(ConfigError, match=r"t_s must be a number or \(T,\) finite seconds, got shape \(2, 2\)"):
        walker.arrays(np.zeros((2, 2)))
