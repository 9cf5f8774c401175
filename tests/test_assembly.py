"""The frame assembler alone: the simulated K-MD2's answers (device logic, no link) as
bytes, or messages, in; frames and counters out. No port, no threads."""

import numpy as np
import pytest

from radar_driver.assembly import DriverCounters, FrameAssembler, Taken
from radar_driver.errors import SensorResponseError, SensorTimeout
from radar_driver.model import simulate_frames
from radar_driver.profile import DEFAULT_PROFILE, resolve_profile
from radar_driver.protocol import Done, Gnfd, Init, OtherMessage, Radc, Resp, RespCode, encode
from radar_driver.scene import SimScene, SimTarget
from radar_driver.simulator import SimFaults, SimulatedKMD2

LSB = np.sqrt(2) * 0.5 / 2048 * 1.001  # half an ADC step on I and Q
SCENE = SimScene((SimTarget(12.0, 20.0, 0.5), SimTarget(4.8, -35.0, 0.1, phase_deg=40.0)))
ANSWER_BYTES = 12 + 2056 + 12  # RESP, RADC, DONE of one GNFD
WORDS = np.full((2, 1, 256, 2), 2048, np.uint16)  # one mid-scale RADC of the default profile


def expected_frame(scene: SimScene) -> np.ndarray:
    r = np.array([[t.range_m for t in scene.targets]])
    a = np.array([[t.angle_deg for t in scene.targets]])
    x = np.array([[t.amplitude * np.exp(1j * np.deg2rad(t.phase_deg)) for t in scene.targets]])
    return simulate_frames(r, a, x, scene.radar)[0]


def answer(dev: SimulatedKMD2) -> bytes:
    """The bytes of the device's answer to one GNFD."""
    return b"".join(r.data for r in dev.receive(encode(Gnfd())))


def poll(asm: FrameAssembler, dev: SimulatedKMD2, frames: int, max_polls: int) -> list:
    """Poll until ``frames`` frames or ``max_polls`` GNFDs."""
    out: list = []
    for _ in range(max_polls):
        out += asm.feed(answer(dev))
        if len(out) >= frames:
            break
    return out


def ticks():
    """A clock for the assembler: 1000 ns, 2000 ns, ..."""
    t = [0]

    def clock() -> int:
        t[0] += 1000
        return t[0]

    return clock


def test_frames_equal_the_model_within_adc_quantization():
    asm = FrameAssembler(DEFAULT_PROFILE, sensor_id="s1", clock=ticks())
    frames = poll(asm, SimulatedKMD2(SCENE, rate_hz=0), 10, 20)
    gamma = expected_frame(SCENE)
    assert [f.seq for f in frames] == list(range(10))
    for i, f in enumerate(frames):
        assert f.sensor_id == "s1" and f.data.shape == (512, 2) and f.data.dtype == np.complex64
        assert np.abs(f.data - gamma).max() <= LSB
        assert f.counters == (2 * i, 2 * i + 1)
        assert f.timestamp_ns == 1000 * (2 * i + 1)  # the clock at the DONE of the frame's first RADC
        assert f.config_id == SCENE.radar.config_id()
    c = asm.counters
    assert (c.frames, c.ramps, c.dropped, c.resyncs, c.skipped_bytes) == (10, 20, 0, 0, 0)
    assert c.bytes == 20 * ANSWER_BYTES


def test_the_bytes_cut_anywhere_make_the_same_frames():
    dev = SimulatedKMD2(SCENE, rate_hz=0)
    stream = b"".join(answer(dev) for _ in range(6))
    whole = FrameAssembler(DEFAULT_PROFILE, clock=ticks())
    cut = FrameAssembler(DEFAULT_PROFILE, clock=ticks())
    a = whole.feed(stream)
    b = [f for i in range(0, len(stream), 7) for f in cut.feed(stream[i : i + 7])]
    assert len(a) == len(b) == 3
    assert [f.counters for f in a] == [f.counters for f in b] == [(0, 1), (2, 3), (4, 5)]
    assert all(np.array_equal(x.data, y.data) for x, y in zip(a, b))
    assert whole.counters == cut.counters


def test_garbage_and_truncated_messages_are_skipped_and_counted():
    dev = SimulatedKMD2(SCENE, rate_hz=0, faults=SimFaults(garbage_prob=0.3, truncate_prob=0.05), seed=4)
    asm = FrameAssembler(DEFAULT_PROFILE)
    frames = poll(asm, dev, 40, 400)
    c = asm.counters
    assert len(frames) == 40
    assert c.resyncs > 5 and c.skipped_bytes > 50
    assert c.incomplete == dev.event_counts["TRUNCATED"] >= 1  # each truncated RADC, refused at its DONE
    gamma = expected_frame(SCENE)
    assert all(np.abs(f.data - gamma).max() <= LSB for f in frames)  # every frame intact
    assert all(f.counters[1] == f.counters[0] + 1 for f in frames)  # consecutive ramps only


def test_done_counter_gaps_count_as_drops():
    dev = SimulatedKMD2(SCENE, rate_hz=0, faults=SimFaults(skip_done_prob=0.2), seed=1)
    asm = FrameAssembler(DEFAULT_PROFILE)
    frames = poll(asm, dev, 30, 300)
    skipped = dev.skipped_radcs
    c = asm.counters
    assert len(frames) == 30 and skipped > 0
    assert c.dropped_radcs == skipped  # the counter's gaps, in RADCs (ramps here)
    assert c.discarded_ramps > 0  # partial frames a gap broke
    assert c.ramps == 2 * c.frames + c.discarded_ramps
    assert c.dropped == (skipped + c.discarded_ramps) // 2  # in frames: ramps measured that no frame carried
    assert all(f.counters[1] == f.counters[0] + 1 for f in frames)


def test_a_gap_of_66_frames_counts_66_dropped_frames_not_132_ramps():
    dev = SimulatedKMD2(SCENE, rate_hz=0, faults=SimFaults(skip_frames_after=3, skip_frames=66))
    asm = FrameAssembler(DEFAULT_PROFILE)
    frames = poll(asm, dev, 6, 12)
    assert dev.skipped_radcs == 132
    c = asm.counters
    assert c.dropped == 66 and c.dropped_radcs == 132 and c.discarded_ramps == 0
    assert [f.counters for f in frames] == [(0, 1), (2, 3), (4, 5), (138, 139), (140, 141), (142, 143)]


def test_an_answer_with_the_last_counter_again_is_not_a_new_frame():
    """A sensor that answered a queued GNFD at once with the RADC it already sent (same
    DONE counter) must not have that RADC assembled twice."""
    asm = FrameAssembler(DEFAULT_PROFILE)
    frames = []
    for counter in (0, 1, 1, 2, 3):
        assert asm.take(Radc(WORDS)) is Taken.NOTHING
        if asm.take(Done(counter)) is Taken.FRAME:
            frames.append(asm.frame())
    c = asm.counters
    assert c.repeated == 1 and c.ramps == 4 and c.frames == 2 and c.dropped == 0
    assert [f.counters for f in frames] == [(0, 1), (2, 3)]


def test_each_done_is_an_answer_and_other_messages_are_not():
    asm = FrameAssembler(DEFAULT_PROFILE)
    assert [asm.take(m) for m in (Resp(), OtherMessage(b"PDAT", b"1234"), Radc(WORDS), Done(7))] == [
        Taken.NOTHING, Taken.NOTHING, Taken.NOTHING, Taken.ANSWER]
    assert asm.held == 1
    assert asm.take(Done(8)) is Taken.ANSWER  # a DONE without its RADC: counted, the partial frame discarded
    c = asm.counters
    assert (c.incomplete, c.discarded_ramps, c.dropped, asm.held) == (1, 1, 0, 0)  # half a frame lost


def test_a_resp_error_to_gnfd_is_raised_and_counted():
    asm = FrameAssembler(DEFAULT_PROFILE)
    with pytest.raises(SensorResponseError, match=r"GNFD.*RESP 2 \(INVALID_PARAMETER\)"):
        asm.take(Resp(RespCode.INVALID_PARAMETER))
    assert asm.counters.resp_errors == 1


def test_answers_without_a_whole_radc_in_a_row_end_in_a_timeout():
    """Every RADC cut short (the codec refuses it at the DONE header inside it)."""
    dev = SimulatedKMD2(SCENE, rate_hz=0, faults=SimFaults(truncate_prob=1.0))
    asm = FrameAssembler(DEFAULT_PROFILE, source="/dev/ttyUSB7")
    for _ in range(FrameAssembler.MAX_INCOMPLETE_IN_A_ROW - 1):
        assert asm.feed(answer(dev)) == []
    with pytest.raises(SensorTimeout, match="8 GNFD answers in a row from /dev/ttyUSB7 lacked a whole RADC"):
        asm.feed(answer(dev))
    c = asm.counters
    assert c.incomplete == 8 and c.frames == 0 and asm.decoder.stats.invalid == 8


def test_a_restart_discards_the_partial_frame_and_a_gap_across_it_counts():
    asm = FrameAssembler(DEFAULT_PROFILE)
    asm.take(Radc(WORDS))
    asm.take(Done(0))
    asm.decode(encode(Resp())[:5])  # half a message in the codec
    asm.restart()  # a reconnect
    assert asm.held == 0 and asm.decoder.pending() == 0
    assert asm.counters.discarded_ramps == 1 and asm.counters.dropped == 0  # half a frame lost so far
    assert asm.feed(encode(Radc(WORDS)) + encode(Done(3)) + encode(Radc(WORDS)) + encode(Done(4))) != []
    c = asm.counters
    assert c.dropped_radcs == 2 and c.dropped == 1 and c.frames == 1  # ramps 1, 2 and the discarded 0


def test_a_profile_of_many_chirps_makes_a_frame_of_one_radc():
    cube = resolve_profile("kmd2-cube256")
    dev = SimulatedKMD2(SCENE, rate_hz=0, profile=cube)
    asm = FrameAssembler(cube, ramps_per_frame=2, chirp_select="first", counters=DriverCounters())
    frames = asm.feed(b"".join(r.data for r in dev.receive(encode(Init(0)) + encode(Gnfd(cube.gnfd_bits["RADC"])))))
    assert len(frames) == 1 and frames[0].counters == (0,) and frames[0].data.shape == (512, 2)
    assert np.abs(frames[0].data - expected_frame(SCENE)).max() <= LSB
