import subprocess

import pytest

from radar_driver.errors import ConfigError
from radar_driver.scene import load_scene, packaged_scenes, resolve_scene
from radar_driver.simulator import SimFaults
from zenoh_helpers import QRADAR


def test_packaged_scenes_load():
    assert {"chamber", "single"} <= set(packaged_scenes())
    chamber = resolve_scene("chamber")
    ranges = sorted(t.range_m for t in chamber.targets)
    assert len(chamber.targets) == 2 and ranges == [4.87, 9.23]  # off the 0.6 m range grid, as real reflectors
    close, far = sorted(chamber.targets, key=lambda t: t.range_m)
    assert far.range_m > close.range_m and close.amplitude / far.amplitude == pytest.approx(0.15)
    assert chamber.noise_std > 0


def test_moving_target_and_ramp(rng):
    walker = resolve_scene("walker")
    mover = next(t for t in walker.targets if t.velocity_m_s)
    assert mover.range_at(2.0) == pytest.approx(mover.range_m + 2.0 * mover.velocity_m_s)
    ramp = walker.ramp(0.0, rng)
    assert ramp.shape == (256, 2)
    assert walker.truth(2.0)[0]["range_m"] == pytest.approx(6.0)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("noise_std = 0.1\n[[target]]\nrange_m = 3\nangle_deg = 0\n", "target 1: missing amplitude"),
        ("[[target]]\nrange_m = 3\nangle_deg = 120\namplitude = 0.2\n", "target 1: angle_deg: 120 is outside"),
        ("[[target]]\nrange_m = 'far'\nangle_deg = 0\namplitude = 0.2\n", "range_m: 'far' is not a finite number"),
        ("[[target]]\nrange_m = 3\nangle_deg = 0\namplitude = 0.2\ncolour = 'red'\n", "unknown keys \\['colour'\\]"),
        ("noise = 0.1\n", "unknown keys \\['noise'\\]"),
        ("[radar]\nramps_per_frame = 0\n", "\\[radar\\]: RadarConfig.ramps_per_frame=0"),
        ("[[target]\nrange_m = 3\n", "not valid TOML"),
        ("noise_std = -1\n", "noise_std: -1 is outside"),
    ],
)
def test_bad_scene_file_gives_a_clear_error(tmp_path, text, fragment):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=fragment) as info:
        load_scene(path)
    assert str(path) in str(info.value)


def test_missing_scene(tmp_path):
    with pytest.raises(ConfigError, match="cannot read scene file"):
        load_scene(tmp_path / "none.toml")
    with pytest.raises(ConfigError, match="no packaged scene of that name"):
        resolve_scene("atlantis")


def test_bad_faults():
    with pytest.raises(ConfigError, match="garbage_prob"):
        SimFaults(garbage_prob=2.0)
    with pytest.raises(ConfigError, match="disconnect_after_frames"):
        SimFaults(disconnect_after_frames=0)


def test_cli_sim_rejects_a_bad_scene(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[[target]]\nrange_m = -3\nangle_deg = 0\namplitude = 1\n")
    proc = subprocess.run([*QRADAR, "sim", "--scene", str(path), "--link",
                           str(tmp_path / "x")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "qradar sim: error:" in proc.stderr and "range_m: -3 is outside" in proc.stderr


def test_a_scene_that_changes_what_a_k_md2_measures_is_refused_by_its_simulator(tmp_path):
    """A scene's [radar] bandwidth_hz: the simulated K-MD2 sent frames of that bandwidth under
    the K-MD2's radar config id, and every one was refused downstream for an unknown id. Now
    the simulator refuses the scene in one line naming the field and the sensor's value."""
    from dataclasses import replace

    from radar_driver.errors import ConfigError
    from radar_driver.scene import resolve_scene
    from radar_driver.simulator import SimulatorServer

    chamber = resolve_scene("chamber-ideal")
    for field, value in (("bandwidth_hz", 500e6), ("f0_hz", 77e9)):
        scene = replace(chamber, radar=replace(chamber.radar, **{field: value}))
        with pytest.raises(ConfigError, match=rf"the scene's \[radar\] {field} = .* is not what a simulated K-MD2 "
                                              rf"measures \(profile kmd2-blocks: {field} = "):
            SimulatorServer(scene, link_path=tmp_path / "kmd2")


def test_an_empty_scene_file_and_a_target_given_twice_are_refused(tmp_path):
    """An empty file as --scene ran a scene of nothing (no noise either) under the file's name;
    two targets at one range and angle ran as one reflector of twice the amplitude, scored as a
    miss and a false target. Each is one line now; a room without targets is still a scene."""
    empty, twice, room = tmp_path / "empty.toml", tmp_path / "twice.toml", tmp_path / "room.toml"
    empty.write_text("")
    target = "[[target]]\nrange_m = 5.0\nangle_deg = 10.0\namplitude = 0.5\n"
    twice.write_text(target + "\n" + target)
    room.write_text("noise_std = 0.01\n")
    with pytest.raises(ConfigError, match="empty.toml: holds no scene"):
        load_scene(empty)
    with pytest.raises(ConfigError, match="twice.toml: targets 1 and 2 stand at the same range and angle"):
        load_scene(twice)
    assert load_scene(room).targets == ()
