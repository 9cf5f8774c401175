"""The tracker (pipeline/dsp/track.py) and the integration of static tracks
(pipeline/dsp/integrate.py): the math on known inputs, then real scenes quantized to 1 bit and
decoded by the default decoder, frame by frame, as the localizer node does."""

import json

import time

import numpy as np
import pytest
from numpy.testing import assert_allclose

from pipeline.dsp.decode import DecoderConfig, decode_batch
from pipeline.errors import ParameterError, WireError
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.integrate import concat_frames, integrate, stack_frames
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.dsp.track import (
    SensorTracks,
    TrackerConfig,
    assign,
    cv_model,
    doppler_fit,
    innovations,
    measurements,
    predict,
    radial_velocity,
    report,
    step_tracks,
    update,
    update_radial_velocity,
    velocity_chi2,
)
from pipeline.nodes.tracker import Integration, Tracker, track_batch
from pipeline.wire import TRACK_FIELDS, FrameHeaders, TracksMsg, decode_tracks
from radar_driver.model import RadarConfig, add_noise, polar_to_xy, simulate_frames, wrap_velocity
from radar_driver.scene import ramp_time_s, resolve_scene
from zenoh_helpers import QRADAR

RATE_HZ = 20.0
PERIOD_NS = 50_000_000


# -- the math on known inputs ------------------------------------------------------------------------
def test_cv_model_is_the_wiener_acceleration_model():
    f, q = cv_model(0.1, 2.0)
    assert_allclose(f @ np.array([1.0, 2.0, 3.0, -4.0]), [1.3, 1.6, 3.0, -4.0])
    # Q = G G^T sigma^2 with G = (dt^2/2, dt) a axis
    g = np.array([0.005, 0.1])
    assert_allclose(q[np.ix_([0, 2], [0, 2])], 4.0 * np.outer(g, g))
    assert_allclose(q[np.ix_([1, 3], [1, 3])], 4.0 * np.outer(g, g))
    assert q[0, 1] == q[0, 3] == q[2, 1] == 0.0


def test_measurement_covariance_is_the_jacobian_of_polar_to_xy():
    r, a = np.array([5.0, 12.0]), np.array([-30.0, 10.0])
    z, cov = measurements(r, a, 0.1, 2.0)
    x, y = polar_to_xy(r, np.deg2rad(a))
    assert_allclose(z, np.stack([x, y], axis=-1))
    eps = 1e-6
    for i in range(2):  # numeric Jacobian of (R, theta) -> (x, y)
        th = np.deg2rad(a[i])
        jr = (np.array(polar_to_xy(r[i] + eps, th)) - np.array(polar_to_xy(r[i] - eps, th))) / (2 * eps)
        ja = (np.array(polar_to_xy(r[i], th + eps)) - np.array(polar_to_xy(r[i], th - eps))) / (2 * eps)
        j = np.stack([jr, ja], axis=1)
        assert_allclose(cov[i], j @ np.diag([0.01, np.deg2rad(2.0) ** 2]) @ j.T, rtol=1e-6)


def test_update_is_the_kalman_update():
    rng = np.random.default_rng(1)
    a = rng.standard_normal((3, 4, 4))
    p = a @ a.transpose(0, 2, 1) + np.eye(4)
    x = rng.standard_normal((3, 4))
    z = rng.standard_normal((3, 2))
    b = rng.standard_normal((3, 2, 2))
    r = b @ b.transpose(0, 2, 1) + 0.1 * np.eye(2)
    x1, p1 = update(x, p, z, r)
    h = np.eye(2, 4)
    for i in range(3):  # the textbook form
        s = h @ p[i] @ h.T + r[i]
        k = p[i] @ h.T @ np.linalg.inv(s)
        assert_allclose(x1[i], x[i] + k @ (z[i] - h @ x[i]))
        assert_allclose(p1[i], (np.eye(4) - k @ h) @ p[i], atol=1e-10)
    d2, logdet = innovations(x, p, z, r)
    for i in range(3):
        for j in range(3):
            s = p[i, :2, :2] + r[j]
            nu = z[j] - x[i, :2]
            assert_allclose(d2[i, j], nu @ np.linalg.solve(s, nu))
            assert_allclose(logdet[i, j], np.log(np.linalg.det(s)))
    assert_allclose(velocity_chi2(x, p), [x[i, 2:] @ np.linalg.solve(p[i, 2:, 2:], x[i, 2:]) for i in range(3)])


def test_predict_moves_at_constant_velocity_and_grows_the_covariance():
    x = np.array([[1.0, 2.0, 0.5, -1.0]])
    p = np.eye(4)[None] * 0.01
    x1, p1 = predict(x, p, 2.0, 1.0)
    assert_allclose(x1, [[2.0, 0.0, 0.5, -1.0]])
    f, q = cv_model(2.0, 1.0)
    assert_allclose(p1[0], f @ p[0] @ f.T + q)
    assert p1[0, 0, 0] == pytest.approx(0.01 + 4 * 0.01 + 4.0)  # var x + dt^2 var vx + dt^4 / 4 sigma_a^2


def test_assign_is_global_and_gated():
    d2 = np.array([[1.0, 2.0], [1.5, 50.0]])
    rows, cols = assign(d2, np.zeros_like(d2), 13.8)
    assert sorted(zip(rows.tolist(), cols.tolist())) == [(0, 1), (1, 0)]  # greedy would take (0, 0) and lose track 1
    rows, cols = assign(np.array([[20.0, 30.0]]), np.zeros((1, 2)), 13.8)
    assert rows.size == cols.size == 0
    rows, cols = assign(np.zeros((0, 3)), np.zeros((0, 3)), 13.8)
    assert rows.size == 0


def test_assign_is_the_brute_force_optimum():
    """The Hungarian assignment against every assignment enumerated (the reference)."""
    import itertools

    rng = np.random.default_rng(5)
    for _ in range(50):
        t, k = rng.integers(1, 5, size=2)
        d2 = rng.exponential(8.0, (t, k))
        logdet = rng.normal(0.0, 1.0, (t, k))
        rows, cols = assign(d2, logdet, 13.8)
        ok = d2 <= 13.8
        best = (0, 0.0)  # (pairs, -cost): the most pairs within the gate, then the least cost
        for perm in itertools.permutations(range(max(t, k))):
            pairs = [(i, j) for i, j in enumerate(perm[:t]) if j < k and ok[i, j]]
            score = (len(pairs), -sum(d2[i, j] + logdet[i, j] for i, j in pairs))
            best = max(best, score)
        got = (len(rows), -float(sum(d2[rows, cols] + logdet[rows, cols])))
        assert got[0] == best[0] and got[1] == pytest.approx(best[1])


@pytest.mark.parametrize("kw", [{"accel_mps2": 0}, {"gate_chi2": float("nan")}, {"confirm_hits": 0},
                                {"max_tracks": 2.5}, {"static_chi2": 20.0, "moving_chi2": 10.0},
                                {"integrate_s": -1}, {"integrate_s": True}, {"timestamp_sigma_s": 0},
                                {"timestamp_sigma_s": float("inf")}])
def test_bad_config_is_refused(kw):
    with pytest.raises(ParameterError, match="tracker: "):
        TrackerConfig(**kw)


# -- track management on synthetic targets -----------------------------------------------------------
def _run(tracker, ranges, angles, sid="s"):
    """Step the tracker over frames of targets (F, K) (NaN: absent); the tracks of each frame."""
    return [tracker.step(sid, i * PERIOD_NS, r[np.isfinite(r)], a[np.isfinite(r)]) for i, (r, a) in
            enumerate(zip(ranges, angles))]


def test_birth_needs_hits_and_a_lone_false_target_never_confirms():
    cfg = TrackerConfig()
    r = np.full((10, 2), np.nan)
    a = np.full((10, 2), np.nan)
    r[:, 0], a[:, 0] = 8.0, 10.0
    r[4, 1], a[4, 1] = 30.0, -40.0  # one frame only
    out = _run(Tracker(cfg), r, a)
    assert [len(o) for o in out[:cfg.confirm_hits - 1]] == [0] * (cfg.confirm_hits - 1)
    assert all(len(o) == 1 and o[0]["track_id"] == 1 for o in out[cfg.confirm_hits - 1:])


def test_state_is_bounded_and_forgotten():
    tr = Tracker(TrackerConfig(max_tracks=3), max_sensors=2)
    r = np.arange(10.0, 20.0)[None].repeat(5, axis=0)
    out = _run(tr, r, np.zeros_like(r))
    assert len(tr.state("s").ids) == 3 and len(out[-1]) == 3
    _run(tr, r[:1], np.zeros_like(r[:1]), "b")
    _run(tr, r[:1], np.zeros_like(r[:1]), "c")  # a third sensor: the oldest goes
    assert tr.sensors == ["b", "c"]
    tr.forget("b")
    assert tr.sensors == ["c"]


def test_a_late_frame_is_left_out_and_time_going_far_back_starts_afresh():
    tr = Tracker()
    t0 = 1000 * PERIOD_NS
    for i in range(5):
        tracks = tr.step("s", t0 + i * PERIOD_NS, [8.0], [0.0])
    assert tr.step("s", t0 + 2 * PERIOD_NS, [30.0], [40.0]) == tracks  # came late: nothing changes
    assert tr.state("s").hits.tolist() == [5] and tr.state("s").last_ns == t0 + 4 * PERIOD_NS
    assert tr.step("s", t0 - int(6e9), [8.0], [0.0]) == []  # a restarted sensor clock: no stale track
    assert tr.state("s").next_id == 3


def test_static_test_has_hysteresis_and_flags_motion():
    tr = Tracker()
    rng = np.random.default_rng(3)
    n = 60
    r = np.stack([8.0 + 0.03 * rng.standard_normal(n), 4.0 + 1.0 * np.arange(n) / RATE_HZ], axis=1)
    a = np.stack([20.0 + 1.0 * rng.standard_normal(n), -30.0 + 1.0 * rng.standard_normal(n)], axis=1)
    out = _run(tr, r, a)
    by_id = {t["track_id"]: t for t in out[-1]}
    assert by_id[1]["static"] and not by_id[2]["static"]
    assert_allclose(np.hypot(by_id[2]["vx_mps"], by_id[2]["vy_mps"]), 1.0, atol=0.15)
    static_frames = [next(t for t in o if t["track_id"] == 1)["static"] for o in out[10:]]
    assert all(static_frames)  # once static, the strays of a static reflector do not end it


# -- real scenes, 1 bit, the default decoder ----------------------------------------------------------
def _decode(frames, radar, k, seed=7, auto_k=False):
    q = quantize_frames(frames, QuantizerConfig(), np.arange(frames.shape[0], dtype=np.uint64), dither_seed=seed)
    det = decode_batch(q, radar, k, DecoderConfig(gate=RangeGate.default(radar), auto_k=auto_k))
    return q, det


def _scene_frames(name, n, seed=1):
    scene = resolve_scene(name)
    rpf = scene.radar.ramps_per_frame
    t = ramp_time_s(np.arange(n * rpf), RATE_HZ * rpf)
    frames = scene.ramps(t, np.random.default_rng(seed)).reshape(n, rpf * scene.radar.samples_per_ramp, 2)
    return scene, frames


def _headers(n, sid="s", t0_ns=0):
    return FrameHeaders([sid] * n, np.arange(n, dtype=np.uint64), t0_ns + np.arange(n, dtype=np.int64) * PERIOD_NS,
                        np.zeros(n, dtype=np.uint32))


def _nearest_track(tracks, x, y, within_m=1.0):
    if not tracks:
        return None
    d = [np.hypot(t["x_m"] - x, t["y_m"] - y) for t in tracks]
    i = int(np.argmin(d))
    return tracks[i] if d[i] <= within_m else None


def test_walker_one_id_speed_and_position():
    n = 100  # 5 s: the walker goes from 3 m to 10.5 m
    scene, frames = _scene_frames("walker", n)
    _, det = _decode(frames, scene.radar, 2)
    msgs = [decode_tracks(p) for p in track_batch(Tracker(TrackerConfig(integrate_s=0)), _headers(n), det,
                                                  radar=scene.radar)]
    walker = scene.targets[0]
    th = np.deg2rad(walker.angle_deg)
    ids, speed_err, track_err, frame_err, doppler_err = [], [], [], [], []
    for i, m in enumerate(msgs):
        tx, ty = polar_to_xy(walker.range_at(i / RATE_HZ), th)
        frame_err.append(np.min(np.hypot(det.x_m[i] - tx, det.y_m[i] - ty)))
        t = _nearest_track(m.tracks, tx, ty)
        if t is None:
            continue
        ids.append(t["track_id"])
        track_err.append(np.hypot(t["x_m"] - tx, t["y_m"] - ty))
        speed_err.append(np.hypot(t["vx_mps"] - walker.velocity_m_s * np.cos(th),
                                  t["vy_mps"] - walker.velocity_m_s * np.sin(th)))
        assert not t["static"] or i < 10
        if i >= 20:  # 1 s: the Doppler's ambiguity resolved (6 whole V at 1.5 m/s)
            doppler_err.append(t["radial_velocity_mps"] - walker.velocity_m_s)
    assert len(set(ids)) == 1 and len(ids) >= n - 5  # one id, from confirmation to the end
    assert np.max(np.abs(doppler_err)) <= 0.01, doppler_err
    assert np.median(speed_err) <= 0.05  # positions alone: 0.033 m/s
    assert np.median(track_err) <= np.median(frame_err)


def _stalled_stamps(n, stalls_ns, t0_ns=10**9):
    """Timestamps of n frames measured PERIOD_NS apart as a busy host's clock stamps them:
    frame i's arrival held ``stalls_ns[i]`` ns, and the frames that came meanwhile taken
    (and stamped) together after it, 1 ms apart (radar_driver.assembly: the host's clock)."""
    out = np.empty(n, dtype=np.int64)
    free = 0
    for i in range(n):
        out[i] = max(t0_ns + i * PERIOD_NS, free) + stalls_ns.get(i, 0)
        free = int(out[i]) + 1_000_000
    return out


def test_walker_keeps_one_track_through_a_busy_hosts_timestamps():
    """The frames' timestamps are the host's clock when they arrived: a busy host stamps a
    frame 120-200 ms late and the next ones bunched. The walker (1.5 m/s) is then up to
    0.3 m behind where its track predicts it at the stamp; the tracker counts the
    timestamps' error (timestamp_sigma_s) and keeps one track, as with exact timestamps.
    One that trusts its timestamps (the filter's position std 5 mm) loses it at every stall."""
    n = 80
    scene, frames = _scene_frames("walker", n)
    _, det = _decode(frames, scene.radar, 2)
    stamps = _stalled_stamps(n, {10: 200_000_000, 23: 150_000_000, 36: 120_000_000, 50: 180_000_000,
                                 63: 200_000_000})
    assert np.diff(stamps)[9:14].tolist() == [250_000_000] + [1_000_000] * 4
    headers = FrameHeaders(["s"] * n, np.arange(n, dtype=np.uint64), stamps, np.zeros(n, dtype=np.uint32))

    def track(cfg):
        tr = Tracker(cfg)
        return tr, [decode_tracks(p) for p in track_batch(tr, headers, det, radar=scene.radar)]

    tr, msgs = track(TrackerConfig(integrate_s=0))
    walker = scene.targets[0]
    th = np.deg2rad(walker.angle_deg)
    ids = []
    for i, m in enumerate(msgs[5:], start=5):
        tx, ty = polar_to_xy(walker.range_at(i / RATE_HZ), th)
        t = _nearest_track(m.tracks, tx, ty, 0.5)
        assert t is not None and not t["static"], i
        ids.append(t["track_id"])
    assert set(ids) == {ids[0]} and tr.state("s").next_id == 3  # the walker and the reflector, no other
    last = next(t for t in msgs[-1].tracks if t["track_id"] == ids[0])
    assert abs(last["radial_velocity_mps"] - walker.velocity_m_s) < 0.01  # its Doppler resolved all the same
    trusting, _ = track(TrackerConfig(integrate_s=0, timestamp_sigma_s=1e-4))
    assert trusting.state("s").next_id > 6


def _moving(n, r0, v, angle, amp, seed=2, noise=0.01):
    """Frames (n, 512, 2) of targets at ranges r0 + v t (NaN r0: absent; v radial, m/s, also
    between the frame's ramps), with complex noise of std ``noise`` a component."""
    radar = RadarConfig()
    t = np.arange(n)[:, None] / RATE_HZ
    r = np.asarray(r0)[None] + np.asarray(v)[None] * t
    a = np.broadcast_to(np.asarray(angle, float), r.shape)
    x = np.broadcast_to(np.asarray(amp, complex), r.shape).copy()
    x[~np.isfinite(r)] = 0.0
    frames = simulate_frames(np.nan_to_num(r, nan=50.0), a, x, radar,
                             velocity_mps=np.broadcast_to(np.asarray(v, float), r.shape))
    frames = frames + noise * (np.random.default_rng(seed).standard_normal(frames.shape)
                               + 1j * np.random.default_rng(seed + 1).standard_normal(frames.shape))
    return radar, frames, r, a


def _ids_along(msgs, r, a, k):
    """The id of the track nearest target k in each frame (None: no track within 1 m)."""
    out = []
    for i, m in enumerate(msgs):
        if not np.isfinite(r[i, k]):
            out.append(None)
            continue
        x, y = polar_to_xy(r[i, k], np.deg2rad(a[i, k]))
        t = _nearest_track(m.tracks, x, y)
        out.append(None if t is None else t["track_id"])
    return out


def test_a_target_that_appears_and_one_that_vanishes():
    n = 80
    radar, frames, r, a = _moving(n, [6.0, 15.0, 25.0], [0.0, 0.5, -0.5], [10.0, -25.0, 40.0], [0.3, 0.25, 0.2])
    r[:30, 1] = np.nan  # target 1 appears at frame 30
    r[50:, 2] = np.nan  # target 2 vanishes at frame 50
    radar, frames, _, _ = _moving(n, [6.0, 15.0, 25.0], [0.0, 0.5, -0.5], [10.0, -25.0, 40.0], [0.3, 0.25, 0.2])
    frames[:30] = _moving(30, [6.0, np.nan, 25.0], [0.0, 0.5, -0.5], [10.0, -25.0, 40.0], [0.3, 0.25, 0.2])[1]
    frames[50:] = _moving(n, [6.0, 15.0, np.nan], [0.0, 0.5, -0.5], [10.0, -25.0, 40.0], [0.3, 0.25, 0.2])[1][50:]
    _, det = _decode(frames, radar, 3, auto_k=True)
    cfg = TrackerConfig(integrate_s=0)
    msgs = [decode_tracks(p) for p in track_batch(Tracker(cfg), _headers(n), det)]
    ids = [_ids_along(msgs, r, a, k) for k in range(3)]
    # the steady target: one id throughout; the new one: tracked within confirm_hits + 2 frames, one id
    assert len(set(ids[0][cfg.confirm_hits:])) == 1 and None not in ids[0][cfg.confirm_hits:]
    assert len(set(ids[1][30 + cfg.confirm_hits + 2:])) == 1 and None not in ids[1][30 + cfg.confirm_hits + 2:]
    assert len(set(ids[2][cfg.confirm_hits:50])) == 1 and None not in ids[2][cfg.confirm_hits:50]
    gone = ids[2][cfg.confirm_hits]
    coast = int(cfg.max_coast_s * RATE_HZ) + 2
    assert all(gone not in [t["track_id"] for t in m.tracks] for m in msgs[50 + coast:])  # it dies
    assert len({ids[0][-1], ids[1][-1], gone}) == 3


def test_two_targets_that_cross_keep_their_ids():
    n = 100  # 5 s; they meet in range at t = 2.5 s (8 m), 20 degrees apart
    radar, frames, r, a = _moving(n, [5.5, 10.5], [1.0, -1.0], [10.0, -10.0], [0.3, 0.3])
    _, det = _decode(frames, radar, 2)
    msgs = [decode_tracks(p) for p in track_batch(Tracker(TrackerConfig(integrate_s=0)), _headers(n), det)]
    ids = [_ids_along(msgs, r, a, k) for k in range(2)]
    before, after = slice(5, 35), slice(65, n)
    for k in range(2):
        seen = {i for i in ids[k][before] + ids[k][after] if i is not None}
        assert len(seen) == 1, f"target {k}: track ids {ids[k]}"
    assert ids[0][5] != ids[1][5]
    # no lost track: both ids are reported in every frame from confirmation to the end
    for m in msgs[5:]:
        assert {ids[0][5], ids[1][5]} <= {t["track_id"] for t in m.tracks}


# -- Doppler: the radial velocity, its ambiguity resolved over frames ---------------------------------
def test_radial_velocity_update_is_the_extended_kalman_update():
    rng = np.random.default_rng(4)
    x = np.column_stack([rng.uniform(2, 30, 3), rng.uniform(-10, 10, 3), rng.normal(0, 1, (3, 2))])
    h, jac = radial_velocity(x)
    assert_allclose(h, np.einsum("ti,ti->t", x[:, :2], x[:, 2:]) / np.hypot(x[:, 0], x[:, 1]))
    eps = 1e-6  # the Jacobian by finite differences
    num = np.stack([(radial_velocity(x + eps * np.eye(4)[j])[0] - h) / eps for j in range(4)], axis=1)
    assert_allclose(jac, num, atol=1e-5)
    a = rng.normal(size=(3, 4, 4))
    p = a @ a.transpose(0, 2, 1) + np.eye(4)
    v = h + np.array([0.1, -0.05, 30.0])  # the last beyond the gate
    x2, p2, made = update_radial_velocity(x, p, v, 0.02)
    assert made.tolist() == [True, True, False]
    for i in range(2):
        hh = jac[i][None]
        s = hh @ p[i] @ hh.T + 0.02 ** 2
        k = p[i] @ hh.T / s
        assert_allclose(x2[i], x[i] + (k * (v[i] - h[i]))[:, 0])
        assert_allclose(p2[i], (np.eye(4) - k @ hh) @ p[i], atol=1e-9)
    assert_allclose(x2[2], x[2]) and assert_allclose(p2[2], p[2])


def test_doppler_fit_finds_the_whole_number_of_v():
    v_amb, t = 0.25, np.arange(20) / 20.0
    for n_true in (-9, 0, 4):
        y = 12.0 + n_true * v_amb * t + 0.01 * np.random.default_rng(n_true + 20).standard_normal(t.size)
        w = np.full(t.size, 1 / 0.01 ** 2)
        sums = np.array([[w.sum(), (w * t).sum(), (w * t * t).sum(), (w * y).sum(), (w * t * y).sum(),
                          (w * y * y).sum(), t.size]])
        slope, sd, whole = doppler_fit(sums, v_amb)
        assert whole[0] == n_true and abs(slope[0] - n_true) < 3 * sd[0] and sd[0] < 1 / 8
        bad = sums.copy()
        bad[0, :6] *= 1e4  # ranges claimed 100 x surer than they scatter: sd follows the scatter
        assert_allclose(doppler_fit(bad, v_amb)[1], sd, rtol=0.3)


def _doppler_targets(v, n=60, r0=10.0, angle=20.0, sigma_r=0.01, seed=0, gap=None):
    """One target at r0 + v t, its Doppler folded into V, ranges with noise sigma_r: stepped
    through a tracker state; the reported tracks per frame ([] where a gap leaves it out)."""
    cfg, st, out = TrackerConfig(), SensorTracks(), []
    rng = np.random.default_rng(seed)
    v_amb = RadarConfig().velocity_ambiguity_mps
    for i in range(n):
        if gap is not None and gap[0] <= i < gap[1]:
            out.append([])
            continue
        r = r0 + v * i / RATE_HZ + sigma_r * rng.standard_normal()
        step_tracks(st, cfg, i * PERIOD_NS, np.array([r]), np.array([angle]), np.array([15.6]),  # sigma_R 0.01 m
                    wrap_velocity(np.array([v]), RadarConfig()), v_amb)
        out.append(report(st, i * PERIOD_NS))
    return st, out


@pytest.mark.parametrize("v", [0.0, 0.125, 0.8, -2.3, 3.9])
def test_a_track_resolves_its_dopplers_ambiguity_and_its_velocity_agrees(v):
    st, out = _doppler_targets(v)
    first = next(i for i, o in enumerate(out) if o and "radial_velocity_mps" in o[0])
    assert first <= 20  # 1 s
    for o in out[first:]:
        (t,) = o
        assert abs(t["radial_velocity_mps"] - v) < 1e-9  # the exact Doppler, unwrapped
    t = out[-1][0]
    th = np.arctan2(t["y_m"], t["x_m"])
    assert abs(t["vx_mps"] * np.cos(th) + t["vy_mps"] * np.sin(th) - v) < 0.01  # the filter's radial velocity
    assert st.doppler_rejected == 0 and st.doppler_changed == 0


@pytest.mark.parametrize("v", [0.125, 0.8, -2.3])
def test_decoded_frames_in_noise_resolve_the_right_whole_number_of_v(v):
    """cml's Doppler of a target moving between the ramps (0.125 m/s: a blind speed of the
    static model), 1-bit at the default alpha in noise 0.1 with amplitude 0.3, off the grid:
    the track's radial velocity resolved within 25 frames and never a wrong whole V after."""
    n = 120
    radar, frames, r, a = _moving(n, [23.37], [v], [12.0], [0.3], seed=4, noise=0.1)
    _, det = _decode(frames, radar, 1)
    msgs = [decode_tracks(p) for p in track_batch(Tracker(TrackerConfig(integrate_s=0)), _headers(n), det,
                                                  radar=radar)]
    got = []
    for i, m in enumerate(msgs):
        x, y = polar_to_xy(r[i, 0], np.deg2rad(a[i, 0]))
        t = _nearest_track(m.tracks, x, y)
        got.append(None if t is None else t.get("radial_velocity_mps"))
    first = next(i for i, g in enumerate(got) if g is not None)
    assert first <= 25, got[:30]
    err = np.array([np.inf if g is None else g - v for g in got[first:]])
    assert (np.abs(err) < radar.velocity_ambiguity_mps / 4).all(), got[first:]  # never a wrong whole V
    assert np.median(np.abs(err)) < 0.005, np.median(np.abs(err))


def test_a_gap_in_the_doppler_starts_its_history_afresh():
    _, out = _doppler_targets(1.1, n=80, gap=(30, 40))  # 0.5 s without the target: 1.1 m/s may have changed
    assert "radial_velocity_mps" in out[29][0]
    assert out[40] and "radial_velocity_mps" not in out[40][0]  # unresolved again ...
    assert all("radial_velocity_mps" in o[0] for o in out[60:])  # ... and resolved again
    assert abs(out[-1][0]["radial_velocity_mps"] - 1.1) < 1e-9


def test_no_doppler_no_radial_velocity():
    """PBP keeps the static model (no Doppler): its tracks have no radial velocity; nor do
    tracks fed targets without their radar (whose V the Doppler needs)."""
    radar, frames, r, a = _moving(30, [15.0], [0.6], [10.0], [1.0])
    q = quantize_frames(frames, QuantizerConfig(), np.arange(30, dtype=np.uint64), dither_seed=7)
    pbp = decode_batch(q, radar, 1, DecoderConfig(algo="pbp", gate=RangeGate.default(radar)))
    cml = decode_batch(q, radar, 1, DecoderConfig(gate=RangeGate.default(radar)))
    for det, rad in ((pbp, radar), (cml, None)):
        msgs = [decode_tracks(p) for p in track_batch(Tracker(TrackerConfig(integrate_s=0)), _headers(30), det,
                                                      radar=rad)]
        assert msgs[-1].tracks and not any("radial_velocity_mps" in t for m in msgs for t in m.tracks)
    msgs = [decode_tracks(p) for p in track_batch(Tracker(TrackerConfig(integrate_s=0)), _headers(30), cml,
                                                  radar=radar)]
    assert abs(msgs[-1].tracks[0]["radial_velocity_mps"] - 0.6) < 0.005


# -- the wire --------------------------------------------------------------------------------------
def test_tracks_json_round_trip_and_exact_fields():
    t = {"track_id": 7, "range_m": 9.23, "angle_deg": 15.0, "x_m": 8.9, "y_m": 2.4, "vx_mps": -0.01,
         "vy_mps": 0.02, "sigma_m": 0.05, "age_s": 3.5, "hits": 70, "static": True, "radial_velocity_mps": 0.0125}
    msg = TracksMsg("kmd2-0", 41, 1795269781156003626, [t], 1795269781183123456)
    obj = json.loads(msg.to_json())
    assert list(obj) == ["version", "type", "sensor_id", "seq", "timestamp_ns", "published_ns", "tracks"]
    assert obj["type"] == "tracks" and list(obj["tracks"][0]) == list(TRACK_FIELDS)
    assert decode_tracks(msg.to_json()) == msg
    unresolved = {k: v for k, v in t.items() if k != "radial_velocity_mps"}  # an optional field: absent
    assert decode_tracks(TracksMsg("a", 0, 0, [unresolved]).to_json()).tracks == [unresolved]
    assert decode_tracks(TracksMsg("a", 0, 0, []).to_json()).tracks == []


@pytest.mark.parametrize("edit, what", [
    (lambda o: o["tracks"][0].update(static=1), "static"),
    (lambda o: o["tracks"][0].update(hits=-1), "hits"),
    (lambda o: o["tracks"][0].update(track_id=True), "track_id"),
    (lambda o: o["tracks"][0].pop("sigma_m"), "sigma_m"),
    (lambda o: o["tracks"][0].update(radial_velocity_mps="fast"), "radial_velocity_mps"),
    (lambda o: o["tracks"][0].update(radial_velocity_mps=True), "radial_velocity_mps"),
    (lambda o: o["tracks"][0].update(vx_mps="1.5"), "vx_mps"),
    (lambda o: o.update(tracks={}), "tracks"),
    (lambda o: o.update(sensor_id="a/b"), "sensor_id"),
    (lambda o: o.update(type="targets"), "type"),
])
def test_bad_tracks_json_is_refused_with_its_field(edit, what):
    t = dict(zip(TRACK_FIELDS, [1, 9.0, 1.0, 9.0, 0.1, 0.0, 0.0, 0.1, 1.0, 3, False]))
    obj = json.loads(TracksMsg("s", 1, 2, [t], 3).to_json())
    edit(obj)
    with pytest.raises(WireError, match=what):
        decode_tracks(json.dumps(obj).encode(), "radar/s/tracks")
    with pytest.raises(WireError, match="not finite|JSON"):
        decode_tracks(b'{"version":1,"type":"tracks","sensor_id":"s","seq":1,"timestamp_ns":0,"published_ns":0,'
                      b'"tracks":[{"track_id":1,"range_m":NaN}]}')


# -- integration of static tracks ---------------------------------------------------------------------
def test_stacked_frames_are_one_frame_of_more_ramps():
    scene, frames = _scene_frames("chamber-ideal", 3)
    q, _ = _decode(frames[:0], scene.radar, 2)  # (no frames: nothing to decode)
    q = quantize_frames(frames, QuantizerConfig(), np.arange(3, dtype=np.uint64), dither_seed=5)
    z, xi, delta = stack_frames(q)
    assert z.shape == xi.shape == (1, 3 * 512, 2)
    assert_allclose(xi[0, 512:1024], q.take(np.array([1])).dither()[0])
    # the codes' signs are the frames' own; one common step
    assert np.array_equal(np.sign(z[0].real), np.sign(q.values().reshape(-1, 2).real))
    assert_allclose(np.abs(z.real), delta / 2)
    parts = concat_frames([q.take(np.array([0])), q.take(np.array([1, 2]))])
    assert np.array_equal(parts.codes, q.codes) and np.array_equal(parts.seq, q.seq)
    with pytest.raises(ParameterError, match="dithered"):
        stack_frames(quantize_frames(frames, QuantizerConfig(alpha=0.0), np.arange(3, dtype=np.uint64)))


def test_integration_sharpens_a_static_scene():
    scene, frames = _scene_frames("chamber-ideal", 40)
    q, det = _decode(frames, scene.radar, 2)
    truth = scene.truth()
    tx = np.array([t["x_m"] for t in truth])
    ty = np.array([t["y_m"] for t in truth])
    one = np.hypot(det.x_m[:, :, None] - tx, det.y_m[:, :, None] - ty).min(axis=1)  # (F, 2)
    gate = RangeGate.default(scene.radar)
    errs = []
    for s in range(0, 40, 20):
        d = integrate(q.take(np.arange(s, s + 20)), scene.radar, 2, gate)
        errs.append(np.hypot(d.x_m[0][:, None] - tx, d.y_m[0][:, None] - ty).min(axis=0))
    assert np.median(errs) < 0.5 * np.median(one)


def test_tracker_reports_the_integrated_position_of_static_tracks():
    n = 40
    scene, frames = _scene_frames("chamber-ideal", n)
    q, det = _decode(frames, scene.radar, 2)
    gate = RangeGate.default(scene.radar)
    cfg = TrackerConfig(integrate_s=1.0)
    tr = Tracker(cfg, Integration(k=2, gate=gate, every_s=0.0))
    msgs = [decode_tracks(p) for p in track_batch(tr, _headers(n), det, q, scene.radar)]
    plain = [decode_tracks(p) for p in track_batch(Tracker(TrackerConfig(integrate_s=0)), _headers(n), det)]
    assert tr.refinements > 0
    st = tr.state("s")
    assert st.static.all() and np.isfinite(st.refined).all()
    truth = scene.truth()

    def err(ms):
        e = []
        for t in truth:
            for m in ms[-10:]:
                tk = _nearest_track(m.tracks, t["x_m"], t["y_m"])
                e.append(np.hypot(tk["x_m"] - t["x_m"], tk["y_m"] - t["y_m"]))
        return np.median(e)

    assert err(msgs) < err(plain)
    # the reported position is the refined one
    last = {t["track_id"]: t for t in msgs[-1].tracks}
    for i, tid in enumerate(st.ids.tolist()):
        assert_allclose([last[tid]["x_m"], last[tid]["y_m"]], st.refined[i], rtol=1e-8)


def test_background_refinements_do_not_hold_the_frames():
    """The live localizer refines static tracks in a thread of its own: frames go on while a
    refinement runs (those due meanwhile are skipped, not waited for), its result lands on
    the same static tracks, and close() ends the thread."""
    n = 40
    scene, frames = _scene_frames("chamber-ideal", n)
    q, det = _decode(frames, scene.radar, 2)
    gate = RangeGate.default(scene.radar)
    cfg = TrackerConfig(integrate_s=1.0)
    sync = Tracker(cfg, Integration(k=2, gate=gate, every_s=0.0))
    track_batch(sync, _headers(n), det, q, scene.radar)
    bg = Tracker(cfg, Integration(k=2, gate=gate, every_s=0.0), background=True)
    track_batch(bg, _headers(n), det, q, scene.radar)
    assert bg.refinements_skipped > 0  # frames came on while a refinement ran
    deadline = time.monotonic() + 60
    while bg._pending and time.monotonic() < deadline:
        time.sleep(0.01)
    assert 0 < bg.refinements < sync.refinements and bg.refinement_errors == 0
    with bg._lock:
        refined = bg.state("s").refined.copy()
    # the last refinement saw a window older than the sync tracker's last one, by as many frames
    # as the host was slow (a window short enough may miss the weak reflector: that track then
    # reports its filter's), so its positions are another estimate of the same reflectors: each
    # lands on the track of the reflector the sync tracker's refinement found, near it (the weak
    # one, amplitude 0.036, was 0.11 m off on a window of a busy host's few frames)
    found = np.isfinite(refined).all(axis=1)
    assert found.any()
    truth = np.array([[t["x_m"], t["y_m"]] for t in scene.truth()])

    def reflector(xy):
        return np.linalg.norm(xy[:, None, :] - truth[None], axis=2).argmin(axis=1)

    mine = reflector(refined[found])
    assert (mine == reflector(sync.state("s").refined[found])).all() and len(set(mine.tolist())) == found.sum()
    assert np.linalg.norm(refined[found] - truth[mine], axis=1).max() < 0.25
    bg.close()
    assert bg._thread is None


def test_integration_stops_when_the_track_moves():
    st = SensorTracks()
    cfg = TrackerConfig()
    for i in range(20):
        step_tracks(st, cfg, i * PERIOD_NS, np.array([8.0]), np.array([0.0]))
    assert st.static.all()
    st.refined[:] = [8.0, 0.0]
    for i in range(20, 40):  # it walks off, accelerating at 3 m/s^2 (a brisk start)
        t = (i - 19) / RATE_HZ
        step_tracks(st, cfg, i * PERIOD_NS, np.array([8.0 + 1.5 * t * t]), np.array([0.0]))
        if not st.static.all():
            break
    assert len(st.ids) == 1 and not st.static.any() and np.isnan(st.refined).all()
    assert i < 30  # within half a second (0.3 m)


# -- live: a real `qradar localize --track` over zenoh ---------------------------------------------------
def test_live_localize_track_publishes_tracks(free_port, connect_when_ready):
    import subprocess
    import sys
    import time

    import zenoh
    from zenoh_helpers import Collector, wait_until

    from pipeline.wire import encode_quantized_batch

    n = 60
    scene, frames = _scene_frames("walker", n)
    radar = scene.radar
    seed = 11
    from pipeline.dsp.quantize import sensor_dither_seed
    q = quantize_frames(frames, QuantizerConfig(), np.arange(n, dtype=np.uint64),
                        dither_seed=sensor_dither_seed(seed, "walk0"))
    t0 = time.time_ns()
    headers = FrameHeaders(["walk0"] * n, np.arange(n, dtype=np.uint64), t0 + np.arange(n, dtype=np.int64) * PERIOD_NS,
                           np.full(n, radar.config_id(), dtype=np.uint32))
    payloads = encode_quantized_batch(headers, q)
    ep = f"tcp/127.0.0.1:{free_port}"
    proc = subprocess.Popen([*QRADAR, "localize", "--listen", ep, "--K", "2", "--track",
                             "--duration", "240"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        session = connect_when_ready(ep, timeout_s=30, mode="client")
        col = Collector(session, "radar/walk0/**")

        def alive():
            return {str(r.ok.key_expr).split("/")[2] for r in session.liveliness().get("radar/alive/**", timeout=1.0)
                    if r.ok is not None}

        wait_until(lambda: "localize" in alive(), 30, "the localizer alive")
        pub = session.declare_publisher("radar/walk0/quantized", congestion_control=zenoh.CongestionControl.BLOCK)
        for p in payloads:  # in order, at about the sensor's pace
            pub.put(p)
            time.sleep(0.01)
        wait_until(lambda: len(col.of("walk0/tracks")) == n, 120,
                   lambda: f"{n} tracks messages (got {len(col.of('walk0/tracks'))})")
        msgs = [decode_tracks(p, "radar/walk0/tracks") for p in col.of("walk0/tracks")]
        raw = [json.loads(p) for p in col.of("walk0/tracks")]
        session.close()
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert sorted(m.seq for m in msgs) == list(range(n))
    msgs.sort(key=lambda m: m.seq)
    assert all(m.timestamp_ns == t0 + m.seq * PERIOD_NS and m.published_ns >= t0 for m in msgs)
    assert all(list(o) == ["version", "type", "sensor_id", "seq", "timestamp_ns", "published_ns", "tracks"]
               for o in raw)
    walker, reflector = scene.targets
    th = np.deg2rad(walker.angle_deg)
    ids = set()
    for m in msgs[10:]:
        tx, ty = polar_to_xy(walker.range_at(m.seq / RATE_HZ), th)
        t = _nearest_track(m.tracks, tx, ty)
        assert t is not None and not t["static"] and t["vx_mps"] > 1.0
        ids.add(t["track_id"])
    assert len(ids) == 1
    rx, ry = polar_to_xy(reflector.range_m, np.deg2rad(reflector.angle_deg))
    t = _nearest_track(msgs[-1].tracks, rx, ry, 0.5)
    assert t is not None and t["static"] and t["hits"] >= n - 5 and t["age_s"] == pytest.approx((n - 1) / RATE_HZ)
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["frames_out"] == n  # frames, not messages: the tracks do not count twice


# -- recorded: qradar run --track to MCAP, replayed; qradar reprocess --track -------------------------
def test_run_track_records_tracks_that_replay(tmp_path):
    import subprocess
    import sys

    from replay.mcapio import McapFile

    path = tmp_path / "run.mcap"
    proc = subprocess.run([*QRADAR, "run", "--scene", "walker", "--frames", "40", "--track",
                           "--json", "--record", str(path)], capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    s = json.loads(proc.stdout)
    # (a frame the driver polled too late on a busy host is a counted drop, the run goes on to 40, so the
    # drops are not bounded here: the drops' own tests are test_run_sensor's and test_faults')
    assert s["frames_targets"] == 40
    assert s["tracks"]["messages"] == 40 and s["tracks"]["last_track_id"] == {"kmd2-0": 2}
    assert s["tracks"]["static_track_error_m"]["median"] < 0.3  # the reflector at 20 m, from when it is static
    f = McapFile(path)
    tracks = [(ch, m) for ch, m in f.messages() if ch.topic == "radar/kmd2-0/tracks"]
    assert len(tracks) == 40
    schema = f.schemas[tracks[0][0].schema_id]
    msgs = [decode_tracks(m.data, ch.topic) for ch, m in tracks]
    assert sorted(m.seq for m in msgs) == list(range(40))
    assert {len(m.tracks) for m in msgs[10:]} == {2}  # the walker and the reflector, from confirmation on
    assert schema.name == "qradar.Tracks" and json.loads(schema.data)["required"][-1] == "tracks"
    rp = subprocess.run([*QRADAR, "replay", str(path), "--fast", "--replay-prefix", "replay"],
                        capture_output=True, text=True, timeout=120)
    assert rp.returncode == 0, rp.stderr
    out = json.loads(rp.stdout.strip().splitlines()[-1])
    assert out["published"] >= 4 * 40  # raw, quantized, targets and tracks


def test_reprocess_track_integrates_the_chamber_recording(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    from replay.mcapio import McapFile

    chamber = Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap"
    out = tmp_path / "rp"
    proc = subprocess.run([*QRADAR, "reprocess", str(chamber), "--alpha", "0.45", "--track",
                           "--out", str(out), "--mcap", str(tmp_path / "re.mcap"), "--quiet"],
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    t = json.loads((out / "results.json").read_text())["tracks"]
    assert t["track_ids"] == [1, 2] and t["refinements"] > 0 and t["integrate_s"] == 1.0
    # the static reflectors after 1 s of integration: several times sharper than a frame's targets
    assert t["static_track_error_median_m"] < 0.5 * t["target_error_median_m"]
    assert "tracks: ids [1, 2]" in proc.stdout
    recorded = [decode_tracks(m.data) for ch, m in McapFile(tmp_path / "re.mcap").messages()
                if ch.topic.endswith("/tracks")]
    assert len(recorded) == 106 and all(len(m.tracks) == 2 for m in recorded[10:])


def test_tracker_state_expires_with_its_sensor(bus, zenoh_session):
    """A localizer with tracks forgets a sensor's tracks when it forgets the sensor
    (silent for its sensor expiry), through the real node and bus."""
    import time

    import zenoh
    from zenoh_helpers import Collector, wait_until

    from pipeline.nodes.stream import LocalizeNode, LocalizerConfig
    from pipeline.dsp.quantize import sensor_dither_seed
    from pipeline.wire import encode_quantized_batch

    n = 10
    scene, frames = _scene_frames("walker", n)
    q = quantize_frames(frames, QuantizerConfig(), np.arange(n, dtype=np.uint64),
                        dither_seed=sensor_dither_seed(0, "exp0"))
    headers = FrameHeaders(["exp0"] * n, np.arange(n, dtype=np.uint64),
                           time.time_ns() + np.arange(n, dtype=np.int64) * PERIOD_NS,
                           np.full(n, scene.radar.config_id(), dtype=np.uint32))
    col = Collector(zenoh_session, "radar/exp0/tracks")
    node = LocalizeNode(bus, LocalizerConfig(k=2), session=zenoh_session, tracking=TrackerConfig(),
                        sensor_expiry_s=0.5, health_period_s=0.1).start()
    try:
        pub = zenoh_session.declare_publisher("radar/exp0/quantized", congestion_control=zenoh.CongestionControl.BLOCK)
        for p in encode_quantized_batch(headers, q):
            pub.put(p)
        wait_until(lambda: len(col.of("exp0/tracks")) == n, 20, f"{n} tracks messages")
        assert node.tracker.sensors == ["exp0"] and len(node.tracker.state("exp0").ids) >= 2
        wait_until(lambda: node.tracker.sensors == [], 10, "the silent sensor's tracks forgotten")
    finally:
        node.stop()
    assert node.sensors_expired == 1


# -- the Monte Carlo in time ---------------------------------------------------------------------------
def test_time_monte_carlo_error_falls_with_the_frames():
    from pipeline.dsp.integrate import time_monte_carlo

    r = time_monte_carlo(24, (1, 4, 16), 0.0, seed=3)
    assert r["T"] == [1, 4, 16] and r["runs"] == 24
    assert r["median_m"][2] < 0.25 * r["median_m"][0] and r["slope"] < -0.6
    assert time_monte_carlo(24, (16, 1, 4, 4), 0.0, seed=3) == r  # T in order, once each: the same curve
    with pytest.raises(ParameterError, match="noise_sigma"):
        time_monte_carlo(2, (1,), float("nan"))
    with pytest.raises(ParameterError, match="runs"):
        time_monte_carlo(0, (1,))


def test_cli_montecarlo_time_writes_its_curve(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "mct"
    proc = subprocess.run([*QRADAR, "montecarlo-time", "--runs", "6", "--frames", "1", "8",
                           "--noise-sigma", "0", "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    res = json.loads((out / "time.json").read_text())
    assert len(res) == 1 and res[0]["T"] == [1, 8] and res[0]["median_m"][1] < res[0]["median_m"][0]
    assert (out / "time.png").read_bytes()[:4] == b"\x89PNG" and "slope" in proc.stdout
    bad = subprocess.run([*QRADAR, "montecarlo-time", "--out", "/proc/qradar"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1].startswith("qradar montecarlo-time: error: ")
