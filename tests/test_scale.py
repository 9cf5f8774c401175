"""Issue 13, the paper's IoT case at scale: edge quantization (the sensor's process
publishes 1-bit frames), nodes that batch across sensors, sensors shared among several
processes (--shard, --sensors), spread sources and health in slices. Real zenoh
sessions, in process and across processes over 127.0.0.1; every wait bounded."""

import json
import subprocess
import threading
import zlib

import numpy as np
import pytest

from pipeline.bus.session import BusConfig, Shard
from pipeline.dsp.decode import DEFAULT_ALPHA
from pipeline.errors import ParameterError
from pipeline.nodes.counters import HEALTH_SLICES
from pipeline.nodes.intake import QueueConfig
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode, run_nodes
from pipeline.dsp.quantize import QuantizerConfig
from pipeline.wire import decode_health, decode_quantized, decode_raw, decode_targets
from radar_driver.scene import resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource
from zenoh_helpers import QRADAR, RUNTIME_DECODER, Collector, stop_when, wait_until

CHAMBER = resolve_scene("chamber")
QUANT = QuantizerConfig(alpha=1.0, dither_seed=9)


def sim(sensors=4, frames=6, rate=50.0, prefix="e", send="burst", seed=3):
    return SimulatedSource(SimSourceConfig(CHAMBER, sensors=sensors, rate_hz=rate, id_prefix=prefix, frames=frames,
                                           seed=seed, send=send))


def run_until_done(nodes, done, timeout_s=30.0):
    """``run_nodes(nodes)`` until ``done()`` (every frame the source sent is accounted for
    downstream), at most ``timeout_s``."""
    stop = threading.Event()
    threading.Thread(target=stop_when, args=(done, stop, timeout_s), daemon=True).start()
    run_nodes(nodes, timeout_s + 5, stop)


def by_frame(payloads, decode):
    out = {}
    for p in payloads:
        m = decode(p)
        assert (m.sensor_id, m.seq) not in out, "a frame came twice"
        out[(m.sensor_id, m.seq)] = m
    return out


# -- sources -----------------------------------------------------------------------------------
def test_spread_sensors_send_the_same_frames_in_groups_over_the_period():
    burst, spread = sim(sensors=40, frames=3, rate=20.0), sim(sensors=40, frames=3, rate=20.0, send="spread")
    b = list(burst.frame_batches())
    s = list(spread.frame_batches())
    assert [len(g) for g in b] == [40, 40, 40]  # one burst per period
    assert len(s) == 3 * 25 and {len(g) for g in s} == {1, 2}  # 50 ms period / 2 ms slots: 25 groups of 40
    fb = [f for g in b for f in g]
    fs = [f for g in s for f in g]
    assert [(f.sensor_id, f.seq) for f in fb] == [(f.sensor_id, f.seq) for f in fs]
    assert all(np.array_equal(x.data, y.data) for x, y in zip(fb, fs))  # the same frames, sent at other times
    # group j of a period (sensors j*40//25 ..) is sent j/25 of the period after the first:
    # stamped at its due time, or later when this process was late making it
    t = np.array([f.timestamp_ns for f in fs[:40]]) - fs[0].timestamp_ns
    due = np.array([j for j in range(25) for _ in range(j * 40 // 25, (j + 1) * 40 // 25)]) * 2e6
    assert np.all(t >= due - 2e5) and np.all(np.diff(t) >= 0), t
    assert len({f.timestamp_ns for f in fb[:40]}) == 1
    assert burst.stats()["e0"]["frames"] == 3 and spread.stats()["e39"]["frames"] == 3


def test_a_limit_cuts_a_group_and_the_next_read_resumes_it():
    src = sim(sensors=5, frames=2, rate=0.0)
    with src:
        first = [(f.sensor_id, f.seq) for f in src.frames(3)]
        rest = [(f.sensor_id, f.seq) for f in src.frames()]
    assert first == [("e0", 0), ("e1", 0), ("e2", 0)]
    assert rest[:2] == [("e3", 0), ("e4", 0)] and len(rest) == 7
    with pytest.raises(Exception, match="send"):
        SimSourceConfig(CHAMBER, send="random")


# -- edge quantization ---------------------------------------------------------------------------
def test_edge_frames_are_the_central_quantizers_frames_and_decode_to_the_same_targets(zenoh_session):
    """The same sensors (same noise seed) quantized in the source's process and by a quantize
    node give byte-identical 1-bit frames, and the localizer finds the same targets."""
    session = zenoh_session
    edge, central = BusConfig(prefix="edge"), BusConfig(prefix="central")
    col = Collector(session, "*/*/*")
    loc_cfg = LocalizerConfig(k=2, algo="qiht", radar=CHAMBER.radar)
    e_src = SourceNode(edge, sim(), session=session, quantizer=QUANT, raw_every=2)
    c_src = SourceNode(central, sim(), session=session)
    nodes = [LocalizeNode(edge, loc_cfg, session=session), LocalizeNode(central, loc_cfg, session=session),
             QuantizeNode(central, QUANT, session=session), e_src, c_src]
    def both_targeted() -> bool:  # each frame's targets on both paths
        with col.lock:
            keys = [k for k, _ in col.items if k.endswith("/targets")]
        return sum(k.startswith("edge/") for k in keys) >= 4 * 6 and sum(k.startswith("central/") for k in keys) >= 4 * 6

    stop = threading.Event()
    threading.Thread(target=stop_when, args=(both_targeted, stop, 30), daemon=True).start()
    run_nodes(nodes, 35, stop)
    with col.lock:
        items = list(col.items)
    of = lambda prefix, topic: [p for k, p in items if k.startswith(prefix + "/") and k.endswith("/" + topic)]  # noqa: E731
    eq, cq = by_frame(of("edge", "quantized"), decode_quantized), by_frame(of("central", "quantized"), decode_quantized)
    assert len(eq) == len(cq) == 4 * 6
    for f, m in eq.items():
        assert m.header()[:1] + m.header()[3:] == cq[f].header()[:1] + cq[f].header()[3:]  # all but seq/timestamp order
        assert np.array_equal(m.codes, cq[f].codes) and m.dither_seed == cq[f].dither_seed
    # raw frames only every 2nd seq at the edge
    assert sorted({m.seq for m in map(decode_raw, of("edge", "raw"))}) == [0, 2, 4]
    et, ct = by_frame(of("edge", "targets"), decode_targets), by_frame(of("central", "targets"), decode_targets)
    assert set(et) == set(ct) == set(eq)
    for f, t in et.items():
        assert [round(x["range_m"], 9) for x in t.targets] == [round(x["range_m"], 9) for x in ct[f].targets]
        assert [x["angle_deg"] for x in t.targets] == pytest.approx([x["angle_deg"] for x in ct[f].targets])


def test_edge_quantization_options_are_checked():
    with pytest.raises(ParameterError, match="raw_every"):
        SourceNode(BusConfig(), sim(), session=object(), raw_every=0)  # neither raw nor quantized: nothing


# -- sharing the sensors -----------------------------------------------------------------------------
def test_shards_serve_exactly_their_sensors_and_together_every_one(bus, zenoh_session):
    session = zenoh_session
    col = Collector(session, "radar/*/targets")
    shards = [Shard(i, 3) for i in range(3)]
    locs = [LocalizeNode(bus, LocalizerConfig(k=2, radar=CHAMBER.radar), session=session, shard=sh) for sh in shards]
    src = SourceNode(bus, sim(sensors=12, frames=5, prefix="sh"), session=session, quantizer=QUANT)
    run_until_done(locs + [src], lambda: all(
        (t := loc.totals())["frames_out"] + t["foreign_frames"] == 5 * 12 for loc in locs))
    ids = [f"sh{i}" for i in range(12)]
    for sh, loc in zip(shards, locs):
        mine = {s for s in ids if zlib.crc32(s.encode()) % 3 == sh.index}
        assert set(loc.stats) == mine, sh  # state and targets for its own sensors only
        t = loc.totals()
        assert t["frames_out"] == 5 * len(mine) and t["foreign_frames"] == 5 * (12 - len(mine))
    got = by_frame(col.of("/targets"), decode_targets)  # each frame's targets exactly once
    assert set(got) == {(s, q) for s in ids for q in range(5)}


def test_a_sensor_pattern_is_filtered_by_zenoh(bus, zenoh_session):
    session = zenoh_session
    loc = LocalizeNode(bus, LocalizerConfig(k=1, radar=CHAMBER.radar), session=session, sensors="a1*")
    src_a = SourceNode(bus, sim(sensors=12, frames=3, prefix="a"), session=session, quantizer=QUANT)
    run_until_done([loc, src_a], lambda: loc.totals()["frames_in"] == 9)
    assert set(loc.stats) == {"a1", "a10", "a11"} and loc.totals()["frames_in"] == 9
    with pytest.raises(ParameterError, match="pattern"):
        LocalizeNode(bus, LocalizerConfig(k=1), session=session, sensors="a/b")
    for bad in ("2/2", "x", "-1/2", "1/0"):
        with pytest.raises(ParameterError, match="shard"):
            Shard.parse(bad)


# -- health in slices --------------------------------------------------------------------------------
def test_health_of_many_sensors_comes_in_slices_once_a_period(bus, zenoh_session):
    session = zenoh_session
    period = 0.5
    loc = LocalizeNode(bus, LocalizerConfig(k=1, radar=CHAMBER.radar), session=session, health_period_s=period)
    src = SourceNode(bus, sim(sensors=30, frames=2, rate=20.0, prefix="h"), session=session, quantizer=QUANT,
                     health_period_s=60)
    col = Collector(session, "radar/*/health")
    loc.start()
    src.start()
    try:
        wait_until(lambda: src.done.is_set(), 10, "the source")
        wait_until(lambda: loc.totals()["frames_out"] == 60, 10, "every frame localized")
        with col.lock:
            col.items.clear()

        def localizer_health() -> dict[str, list[int]]:
            """Each sensor's localize health since the clear: its timestamps (ns)."""
            per_sensor: dict[str, list[int]] = {}
            for h in map(decode_health, col.of("/health")):
                if h.node == "localize":
                    per_sensor.setdefault(h.sensor_id, []).append(h.timestamp_ns)
            return per_sensor

        # three of each sensor's health messages (not a fixed time: a busy host delays a period)
        wait_until(lambda: len(per := localizer_health()) == 30 and all(len(v) >= 3 for v in per.values()), 20,
                   "three health messages of each of the 30 sensors")
        per_sensor = localizer_health()
        mine = [h for h in map(decode_health, col.of("/health")) if h.node == "localize"]
    finally:
        src.stop()
        loc.stop()
    assert set(per_sensor) == {f"h{i}" for i in range(30)}
    # once a period each: the mean spacing of a sensor's health no less than about the period (the
    # loop's waits never end early), and not several periods (a loose bound: a busy host delays ticks) ...
    spacing = {k: (v[-1] - v[0]) / (len(v) - 1) / 1e9 for k, v in per_sensor.items()}
    assert all(0.75 * period <= t <= 4 * period for t in spacing.values()), spacing
    # ... and every HEALTH_SLICES ticks of the health loop (a slice of the period each; every tick publishes
    # the health of some sensors, all with the tick's one timestamp): however late a busy host's ticks
    # (which only delay, so no upper bound on the spacing in seconds)
    tick = {t: i for i, t in enumerate(sorted({t for v in per_sensor.values() for t in v}))}
    ticks = {k: [tick[t] for t in sorted(v)] for k, v in per_sensor.items()}
    assert all(np.diff(v).tolist() == [HEALTH_SLICES] * (len(v) - 1) for v in ticks.values()), ticks
    # the 30 sensors are spread over the slices of the period, not published at one instant
    assert len({v[0] % HEALTH_SLICES for v in ticks.values()}) >= 5, ticks
    assert all(h.frames_out == 2 and h.latency_ms["p99"] is not None for h in mine)


# -- the commands, across processes ---------------------------------------------------------------------
def cli(*args):
    return subprocess.Popen([*QRADAR, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def test_pulled_and_callback_input_give_the_same_targets(zenoh_session):
    """A localizer that drains zenoh's FIFO itself and one handed each message by zenoh's
    callback thread (the default) find the same targets in the same frames, each frame once."""
    session = zenoh_session
    col = Collector(session, "*/*/targets")
    cfg = LocalizerConfig(k=2, radar=CHAMBER.radar)
    buses = {mode: BusConfig(prefix=mode) for mode in ("pull", "callback")}
    locs = {mode: LocalizeNode(bus, cfg, session=session, queue=QueueConfig(input_mode=mode))
            for mode, bus in buses.items()}
    srcs = {mode: SourceNode(bus, sim(sensors=5, frames=8, prefix="m", send="spread"), session=session,
                             quantizer=QUANT) for mode, bus in buses.items()}
    run_until_done(list(locs.values()) + list(srcs.values()),
                   lambda: all(loc.totals()["frames_out"] >= 40 for loc in locs.values()) and len(col.items) >= 80,
                   timeout_s=30)
    with col.lock:
        items = list(col.items)
    got = {mode: by_frame([p for k, p in items if k.startswith(mode + "/")], decode_targets) for mode in buses}
    frames = {(f"m{i}", q) for i in range(5) for q in range(8)}
    assert set(got["pull"]) == set(got["callback"]) == frames
    for f in frames:
        assert got["pull"][f].targets == got["callback"][f].targets
    for mode, loc in locs.items():
        t = loc.totals()
        assert loc.input_mode == mode and t["frames_in"] == t["frames_out"] == 40, (mode, t)
        assert not loc.errors and t["drops"] == t["processing_errors"] == 0


def test_the_input_mode_is_checked(bus):
    with pytest.raises(ParameterError, match="input mode 'push' must be one of"):
        LocalizeNode(bus, LocalizerConfig(), session=object(), queue=QueueConfig(input_mode="push"))
    r = subprocess.run([*QRADAR, "localize", "--input", "push"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "--input: invalid choice: 'push'" in r.stderr.strip().splitlines()[-1]


def test_edge_source_and_two_sharded_localizers_across_processes(free_port, connect_when_ready):
    ep = f"tcp/127.0.0.1:{free_port}"
    # (caps: the test ends them; the waits below may add up to more than a minute on a loaded host)
    router = cli("router", "--listen", ep, "--duration", "180")
    locs = []
    try:
        session = connect_when_ready(ep, timeout_s=30, mode="client")
        locs = [cli("localize", *RUNTIME_DECODER, "--mode", "client", "--connect", ep, "--shard", f"{i}/2",
                    "--duration", "180") for i in range(2)]
        col = Collector(session, "radar/*/targets")
        quant = Collector(session, "radar/*/quantized")
        wait_until(lambda: sum(1 for r in session.liveliness().get("radar/alive/localize/**", timeout=1.0)
                               if r.ok is not None) == 2, 30, "both localizers up")
        src = cli("source", "--mode", "client", "--connect", ep, "--sensors", "6", "--frames", "10", "--rate", "40", "--send", "spread",
                  "--quantized", "--dither-seed", "4", "--id-prefix", "x")
        out, err = src.communicate(timeout=60)
        assert src.returncode == 0, err
        report = json.loads(out.strip().splitlines()[-1])
        assert report["frames_out"] == 60  # quantized frames only: no raw
        wait_until(lambda: len(col.of("/targets")) >= 60, 20, "targets of every frame")
        got = by_frame(col.of("/targets"), decode_targets)
        assert set(got) == {(f"x{i}", q) for i in range(6) for q in range(10)}
        q = decode_quantized(quant.of("/quantized")[0])
        assert q.bits == 1 and q.alpha == np.float32(DEFAULT_ALPHA)  # the one default (pipeline.defaults)
    finally:
        totals = []
        for p in locs:
            p.terminate()
            out, err = p.communicate(timeout=30)
            totals.append(json.loads(out.strip().splitlines()[-1]))
        router.terminate()
        router.communicate(timeout=30)
    assert sum(t["frames_out"] for t in totals) == 60 and all(t["frames_out"] > 0 for t in totals)
    assert sum(t["foreign_frames"] for t in totals) == 60
    assert all(t["drops"] == 0 and t["decode_errors"] == 0 for t in totals)


def test_edge_options_are_refused_where_they_make_no_sense():
    r = subprocess.run([*QRADAR, "source", "--raw-every", "2", "--frames", "1"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "--raw-every is for edge quantization" in r.stderr
    r = subprocess.run([*QRADAR, "localize", "--shard", "3/2", "--duration", "0.1"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "shard" in r.stderr
    for args, says in ((["localize", "--sensors", "a/b"], "sensor pattern 'a/b' must be one key chunk"),
                       (["localize", "--batch-linger", "-1"], "--batch-linger"),
                       (["drive", "--port", "/dev/null", "--quantize", "--no-publish"], "cannot go with --no-publish")):
        r = subprocess.run([*QRADAR, *args], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and says in r.stderr.strip().splitlines()[-1], r.stderr
        assert "Traceback" not in r.stderr
