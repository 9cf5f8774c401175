"""Sensor profiles: the two shipped ones load and validate, bad files fail with one line
naming the key, and the cube profile's chirp selection builds frames of M = R x 256."""

import numpy as np
import pytest

from radar_driver.errors import ConfigError
from radar_driver.model import RadarConfig, simulate_frames
from radar_driver.profile import (
    DEFAULT_PROFILE,
    PROFILES_DIR,
    load_profile,
    packaged_profiles,
    profile_from_dict,
    resolve_profile,
)
from radar_driver.scene import SimScene, SimTarget
from radar_driver.session import SensorSession, SessionConfig
from radar_driver.simulator import SimulatorServer

LSB = np.sqrt(2) * 0.5 / 2048 * 1.001


def test_two_profiles_ship_and_the_default_is_the_original_layout():
    assert packaged_profiles() == ["kmd2-blocks", "kmd2-cube256"]
    assert DEFAULT_PROFILE.name == "kmd2-blocks"
    lay = DEFAULT_PROFILE.radc
    assert (lay.receivers, lay.chirps, lay.samples, lay.order, lay.payload_len) == (2, 1, 256, "blocks", 2048)
    cube = resolve_profile("kmd2-cube256").radc
    assert (cube.receivers, cube.chirps, cube.samples, cube.order, cube.payload_len) == (3, 256, 256, "interleaved",
                                                                                         786_432)
    assert DEFAULT_PROFILE.baud_codes == {0: 115_200, 1: 460_800, 2: 921_600, 3: 2_000_000, 4: 3_000_000}
    assert DEFAULT_PROFILE.gnfd_bits["RADC"] == 1 and DEFAULT_PROFILE.startup_baud == 115_200
    assert resolve_profile(PROFILES_DIR / "kmd2-cube256.toml").name == "kmd2-cube256"


def _dict(**radc):
    return {"name": "t", "radc": {"receivers": 2, "chirps": 1, "samples": 256, **radc}}


@pytest.mark.parametrize("change, fragment", [
    (_dict(order="zigzag"), r"radc.order='zigzag' must be one of \['blocks', 'interleaved'\]"),
    (_dict(word="float32"), "radc.word='float32' must be one of"),
    (_dict(azimuth=[0, 0]), "radc.azimuth=.* must be two different receiver indices"),
    (_dict(azimuth=[0, 2]), "radc.azimuth=.* in \\[0, 2\\)"),
    (_dict(adc_bits=12, offset=5000), "radc.offset=5000 must be an integer code in \\[0, 4095\\]"),
    (_dict(chirps=0), "radc.chirps=0 must be an integer >= 1"),
    (_dict(colour="red"), "\\[radc\\] has unknown keys \\['colour'\\]"),
    ({"name": "t", "baud_codes": {"0": 9600}}, "startup_baud=115200 must be one of the baud codes' speeds"),
    ({"name": "t", "gnfd_bits": {"RADC": 3}}, "gnfd_bits.RADC=3 must be one bit"),
    ({"name": "t", "lengths": {"DONE": [4, 4]}}, "the length of DONE is fixed by the protocol"),
    ({"name": "t", "lengths": {"PDAT": [9, 1]}}, "lengths.PDAT=\\[9, 1\\] must be \\[min, max\\]"),
    ({"name": "t", "speed": 3}, "unknown keys \\['speed'\\]"),
    ({"radc": {}}, "missing name"),
])
def test_bad_profiles_fail_with_one_line_naming_the_key(change, fragment):
    with pytest.raises(ConfigError, match=fragment) as info:
        profile_from_dict(change, "test.toml")
    assert "\n" not in str(info.value) and "test.toml" in str(info.value)


def test_bad_files_and_names(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("name = \n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        load_profile(bad)
    with pytest.raises(ConfigError, match="no packaged profile of that name; packaged: \\['kmd2-blocks'"):
        resolve_profile("kmd2-nope")


def test_a_copied_profile_with_another_word_format_round_trips(tmp_path):
    text = (PROFILES_DIR / "kmd2-blocks.toml").read_text().replace('word = "uint16le"', 'word = "int16le"')
    text = text.replace("offset = 2048", "offset = 0").replace('name = "kmd2-blocks"', 'name = "signed"')
    path = tmp_path / "signed.toml"
    path.write_text(text)
    lay = load_profile(path).radc
    assert (lay.min_word, lay.max_word, lay.full_scale) == (-2048, 2047, 2048.0)
    x = np.random.default_rng(0).uniform(-0.9, 0.9, (1, 256, 2)) * np.exp(0.3j)
    words = lay.from_complex(x)
    assert np.abs(lay.to_complex(lay.words_from_payload(lay.payload_from_words(words))) - x).max() <= LSB


def test_chirp_selection():
    cube = resolve_profile("kmd2-cube256").radc
    assert cube.chirp_indices(2, "first").tolist() == [0, 1]
    assert cube.chirp_indices(4, "stride").tolist() == [0, 64, 128, 192]
    with pytest.raises(ConfigError, match="a frame of 300 ramps needs 300 chirps; a RADC of this profile has 256"):
        cube.chirp_indices(300)
    with pytest.raises(ConfigError, match="chirp_select='odd' must be one of"):
        SessionConfig("/dev/null", profile="kmd2-cube256", chirp_select="odd")


@pytest.mark.parametrize("select", ["first", "stride"])
def test_cube_frames_of_four_chirps_equal_the_model(tmp_path, select):
    radar = RadarConfig(ramps_per_frame=4)
    scene = SimScene((SimTarget(12.0, 20.0, 0.5), SimTarget(4.8, -35.0, 0.1, phase_deg=40.0)), radar=radar)
    link = tmp_path / "kmd2"
    with SimulatorServer(scene, link_path=link, rate_hz=0, profile=resolve_profile("kmd2-cube256")) as sim:
        with SensorSession(SessionConfig(str(link), ramps_per_frame=4, profile="kmd2-cube256",
                                         chirp_select=select, reconnect_timeout_s=5.0)) as s:
            frames = list(s.frames(3))
    assert not sim.errors
    gamma = simulate_frames(*scene.arrays(), radar)[0]
    for i, f in enumerate(frames):
        assert f.data.shape == (1024, 2) and f.counters == (i,)
        assert np.abs(f.data - gamma).max() <= LSB
    assert s.counters.frames == 3 and s.counters.dropped == 0 and s.counters.ramps == 3


def test_each_profile_gives_its_ramp_spacing_and_the_simulated_sensor_measures_on_it():
    """The driver's radar configuration of a profile's frames (its id on every frame) has the
    profile's ramp spacing, and the simulated K-MD2 measures its chirps on the same times:
    kmd2-blocks, one chirp a RADC, a frame's two RADCs 25 ms apart (V = 0.249 m/s);
    kmd2-cube256, 256 chirps a RADC 1/5120 s apart, a frame the first two (V = 32 m/s)."""
    import math

    from radar_driver.errors import ConfigError
    from radar_driver.scene import SimScene, SimTarget
    from radar_driver.simulator import SimulatedKMD2

    blocks, cube = resolve_profile("kmd2-blocks"), resolve_profile("kmd2-cube256")
    assert blocks.radar(2).ramp_interval_s == 0.025 and blocks.radar(2).config_id() == RadarConfig().config_id()
    assert cube.radar(2).ramp_interval_s == 1 / 5120
    assert cube.radar(2, "stride").ramp_interval_s == 128 / 5120
    assert math.isclose(blocks.radar(2).velocity_ambiguity_mps, 0.2487, rel_tol=1e-3)
    assert math.isclose(cube.radar(2).velocity_ambiguity_mps, 31.83, rel_tol=1e-3)
    scene = SimScene(targets=(SimTarget(range_m=12.0, angle_deg=0.0, amplitude=0.5),))
    SimulatedKMD2(scene, profile=blocks)  # the scene's ramps (25 ms) are the profile's
    other = SimScene(targets=scene.targets, radar=RadarConfig(ramp_interval_s=0.05))
    with pytest.raises(ConfigError, match="ramp_interval_s"):
        SimulatedKMD2(other, profile=blocks)
