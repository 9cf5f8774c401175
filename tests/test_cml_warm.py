"""cml's warm start (init_range_m): the same accuracy as a full search on the moving
``walker`` scene and on a Monte Carlo batch, and targets that appear, vanish or cross
found or dropped within a frame or two."""

import numpy as np
import pytest
from test_cml import measure, random_scenes

from pipeline.dsp.cml import CmlResult, cml
from pipeline.errors import ParameterError
from pipeline.dsp.localize import nearest_estimates
from radar_driver.scene import resolve_scene

PFA = 1e-3


def track(z, xi, delta, cfg, k, **kw):
    """Frames decoded one at a time, each from the last one's targets (a sensor's stream)."""
    out, prev = [], np.full((1, k), np.nan)
    for i in range(z.shape[0]):
        res = cml(z[i:i + 1], xi[i:i + 1], delta[i:i + 1], 1, cfg, k, init_range_m=prev, **kw)
        prev = np.where(res.present, res.range_m, np.nan)
        out.append(res)
    return CmlResult(*(np.concatenate([getattr(o, f) for o in out]) for f in CmlResult.__dataclass_fields__))


def position_errors(r, a, res, cfg):
    det = res.detections(cfg)
    return nearest_estimates(r, a, det.range_m, det.angle_deg)[0]


def test_warm_is_as_accurate_as_cold_on_the_walker(cfg):
    scene = resolve_scene("walker")
    rng = np.random.default_rng(0)
    arrays = [scene.arrays(i / 20.0) for i in range(40)]  # 2 s at 20 Hz: the walker moves 3 m
    r, a, x = (np.concatenate([t[j] for t in arrays]) for j in range(3))
    z, xi, delta = measure(r, a, x, cfg, rng, noise=scene.noise_std)
    cold = position_errors(r, a, cml(z, xi, delta, 1, cfg, 2), cfg)
    warm = position_errors(r, a, track(z, xi, delta, cfg, 2), cfg)
    assert np.all(warm.mean(axis=0) <= cold.mean(axis=0) * 1.05 + 0.005)
    assert np.all(np.median(warm, axis=0) <= np.median(cold, axis=0) * 1.05 + 0.005)


def test_warm_is_as_accurate_as_cold_on_a_monte_carlo_batch(cfg):
    rng = np.random.default_rng(1)
    r, a, x = random_scenes(64, 2, rng)
    z, xi, delta = measure(r, a, x, cfg, rng)
    cold = position_errors(r, a, cml(z, xi, delta, 1, cfg, 2), cfg)
    moved = r + rng.uniform(-0.1, 0.1, r.shape)  # the last frame's estimates of targets that moved since
    warm = position_errors(r, a, cml(z, xi, delta, 1, cfg, 2, init_range_m=moved), cfg)
    assert np.median(warm) <= np.median(cold) * 1.05 + 0.005
    assert warm[:, 1].mean() <= cold[:, 1].mean() * 1.05 + 0.01  # weakest target


@pytest.mark.parametrize("pfa", [None, PFA])
def test_a_block_of_warm_or_of_cold_frames_is_decoded_as_in_a_mixed_batch(cfg, pfa):
    """A call whose frames are all warm (or all without a start) takes a shortcut (no copies,
    no re-stacking): each frame's result is the same to the bit as in a batch that mixes
    warm and cold frames, and as a frame decoded without a start."""
    rng = np.random.default_rng(3)
    r, a, x = random_scenes(12, 2, rng)
    z, xi, delta = measure(r, a, x, cfg, rng, noise=0.01)
    k = 2 if pfa is None else 3
    init = np.concatenate([r + rng.uniform(-0.05, 0.05, r.shape), np.full((12, k - 2), np.nan)], axis=1)
    init[0, 1] = init[1, 0] = np.nan  # warm frames with one start
    mixed_init = init.copy()
    mixed_init[6:] = np.nan  # frames 6.. from scratch
    mixed = cml(z, xi, delta, 1, cfg, k, pfa=pfa, init_range_m=mixed_init)
    warm = cml(z[:6], xi[:6], delta[:6], 1, cfg, k, pfa=pfa, init_range_m=init[:6])
    cold = cml(z[6:], xi[6:], delta[6:], 1, cfg, k, pfa=pfa, init_range_m=mixed_init[6:])
    scratch = cml(z[6:], xi[6:], delta[6:], 1, cfg, k, pfa=pfa)
    for name in CmlResult.__dataclass_fields__:
        both = np.concatenate([getattr(warm, name), getattr(cold, name)])
        np.testing.assert_array_equal(both, getattr(mixed, name), err_msg=name)
        np.testing.assert_array_equal(getattr(cold, name), getattr(scratch, name), err_msg=name)


def stream(r, x, cfg, rng, angles=(20.0, -30.0)):
    """1-bit frames of targets at ranges r (T, 2) and amplitudes x (T, 2) (0: absent)."""
    a = np.tile(angles, (r.shape[0], 1))
    return (r, a) + measure(r, a, x, cfg, rng, noise=0.01)


def counts(res):
    return res.present.sum(axis=1)


def test_a_target_that_appears_is_found_within_two_frames(cfg):
    rng = np.random.default_rng(2)
    t = 8
    r = np.tile([40.3, 90.7], (t, 1))
    x = np.tile([1.0, 0.5], (t, 1)).astype(complex)
    x[:4, 1] = 0.0  # the second target appears at frame 4
    r, a, z, xi, delta = stream(r, x, cfg, rng)
    res = track(z, xi, delta, cfg, 3, pfa=PFA)
    assert np.all(counts(res)[:4] == 1)
    assert np.all(counts(res)[6:] == 2)
    np.testing.assert_allclose(np.sort(np.where(res.present, res.range_m, np.inf), axis=1)[6:, :2],
                               r[6:], atol=0.05)


def test_a_target_that_vanishes_is_dropped_within_two_frames(cfg):
    rng = np.random.default_rng(3)
    t = 8
    r = np.tile([40.3, 90.7], (t, 1))
    x = np.tile([1.0, 0.5], (t, 1)).astype(complex)
    x[4:, 0] = 0.0  # the strong one vanishes at frame 4
    r, a, z, xi, delta = stream(r, x, cfg, rng)
    res = track(z, xi, delta, cfg, 3, pfa=PFA)
    assert np.all(counts(res)[:4] == 2)
    assert np.all(counts(res)[6:] == 1)
    np.testing.assert_allclose(res.range_m[6:, 0], 90.7, atol=0.05)


def test_two_targets_that_cross_are_both_found(cfg):
    rng = np.random.default_rng(4)
    t = 24
    time_s = np.arange(t) / 20.0
    r = np.stack([50.0 + 20.0 * time_s, 61.0 - 20.0 * time_s], axis=1)  # 1 m a frame each, cross at 0.275 s
    x = np.tile([1.0, 0.6], (t, 1)).astype(complex)
    r, a, z, xi, delta = stream(r, x, cfg, rng)
    cold = range_errors(r, cml(z, xi, delta, 1, cfg, 2))
    warm = range_errors(r, track(z, xi, delta, cfg, 2))
    apart = np.abs(r[:, 0] - r[:, 1]) > 2.0  # beyond the crossing (within ~2 bins the two tones merge)
    assert np.all(warm[apart] < 0.1)
    assert np.median(warm[apart]) <= np.median(cold[apart]) * 1.05 + 0.005


def range_errors(r, res):
    """|r - nearest estimated range| (T, K), m."""
    est = np.where(res.present, res.range_m, np.inf)
    return np.abs(r[:, :, None] - est[:, None, :]).min(axis=2)


def test_bad_initial_ranges_are_parameter_errors(cfg):
    rng = np.random.default_rng(5)
    r, a, x = random_scenes(2, 1, rng)
    z, xi, delta = measure(r, a, x, cfg, rng)
    for bad, match in ((np.zeros((3, 1)), "shape"), (np.zeros((2, 2)), "shape"), (np.full((2, 1), -1.0), "NaN or in")):
        with pytest.raises(ParameterError, match=match):
            cml(z, xi, delta, 1, cfg, 1, init_range_m=bad)


def test_the_localizer_keeps_each_sensors_last_targets_until_it_expires(bus, zenoh_session):
    """Real nodes: two simulated sensors -> quantize -> cml localizer with warm start; the
    node holds one entry per live sensor (at most K ranges) and drops it on expiry."""
    from radar_driver.scene import SimScene, SimTarget
    from radar_driver.source import SimSourceConfig, SimulatedSource
    from zenoh_helpers import Collector, wait_until

    from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode
    from pipeline.dsp.quantize import QuantizerConfig
    from pipeline.wire import decode_targets

    scene = SimScene((SimTarget(23.43, 12.0, 0.5), SimTarget(9.23, -20.0, 0.2)), noise_std=0.005, name="offgrid")
    col = Collector(zenoh_session, "radar/**")
    loc = LocalizeNode(bus, LocalizerConfig(k=2, algo="cml", full_search_every=5), session=zenoh_session,
                       sensor_expiry_s=1.0, health_period_s=0.2).start()
    q = QuantizeNode(bus, QuantizerConfig(alpha=1.0, dither_seed=3), session=zenoh_session).start()
    src = SourceNode(bus, SimulatedSource(SimSourceConfig(scene, rate_hz=50, id_prefix="w", sensors=2, frames=15)),
                     session=zenoh_session).start()
    try:
        wait_until(lambda: all(len(col.of(f"w{i}/targets")) == 15 for i in range(2)), 20, "the targets")
        with loc._lock:
            assert set(loc._last) == {"w0", "w1"}
            for since, ranges in loc._last.values():
                assert 0 <= since < 5 and ranges.shape == (2,)
                np.testing.assert_allclose(np.sort(ranges), [9.23, 23.43], atol=0.1)
        for i in range(2):
            ranges = np.array([sorted(t["range_m"] for t in decode_targets(p).targets) for p in col.of(f"w{i}/targets")])
            assert np.abs(ranges - [9.23, 23.43]).max() < 0.1  # warm frames as good as the full searches
        wait_until(lambda: not loc._last, 10, "the sensors to expire")
    finally:
        for node in (src, q, loc):
            node.stop()
