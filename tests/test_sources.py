"""One contract for every source of raw frames (radar_driver.source.FrameSource), run
over the three implementations: the serial session talking to a simulated K-MD2 on a
real pseudo-terminal (in each shipped sensor profile), the in-process simulated
sensor, and a recording (an MCAP file written with the real writer and read back)."""

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.wire import RawFrameMsg, encode_raw
from radar_driver.model import simulate_frames
from radar_driver.profile import packaged_profiles, resolve_profile
from radar_driver.scene import SimScene, SimTarget
from radar_driver.session import SensorSession, SessionConfig
from radar_driver.simulator import SimulatorServer
from radar_driver.source import FrameSource, RawFrame, SimSourceConfig, SimulatedSource
from replay.mcapio import McapSink
from replay.source import RecordingSource

LSB = np.sqrt(2) * 0.5 / 2048 * 1.001  # half an ADC step on I and Q
STATIC = SimScene((SimTarget(12.0, 20.0, 0.5), SimTarget(4.8, -35.0, 0.1, phase_deg=40.0)), name="static")
NOISY = SimScene(STATIC.targets, noise_std=0.01, name="noisy")
SEED = 5
PROFILES = packaged_profiles()
KINDS = [f"serial-{p}" for p in PROFILES] + ["in-process", "recording"]


def in_process(scene: SimScene, seed: int, frames: int | None = None) -> SimulatedSource:
    return SimulatedSource(SimSourceConfig(scene, sensors=1, id_prefix="s", rate_hz=0, seed=seed, frames=frames))


def write_recording(path: Path, frames: list[RawFrame], prefix: str = "radar") -> Path:
    sink = McapSink(path, overwrite=True)  # a test may write the same scene twice
    try:
        for f in frames:
            msg = RawFrameMsg(f.sensor_id, f.seq, f.timestamp_ns, f.config_id, f.data)
            sink.write(f"{prefix}/{f.sensor_id}/raw", encode_raw(msg), f.timestamp_ns, f.timestamp_ns, f.seq)
    finally:
        sink.close()
    return path


class Opened:
    """A source of one kind over ``scene`` with ``seed``, and what it needs around it."""

    def __init__(self, kind: str, scene: SimScene, seed: int, tmp_path: Path, n_recorded: int = 12):
        self.kind, self.server = kind, None
        if kind.startswith("serial-"):
            profile = self.profile = resolve_profile(kind.removeprefix("serial-"))
            link = tmp_path / f"kmd2-{scene.name}-{seed}"
            self.server = SimulatorServer(scene, link_path=link, rate_hz=0, seed=seed, profile=profile).start()
            self.source = SensorSession(SessionConfig(str(link), sensor_id="s0", reconnect_timeout_s=5.0,
                                                      profile=profile))
        elif kind == "in-process":
            self.source = in_process(scene, seed)
        else:
            with in_process(scene, seed, frames=n_recorded) as src:
                frames = list(src.frames())
            self.source = RecordingSource(write_recording(tmp_path / f"{scene.name}.mcap", frames))

    def close(self) -> None:
        self.source.close()
        if self.server is not None:
            self.server.stop()
            assert not self.server.errors


@pytest.fixture(params=KINDS)
def opened(request, tmp_path):
    made = []

    def make(scene: SimScene = STATIC, seed: int = SEED, **kw) -> Opened:
        made.append(Opened(request.param, scene, seed, tmp_path, **kw))
        return made[-1]

    make.made = made
    yield make
    for o in made:
        o.close()


def read(source, n: int) -> list[RawFrame]:
    with source:
        return list(source.frames(n))


def test_is_a_frame_source(opened):
    assert isinstance(opened().source, FrameSource)


def opened_profile(opened):
    """The sensor profile of the last source ``opened`` made (None: not a serial sensor's)."""
    return getattr(opened.made[-1], "profile", None)


def test_frames_equal_the_model_within_adc_quantization(opened):
    frames = read(opened().source, 8)
    gamma = simulate_frames(*STATIC.arrays(), STATIC.radar)[0]
    assert len(frames) == 8
    for f in frames:
        assert f.sensor_id == "s0" and f.data.shape == (512, 2) and f.data.dtype == np.complex64
        # a sensor's frames carry its profile's radar (its ramp spacing: the cube's chirps 1/5120 s apart)
        want = opened_profile(opened).radar(STATIC.radar.ramps_per_frame) if opened_profile(opened) else STATIC.radar
        assert f.config_id == want.config_id()
        assert np.abs(f.data - gamma).max() <= LSB


def test_same_scene_and_seed_give_the_same_frames(opened):
    """Noise included: the serial path, the in-process sensor and a recording of it agree
    sample for sample, and another seed gives other noise."""
    frames = read(opened(NOISY, SEED).source, 6)
    with in_process(NOISY, SEED) as ref:
        expected = list(ref.frames(6))
    for f, e in zip(frames, expected, strict=True):
        np.testing.assert_array_equal(f.data, e.data)
    other = read(opened(NOISY, SEED + 1).source, 1)[0]
    assert np.abs(other.data - expected[0].data).max() > 10 * LSB
    gamma = simulate_frames(*NOISY.arrays(), NOISY.radar)[0]
    resid = np.stack([f.data for f in frames]) - gamma
    assert np.std(resid.real) == pytest.approx(NOISY.noise_std, rel=0.1)  # the noise is the scene's


def test_sequence_numbers_and_times_increase(opened):
    frames = read(opened().source, 8)
    assert [f.seq for f in frames] == list(range(8))
    t = [f.timestamp_ns for f in frames]
    assert all(b >= a for a, b in zip(t, t[1:]))
    counters = [c for f in frames for c in f.counters]
    assert counters == sorted(set(counters))  # ramp counters, when the source knows them, increase


def test_counters_count(opened):
    o = opened()
    frames = read(o.source, 7)
    st = o.source.stats()["s0"]
    assert st["frames"] == len(frames) == 7 and st["dropped"] == 0


def test_closing_twice_is_harmless(opened):
    o = opened()
    with o.source as src:
        assert next(iter(src.frames(1))).seq == 0
    o.source.close()
    o.source.close()


def test_request_stop_from_another_thread_ends_the_stream(opened):
    o = opened()
    got = []
    with o.source as src:
        timer = threading.Timer(0.3, src.request_stop)
        timer.start()
        t0 = time.monotonic()
        for f in src.frames():  # endless for serial and in-process; bounded by the stop
            got.append(f)
            if len(got) >= 10_000 or time.monotonic() - t0 > 20:
                break
        timer.cancel()
    assert got and time.monotonic() - t0 < 20, "request_stop did not end the stream"
    if o.kind != "recording":  # a recording of 12 frames may end first, and that is fine too
        assert len(got) < 10_000


def test_a_stop_before_reading_yields_nothing(opened):
    with opened().source as src:
        src.request_stop()
        assert list(src.frames(5)) == []


def test_a_source_that_ends_ends_cleanly(tmp_path):
    with in_process(STATIC, SEED, frames=5) as src:
        frames = list(src.frames())
    assert [f.seq for f in frames] == [0, 1, 2, 3, 4]
    with RecordingSource(write_recording(tmp_path / "r.mcap", frames)) as rec:
        again = list(rec.frames())
        assert [f.seq for f in rec.frames()] == [0, 1, 2, 3, 4]  # reading it again starts over
    assert [f.seq for f in again] == [0, 1, 2, 3, 4] and not rec.truncated


def test_a_recording_counts_sequence_gaps_as_dropped_and_skips_bad_frames(tmp_path):
    with in_process(STATIC, SEED, frames=6) as src:
        frames = list(src.frames())
    kept = [f for f in frames if f.seq not in (2, 3)]
    path = write_recording(tmp_path / "gaps.mcap", kept)
    sink_path = tmp_path / "bad.mcap"
    sink = McapSink(sink_path)
    sink.write("radar/s0/raw", b"QRDR-not-a-frame", 1, 1, 0)
    sink.close()
    with RecordingSource(path) as rec:
        got = list(rec.frames())
    assert [f.seq for f in got] == [0, 1, 4, 5] and rec.stats()["s0"] == {"frames": 4, "dropped": 2, "bad_frames": 0,
                                                                  "seq_resets": 0, "implausible_seq": 0}
    with RecordingSource(sink_path) as bad:
        assert list(bad.frames()) == [] and bad.stats()["s0"]["bad_frames"] == 1


def test_many_in_process_sensors_have_their_own_noise():
    cfg = SimSourceConfig(NOISY, sensors=3, id_prefix="m", rate_hz=0, seed=SEED, frames=2)
    with SimulatedSource(cfg) as src:
        frames = list(src.frames())
    assert [(f.sensor_id, f.seq) for f in frames] == [("m0", 0), ("m1", 0), ("m2", 0), ("m0", 1), ("m1", 1), ("m2", 1)]
    assert np.abs(frames[0].data - frames[1].data).max() > 10 * LSB
    with in_process(NOISY, SEED + 1) as one:  # sensor i draws as a single sensor of seed + i
        np.testing.assert_array_equal(next(iter(one.frames(1))).data, frames[1].data)


def test_reads_that_stop_mid_tick_lose_no_frame():
    cfg = SimSourceConfig(STATIC, sensors=2, id_prefix="m", rate_hz=0, seed=SEED, frames=3)
    with SimulatedSource(cfg) as src:
        got = [(f.sensor_id, f.seq) for f in src.frames(3)] + [(f.sensor_id, f.seq) for f in src.frames(2)]
        got += [(f.sensor_id, f.seq) for f in src.frames()]
    assert got == [(f"m{i}", k) for k in range(3) for i in range(2)]
    assert src.stats() == {"m0": {"frames": 3, "dropped": 0}, "m1": {"frames": 3, "dropped": 0}}
