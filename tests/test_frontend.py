"""The receiver front end of the simulated sensor (radar_driver/frontend.py, a scene's
[frontend] table): the chain against frames computed by hand, the scene files and their
refusals, what each impairment does to the range profile and the angle, ``--empty``, and
the simulated K-MD2 over a real pty emitting impaired frames."""

import json
import subprocess

import numpy as np
import pytest
from numpy.testing import assert_allclose

from pipeline.dsp.localize import back_project, localize
from radar_driver.errors import ConfigError, InputError
from radar_driver.frontend import FRONTEND_KEYS, FrontEnd
from radar_driver.model import RadarConfig, angle_from_antennas_rad, simulate_frames
from radar_driver.scene import SimScene, SimTarget, load_scene, resolve_scene, scene_from_dict
from radar_driver.session import SensorSession, SessionConfig
from radar_driver.simulator import SimulatorServer
from radar_driver.source import SimSourceConfig, SimulatedSource
from zenoh_helpers import QRADAR, RUNTIME_DECODER, wait_until

C = 3e8
LSB = np.sqrt(2) * 0.5 / 2048 * 1.001  # half an ADC step on I and Q
TINY = RadarConfig(samples_per_ramp=4, ramps_per_frame=2)  # M = 8: dR = 0.6 m, R_max = 2.4 m
ALL = FrontEnd(dc_offset=((0.03, -0.02), (-0.025, 0.035)), leakage_amplitude=0.3, leakage_range_m=0.15,
               leakage_phase_deg=40.0, rx2_gain_db=1.0, rx2_phase_deg=30.0, iq_gain_db=0.5, iq_phase_deg=3.0)
ALONE = {
    "dc": FrontEnd(dc_offset=ALL.dc_offset),
    "leakage": FrontEnd(leakage_amplitude=0.3, leakage_range_m=0.15, leakage_phase_deg=40.0),
    "rx2": FrontEnd(rx2_gain_db=1.0, rx2_phase_deg=30.0),
    "iq": FrontEnd(iq_gain_db=0.5, iq_phase_deg=3.0),
    "all": ALL,
}


# -- the chain, by hand ------------------------------------------------------------------------
def hand_targets(cfg: RadarConfig, range_m: float, angle_deg: float, amplitude: complex) -> np.ndarray:
    """Gamma (M, 2) of one target, eq. 2 written out: f_m = f0 + B (m mod N) / N,
    Gamma_1 = x exp(-i 4 pi f_m R / c), Gamma_2 = Gamma_1 exp(+i pi sin(theta)) (d = lambda / 2)."""
    m = np.arange(cfg.n_measurements)
    f = 24e9 + 250e6 * (m % cfg.samples_per_ramp) / cfg.samples_per_ramp
    g1 = amplitude * np.exp(-1j * 4 * np.pi * f * range_m / C)
    return np.stack([g1, g1 * np.exp(1j * np.pi * np.sin(np.deg2rad(angle_deg)))], axis=-1)


def hand_chain(gamma: np.ndarray, fe: FrontEnd, n: int) -> np.ndarray:
    """The front end in real arithmetic, step by step (not the implementation's mu / nu form),
    on a frame (M, 2) of whole ramps of ``n`` samples."""
    m = np.arange(gamma.shape[0])
    f = 24e9 + 250e6 * (m % n) / n
    phase_l = np.deg2rad(fe.leakage_phase_deg) - 4 * np.pi * f * fe.leakage_range_m / C
    leak = fe.leakage_amplitude * (np.cos(phase_l) + 1j * np.sin(phase_l))
    s = gamma + leak[:, None]  # the same on both receivers
    g2, p2 = 10 ** (fe.rx2_gain_db / 20), np.deg2rad(fe.rx2_phase_deg)
    r = s.copy()
    r[:, 1] = g2 * (np.cos(p2) + 1j * np.sin(p2)) * s[:, 1]
    g, phi = 10 ** (fe.iq_gain_db / 20), np.deg2rad(fe.iq_phase_deg)
    i, q = r.real, r.imag
    i2, q2 = i, g * (q * np.cos(phi) - i * np.sin(phi))  # I' = I, Q' = g (Q cos phi - I sin phi)
    (di1, dq1), (di2, dq2) = fe.dc_offset
    return (i2 + np.array([di1, di2])) + 1j * (q2 + np.array([dq1, dq2]))


def test_the_targets_by_hand_are_the_model():
    x = 0.5 * np.exp(1j * np.deg2rad(30))
    assert_allclose(simulate_frames([1.0], [20.0], [x], TINY)[0], hand_targets(TINY, 1.0, 20.0, x), atol=1e-12)


@pytest.mark.parametrize("which", list(ALONE))
def test_each_impairment_alone_and_all_together_against_a_frame_by_hand(which):
    fe = ALONE[which]
    gamma = hand_targets(TINY, 1.0, 20.0, 0.5 * np.exp(1j * np.deg2rad(30)))
    expected = hand_chain(gamma, fe, 4)
    got = fe.apply(gamma, TINY)  # one frame (M, 2)
    assert got.shape == (8, 2) and got.dtype == np.complex128
    assert_allclose(got, expected, atol=1e-12)
    assert np.abs(got - gamma).max() > 1e-3  # each one changes the frame
    assert_allclose(fe.apply(gamma[None], TINY)[0], expected, atol=1e-12)  # a batch of one


def test_a_worked_sample_of_the_i_q_imbalance():
    """One sample, by hand: r = 0.3 + 0.4i, g = 10^(0.5/20) = 1.0592537, phi = 3 deg:
    I' = 0.3, Q' = 1.0592537 (0.4 x 0.9986295 - 0.3 x 0.0523360) = 1.0592537 x 0.3837510 = 0.4064897."""
    one = RadarConfig(samples_per_ramp=1, ramps_per_frame=1)
    y = FrontEnd(iq_gain_db=0.5, iq_phase_deg=3.0).apply(np.array([[0.3 + 0.4j, 0.3 + 0.4j]]), one)
    assert_allclose(y[0], [0.3 + 0.4064897j] * 2, atol=1e-7)


def test_a_batch_is_each_frame_alone_and_the_input_is_kept():
    rng = np.random.default_rng(3)
    batch = simulate_frames(rng.uniform(0, 2.3, (3, 2)), rng.uniform(-60, 60, (3, 2)),
                            rng.uniform(0.1, 0.4, (3, 2)) * np.exp(2j * np.pi * rng.random((3, 2))), TINY)
    before = batch.copy()
    out = ALL.apply(batch, TINY)
    assert out.shape == (3, 8, 2)
    for b in range(3):
        assert_allclose(out[b], hand_chain(batch[b], ALL, 4), atol=1e-12)
    np.testing.assert_array_equal(batch, before)
    ideal = FrontEnd().apply(batch, TINY)
    np.testing.assert_array_equal(ideal, batch)
    assert ideal is not batch


def test_a_frequency_subset_takes_its_leakage_at_its_frequencies():
    fe = ALONE["leakage"]
    idx = np.array([3, 0, 2])
    f = 24e9 + 250e6 * idx / 4
    expected = 0.3 * np.exp(1j * (np.deg2rad(40) - 4 * np.pi * f * 0.15 / C))
    out = fe.apply(np.zeros((1, 3, 2), complex), TINY, indices=idx)
    assert_allclose(out[0], np.stack([expected, expected], axis=-1), atol=1e-12)
    with pytest.raises(InputError, match="multiple of 4"):
        fe.apply(np.zeros((1, 6, 2)), TINY)
    with pytest.raises(InputError, match="shape"):
        fe.apply(np.zeros((8, 3)), TINY)


def test_the_scene_ramps_are_the_targets_through_the_front_end(rng):
    scene = SimScene((SimTarget(1.0, 20.0, 0.5, phase_deg=30.0),), noise_std=0.0, radar=TINY, front_end=ALL)
    ramps = scene.clean_ramps([0.0, 1.0])
    assert ramps.shape == (2, 4, 2)
    gamma = hand_targets(TINY, 1.0, 20.0, 0.5 * np.exp(1j * np.deg2rad(30)))
    assert_allclose(ramps[0], hand_chain(gamma, ALL, 4)[:4], atol=1e-12)
    assert_allclose(scene.target_ramps(0.0)[0], gamma[:4], atol=1e-12)
    noisy = SimScene(scene.targets, noise_std=0.05, radar=TINY, front_end=ALL)
    r1 = noisy.ramps([0.0], np.random.default_rng(1))
    assert_allclose(r1, scene.clean_ramps([0.0]) + noisy.noise(1, np.random.default_rng(1)), atol=1e-12)


def test_image_rejection_ratio_is_the_textbook_one():
    g, phi = 10 ** (0.5 / 20), np.deg2rad(3.0)
    irr_db = 10 * np.log10((1 + g * g + 2 * g * np.cos(phi)) / (1 + g * g - 2 * g * np.cos(phi)))
    fe = FrontEnd(iq_gain_db=0.5, iq_phase_deg=3.0)
    assert fe.image_rejection_db == pytest.approx(irr_db) and fe.image_rejection_db == pytest.approx(28.2, abs=0.05)
    assert FrontEnd().image_rejection_db == np.inf and FrontEnd(rx2_gain_db=3).image_rejection_db == np.inf


# -- what each impairment does to the range profile and the angle ---------------------------------
def profile(frames: np.ndarray, cfg: RadarConfig) -> np.ndarray:
    """Back projection Phi* Z / M, (B, N, 2)."""
    return back_project(np.asarray(frames), cfg)


def test_the_leakage_is_a_return_at_its_range_without_angle(cfg):
    fe = FrontEnd(leakage_amplitude=0.3, leakage_range_m=1.8, leakage_phase_deg=40.0)  # bin 3
    u = profile(fe.apply(np.zeros((1, 512, 2)), cfg), cfg)[0]
    assert np.argmax(np.abs(u[:, 0])) == 3 and np.argmax(np.abs(u[:, 1])) == 3
    assert_allclose(np.abs(u[3]), [0.3, 0.3], atol=1e-12)
    assert np.abs(np.delete(u, 3, axis=0)).max() < 1e-12  # on the grid: nothing elsewhere
    assert angle_from_antennas_rad(u[3, 0], u[3, 1], cfg) == pytest.approx(0.0, abs=1e-12)  # same phase
    skewed = profile(FrontEnd(leakage_amplitude=0.3, leakage_range_m=1.8, rx2_phase_deg=30.0).apply(
        np.zeros((1, 512, 2)), cfg), cfg)[0]
    assert np.rad2deg(angle_from_antennas_rad(skewed[3, 0], skewed[3, 1], cfg)) == pytest.approx(
        np.rad2deg(np.arcsin(30 / 180)))  # through receiver 2's phase like a target at boresight


def test_the_chamber_leakage_and_dc_are_the_strongest_thing_in_range_bin_0():
    chamber = resolve_scene("chamber")
    frame = np.tile(chamber.clean_ramp(0.0), (2, 1))[None]
    u = profile(frame, chamber.radar)[0]
    energy = np.sqrt((np.abs(u) ** 2).sum(axis=1))
    assert np.argmax(energy) == 0  # 0.15 m: bin 0.25
    strong = max(chamber.targets, key=lambda t: t.amplitude)
    assert energy[0] > energy[round(strong.range_m / 0.6)]
    ideal = profile(np.tile(resolve_scene("chamber-ideal").clean_ramp(0.0), (2, 1))[None], chamber.radar)[0]
    assert np.sqrt((np.abs(ideal[0]) ** 2).sum()) < 0.1 * energy[0]


@pytest.mark.parametrize("angle_deg", [-10.0, 25.0])
def test_the_i_q_ghost_sits_at_the_mirrored_bin_at_minus_the_image_rejection(cfg, angle_deg):
    fe = FrontEnd(iq_gain_db=0.5, iq_phase_deg=3.0)
    n = 20  # 12 m, on the grid; its ghost at N - n = 236 (141.6 m)
    u = profile(fe.apply(simulate_frames([12.0], [angle_deg], [0.5], cfg), cfg), cfg)[0]
    level_db = 20 * np.log10(np.abs(u[256 - n]) / np.abs(u[n]))
    assert_allclose(level_db, [-fe.image_rejection_db] * 2, atol=1e-9)  # -28.2 dB on both receivers
    mu, nu = fe.iq_coefficients
    assert_allclose(np.abs(u[256 - n]), [abs(nu) * 0.5] * 2, atol=1e-12)
    others = np.delete(np.abs(u), [n, 256 - n], axis=0)
    assert others.max() < 1e-12
    # the ghost is the conjugate: its phase between the receivers is the target's negated
    ghost_angle = np.rad2deg(angle_from_antennas_rad(u[256 - n, 0], u[256 - n, 1], cfg))
    assert ghost_angle == pytest.approx(-angle_deg)
    assert np.rad2deg(angle_from_antennas_rad(u[n, 0], u[n, 1], cfg)) == pytest.approx(angle_deg, abs=0.5)


@pytest.mark.parametrize("phase_deg", [30.0, -20.0])
def test_receiver_2_phase_skews_the_angle_as_expected(cfg, phase_deg):
    """sin(theta_hat) = sin(theta) + c phi_2 / (2 pi f0 d) = sin(theta) + phi_2 / 180 deg
    at d = lambda / 2: 30 deg of phase is +9.6 deg of angle at boresight."""
    angles = np.array([-40.0, -10.0, 0.0, 25.0, 50.0])
    ranges = np.array([10, 30, 50, 70, 90]) * 0.6  # on the grid
    gamma = simulate_frames(ranges[None], angles[None], np.full((1, 5), 0.2), cfg)
    for fe, expected in [(FrontEnd(rx2_phase_deg=phase_deg),
                          np.rad2deg(np.arcsin(np.sin(np.deg2rad(angles)) + phase_deg / 180))),
                         (FrontEnd(rx2_gain_db=3.0), angles)]:  # a gain alone moves no angle
        det = localize(fe.apply(gamma, cfg), cfg, k=5)
        order = np.argsort(det.range_m[0])
        assert_allclose(det.range_m[0, order], ranges)
        assert_allclose(det.angle_deg[0, order], expected, atol=1e-9)
    if phase_deg == 30.0:
        assert np.rad2deg(np.arcsin(phase_deg / 180)) == pytest.approx(9.59, abs=0.01)


# -- scene files -----------------------------------------------------------------------------------
FULL_TABLE = """
name = "lab"
noise_std = 0.01

[[target]]
range_m = 4.0
angle_deg = 10.0
amplitude = 0.2

[frontend]
dc_offset = [[0.03, -0.02], [-0.025, 0.035]]
leakage_amplitude = 0.3
leakage_range_m = 0.15
leakage_phase_deg = 40
rx2_gain_db = 1.0
rx2_phase_deg = 30.0
iq_gain_db = 0.5
iq_phase_deg = 3
"""


def test_a_frontend_table_loads_and_round_trips(tmp_path):
    path = tmp_path / "lab.toml"
    path.write_text(FULL_TABLE)
    scene = load_scene(path)
    assert scene.front_end == ALL and not scene.front_end.ideal
    assert scene_from_dict(json.loads(json.dumps(scene.to_dict()))) == scene  # as a recording's metadata
    assert set(scene.to_dict()["frontend"]) == set(FRONTEND_KEYS) == {
        "dc_offset", "leakage_amplitude", "leakage_range_m", "leakage_phase_deg", "rx2_gain_db", "rx2_phase_deg",
        "iq_gain_db", "iq_phase_deg"}
    partial = tmp_path / "partial.toml"
    partial.write_text("[frontend]\nrx2_phase_deg = -12\n")
    assert load_scene(partial).front_end == FrontEnd(rx2_phase_deg=-12.0)  # every other key: the ideal sensor
    nothing = tmp_path / "none.toml"
    nothing.write_text("noise_std = 0.0\n")
    assert load_scene(nothing).front_end.ideal
    assert scene_from_dict({"noise_std": 0.1}).front_end.ideal  # a recording made before the front end


@pytest.mark.parametrize(
    "table, fragment",
    [
        ("dc = 0.1", r"\[frontend\]: unknown keys \['dc'\]"),
        ("dc_offset = [0.1, 0.2]", r"\[frontend\]: dc_offset: \[0.1, 0.2\] must be \[\[I1, Q1\], \[I2, Q2\]\]"),
        ("dc_offset = [[0.1, 0.2], [0.3]]", r"dc_offset: .* must be \[\[I1, Q1\], \[I2, Q2\]\]"),
        ("dc_offset = [[0.1, 0.2], [0.3, 1.5]]", r"dc_offset\[1\]\[1\]: 1.5 is outside \[-1.0, 1.0\]"),
        ("dc_offset = [[0.1, 'x'], [0.3, 0.1]]", r"dc_offset\[0\]\[1\]: 'x' is not a finite number"),
        ("leakage_amplitude = -0.1", r"leakage_amplitude: -0.1 is outside \[0.0, 1.0\]"),
        ("leakage_range_m = 200.0", r"\[frontend\]: leakage_range_m: 200.0 is outside \[0, 153.6\)"),
        ("leakage_range_m = -1", r"leakage_range_m: -1 is outside \[0.0, inf\)"),
        ("leakage_phase_deg = 'north'", r"leakage_phase_deg: 'north' is not a finite number"),
        ("rx2_gain_db = true", r"rx2_gain_db: True is not a finite number"),
        ("rx2_phase_deg = nan", r"rx2_phase_deg: nan is not a finite number"),
        ("iq_gain_db = 30", r"iq_gain_db: 30 is outside \[-20.0, 20.0\]"),
        ("iq_phase_deg = 60", r"iq_phase_deg: 60 is outside \[-45.0, 45.0\]"),
    ],
)
def test_a_bad_frontend_table_is_refused_naming_the_file_and_the_key(tmp_path, table, fragment):
    path = tmp_path / "bad.toml"
    path.write_text(f"[frontend]\n{table}\n")
    with pytest.raises(ConfigError, match=fragment) as info:
        load_scene(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: [frontend]") and "\n" not in msg


def test_frontend_must_be_a_table(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("frontend = 3\n")
    with pytest.raises(ConfigError, match=r"bad.toml: \[frontend\]: must be a table"):
        load_scene(path)


def test_the_packaged_chambers_hold_the_documented_assumptions():
    chamber, ideal = resolve_scene("chamber"), resolve_scene("chamber-ideal")
    assert ideal.front_end.ideal and ideal.targets == chamber.targets and ideal.noise_std == chamber.noise_std
    fe = chamber.front_end
    assert all(0.01 <= abs(v) <= 0.05 for pair in fe.dc_offset for v in pair)  # a few % of full scale
    assert 0.1 <= fe.leakage_range_m <= 0.3
    assert fe.leakage_amplitude > max(t.amplitude for t in chamber.targets)  # stronger than any target
    assert 10 <= abs(fe.rx2_phase_deg) <= 60 and 0.5 <= abs(fe.rx2_gain_db) <= 2
    assert fe.iq_gain_db == 0.5 and fe.iq_phase_deg == 3.0
    # it all fits the ADC: the noiseless peak leaves 5 noise stds of headroom
    ramp = chamber.clean_ramp(0.0)
    peak = max(np.abs(ramp.real).max(), np.abs(ramp.imag).max())
    assert peak + 5 * chamber.noise_std < 1.0


# -- the empty chamber ------------------------------------------------------------------------------
def test_the_empty_scene_is_the_front_end_alone():
    chamber = resolve_scene("chamber")
    empty = chamber.without_targets()
    assert empty.targets == () and empty.name == "chamber-empty" and empty.front_end == chamber.front_end
    assert empty.noise_std == chamber.noise_std and empty.truth() == []
    ramp = empty.clean_ramp(0.0)
    assert_allclose(ramp, hand_chain(np.zeros((256, 2), complex), chamber.front_end, 256), atol=1e-12)


def test_cli_sim_empty_serves_frames_without_targets(tmp_path):
    """qradar sim --empty over a real pty: the frames are the front end and the noise only."""
    link, out = tmp_path / "kmd2", tmp_path / "empty.npz"
    sim = subprocess.Popen([*QRADAR, "sim", "--scene", "chamber", "--empty", "--link",
                            str(link), "--rate", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_until(link.exists, 20, f"{link} to appear")
        drive = subprocess.run([*QRADAR, "drive", "--port", str(link), "--frames", "20",
                                "--json", "--no-publish", "--quiet", "--out", str(out)],
                               capture_output=True, text=True, timeout=120)
        assert drive.returncode == 0, drive.stderr
    finally:
        sim.terminate()
        sim.wait(10)
    assert "chamber-empty, 0 targets" in sim.stdout.read()
    frames = np.load(out)["frames"]
    chamber = resolve_scene("chamber")
    front_end_only = np.tile(chamber.without_targets().clean_ramp(0.0), (2, 1))
    resid = frames - front_end_only
    assert np.std(resid.real) == pytest.approx(chamber.noise_std, rel=0.05)  # nothing but noise left
    assert np.abs(resid.mean(axis=0)).max() < 5 * chamber.noise_std / np.sqrt(len(frames))
    with_targets = np.tile(chamber.clean_ramp(0.0), (2, 1))
    assert np.abs(frames.mean(axis=0) - with_targets).max() > 0.2  # the reflectors are not there
    u = profile(frames, chamber.radar).mean(axis=0)
    energy = np.sqrt((np.abs(u) ** 2).sum(axis=1))
    assert np.argmax(energy) == 0
    for t in chamber.targets:  # at the reflectors' bins: the leakage's sidelobes and noise, far below them
        assert energy[round(t.range_m / 0.6)] < 0.5 * t.amplitude


def test_cli_run_empty_reports_no_truth(tmp_path):
    proc = subprocess.run([*QRADAR, "run", *RUNTIME_DECODER, "--empty", "--frames", "10", "--no-record",
                           "--json", "--driver-in-process"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    s = json.loads(proc.stdout.strip().splitlines()[-1])
    assert s["scene"] == "chamber-empty" and s["frames_targets"] >= 10
    assert s["position_error_m"] == {"median": None, "mean": None, "p90": None}  # no target to compare with
    assert s["localizer"]["K"] == 1


# -- the simulated K-MD2 over a real pty --------------------------------------------------------------
def test_the_simulated_kmd2_emits_impaired_frames_over_a_pty(tmp_path):
    """Noiseless: every frame is the hand-computed chain within the ADC's half step."""
    cfg = RadarConfig()
    scene = SimScene((SimTarget(9.0, 15.0, 0.24), SimTarget(4.8, -20.0, 0.05, phase_deg=30.0)), radar=cfg,
                     front_end=ALL, name="impaired")
    with SimulatorServer(scene, link_path=tmp_path / "kmd2", rate_hz=0) as sim, \
            SensorSession(SessionConfig(str(tmp_path / "kmd2"), reconnect_timeout_s=5.0)) as s:
        frames = list(s.frames(5))
    assert not sim.errors
    gamma = (hand_targets(cfg, 9.0, 15.0, 0.24)
             + hand_targets(cfg, 4.8, -20.0, 0.05 * np.exp(1j * np.deg2rad(30))))
    expected = hand_chain(gamma, ALL, 256)
    for f in frames:
        assert np.abs(f.data - expected).max() <= LSB
        assert np.abs(f.data - gamma).max() > 0.2  # not the paper's model


def test_the_packaged_chamber_over_a_pty_is_the_in_process_sensor_and_shows_the_front_end(tmp_path):
    chamber = resolve_scene("chamber")
    with SimulatorServer(chamber, link_path=tmp_path / "kmd2", rate_hz=0, seed=4) as sim, \
            SensorSession(SessionConfig(str(tmp_path / "kmd2"), reconnect_timeout_s=5.0)) as s:
        frames = list(s.frames(8))
    assert not sim.errors
    with SimulatedSource(SimSourceConfig(chamber, rate_hz=0, seed=4, frames=8)) as src:
        same = list(src.frames())
    for f, e in zip(frames, same, strict=True):
        np.testing.assert_array_equal(f.data, e.data)  # the front end in both, noise included
    z = np.stack([f.data for f in frames])
    det = localize(z, chamber.radar, k=2)
    assert np.all(det.bin[:, 0] == 0)  # the leakage outshines every reflector
    strong = max(chamber.targets, key=lambda t: t.amplitude)
    at_strong = np.abs(det.range_m[:, 1] - strong.range_m) <= 0.6
    assert at_strong.all()
    expected = np.rad2deg(np.arcsin(np.sin(np.deg2rad(strong.angle_deg)) + chamber.front_end.rx2_phase_deg / 180))
    assert np.all(np.abs(det.angle_deg[:, 1] - expected) < 2.0), det.angle_deg[:, 1]  # skewed by about +10 deg
    assert np.all(det.angle_deg[:, 1] - strong.angle_deg > 7.0)
