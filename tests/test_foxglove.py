"""The live view in Foxglove (qradar.view), checked with a client that is not ours: the
``@foxglove/ws-protocol`` client in node (tests/js/foxglove_client.mjs, packages installed by
``make test``), which decodes the point clouds with the protobuf schema the server
advertises. Every wait is bounded in count and time; servers bind 127.0.0.1."""

import json
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from pipeline.bus.session import BusConfig
from pipeline.errors import ParameterError
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode, run_nodes
from pipeline.dsp.quantize import QuantizerConfig
from pipeline.wire import TargetsMsg, decode_quantized
from qradar.run import RunConfig, run
from qradar.view import (POINT_FIELDS, TF_TOPIC, FoxgloveView, ViewConfig, ViewError, health_topic, parse_endpoint,
                         range_profile, sensor_topics, target_points)
from radar_driver.model import RadarConfig, polar_to_xy
from radar_driver.scene import resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource
from replay.mcapio import McapFile
from zenoh_helpers import QRADAR, Collector, free_port, stop_when, wait_until

ROOT = Path(__file__).resolve().parents[1]
JS = ROOT / "tests" / "js"
CLIENT = JS / "foxglove_client.mjs"


@pytest.fixture(scope="module")
def node() -> str:
    exe = shutil.which("node")
    if exe is None or not (JS / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.fail("the Foxglove test client needs node and tests/js/node_modules: `make test` installs them "
                    "(`make js-deps`)", pytrace=False)
    return exe


class Client:
    """tests/js/foxglove_client.mjs in node; its JSON lines, collected by a reader thread."""

    def __init__(self, node: str, url: str, topic: str = ".*", timeout_s: float = 30.0):
        self.proc = subprocess.Popen([node, str(CLIENT), url, "--topic", topic, "--timeout-s", str(timeout_s),
                                      "--connect-s", "15"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     stdin=subprocess.DEVNULL, text=True)
        self.lines: list[dict] = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            with self._lock:
                self.lines.append(json.loads(line))

    def events(self, event: str) -> list[dict]:
        with self._lock:
            return [e for e in self.lines if e["event"] == event]

    def messages(self, topic_suffix: str) -> list[dict]:
        """Messages on topics ending with ``topic_suffix``; a JSON message's ``data`` is parsed
        again from its text here (JavaScript rounds integers beyond 2^53, e.g. timestamp_ns)."""
        out = [dict(e) for e in self.events("message") if e["topic"].endswith(topic_suffix)]
        for e in out:
            if e["text"] is not None:
                e["data"] = json.loads(e["text"])
        return out

    def finish(self, timeout_s: float = 15.0) -> str:
        """Wait for the client to end (the server closed, or its own timeout); its end reason."""
        try:
            self.proc.wait(timeout_s)
        finally:
            self.close()
        self._reader.join(5.0)
        ends = self.events("end")
        assert ends, f"the client printed no end line; stderr: {self.proc.stderr.read()}"
        return ends[-1]["reason"]

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5.0)


def check_cloud(cloud: dict, targets: dict) -> None:
    """A decoded PointCloud against the targets message (wire JSON) it was made from."""
    assert cloud["frame_id"] == f"radar_{targets['sensor_id']}"
    assert int(cloud["timestamp_ns"]) == targets["timestamp_ns"]
    assert [f["name"] for f in cloud["fields"]] == list(POINT_FIELDS) and cloud["point_stride"] == 4 * len(POINT_FIELDS)
    assert all(f["type"] == 7 for f in cloud["fields"])  # foxglove.NumericType.FLOAT32
    pts, tgs = cloud["points"], targets["targets"]
    assert len(pts) == len(tgs)
    if not tgs:
        return
    r = np.array([t["range_m"] for t in tgs])
    a = np.array([t["angle_deg"] for t in tgs])
    x, y = polar_to_xy(r, np.radians(a))  # the model's convention, the one place it is defined
    got = {f: np.array([p[f] for p in pts], dtype=float) for f in ("x", "y", "z", "range_m", "angle_deg", "amplitude")}
    assert np.array_equal(got["range_m"], r.astype(np.float32))
    assert np.array_equal(got["angle_deg"], a.astype(np.float32))
    assert_allclose(got["x"], x, rtol=1e-6, atol=1e-5)
    assert_allclose(got["y"], y, rtol=1e-6, atol=1e-5)
    assert_allclose(got["x"], [t["x_m"] for t in tgs], atol=1e-4)  # and the localizer's own x, y agree
    assert_allclose(got["y"], [t["y_m"] for t in tgs], atol=1e-4)
    assert np.all(got["z"] == 0)
    assert_allclose(got["amplitude"], [t["amplitude"] for t in tgs], rtol=1e-6)
    assert_allclose([p["statistic_db"] for p in pts], [t["statistic_db"] for t in tgs], rtol=1e-6)


def test_a_foreign_client_decodes_the_targets_of_a_run(node, tmp_path):
    """``qradar run --foxglove``: the point clouds and targets JSON the node client decodes
    are the run's targets (as its recording holds them), frame by frame."""
    port = free_port()
    client = Client(node, f"ws://127.0.0.1:{port}", topic=r"/targets(_json)?$")
    stop, result = threading.Event(), {}
    cfg = RunConfig(duration_s=20.0, rate_hz=40.0, record=tmp_path / "run.mcap", foxglove=ViewConfig(port=port))
    job = threading.Thread(target=lambda: result.update(summary=run(cfg, live=None, stop=stop)), daemon=True)
    job.start()
    try:
        # the client connects while the run starts, and may miss its first frames: 30 frames after it did
        wait_until(lambda: len(client.messages("/targets")) >= 30 and len(client.messages("/targets_json")) >= 30,
                   20, "30 point clouds and targets messages at the client")
    finally:
        stop.set()
        job.join(30)
        reason = client.finish()
    assert reason == "closed by the server"
    summary = result["summary"]
    assert summary["foxglove"]["url"] == f"ws://127.0.0.1:{port}" and summary["foxglove"]["decode_errors"] == 0
    recorded = [json.loads(m.data) for ch, m in McapFile(tmp_path / "run.mcap").messages()
                if ch.topic == "radar/kmd2-0/targets"]
    # (135 of 137 and 136 of 138 once each on fresh clones, before a stopping node waited for the messages
    # zenoh's callback thread still held for it: the recording's own account, to tell a counted drop from
    # a message the recorder never got)
    account = {k: summary["recording"][k] for k in ("received", "written", "dropped", "lost", "error")}
    assert len(recorded) == summary["frames_targets"] >= 30, account
    by_time = {t["timestamp_ns"]: t for t in recorded}
    advertised = {e["topic"]: e for e in client.events("advertise")}
    assert set(sensor_topics("radar", "kmd2-0").values()) | {TF_TOPIC} <= set(advertised)
    assert advertised["/radar/kmd2-0/targets"]["schemaName"] == "foxglove.PointCloud"
    assert advertised["/radar/kmd2-0/targets"]["encoding"] == "protobuf"
    assert advertised["/radar/kmd2-0/targets_json"]["encoding"] == "json"
    clouds = client.messages("/kmd2-0/targets")
    assert len(clouds) >= 30
    for e in clouds:
        check_cloud(e["data"], by_time[int(e["data"]["timestamp_ns"])])
    jsons = client.messages("/kmd2-0/targets_json")
    assert len(jsons) >= 30
    for e in jsons:
        assert e["data"] == by_time[e["data"]["timestamp_ns"]]  # the wire message, as recorded (same seq)
    assert len({by_time[int(e["data"]["timestamp_ns"])]["seq"] for e in clouds}) == len(clouds)


def test_the_view_serves_profiles_and_health_and_survives_garbage(node, bus, zenoh_session):
    """Two simulated sensors through quantizer and localizer: the client gets each sensor's
    range profiles (equal to ones computed from the quantized frames, peaking at the
    target's range) at most at the asked rate, each node's health, and transforms; malformed
    payloads are counted and the view keeps serving."""
    session = zenoh_session
    quantized = Collector(session, "radar/*/quantized")
    scene = resolve_scene("single")  # one target at 12 m: range bin 20
    view = FoxgloveView(bus, ViewConfig(port=0, profile_rate_hz=4.0), session=session, health_period_s=0.2)
    view.start()
    client = Client(node, view.url, topic=r"/(targets|range_profile|health/\w+|tf)$")
    try:
        wait_until(lambda: client.events("open"), 15, "the client to connect")
        src = SourceNode(bus, SimulatedSource(SimSourceConfig(scene, sensors=2, rate_hz=50, id_prefix="sim",
                                                              frames=75)), session=session, health_period_s=0.2)
        nodes = [LocalizeNode(bus, LocalizerConfig(k=1, algo="pbp"), session=session, health_period_s=0.2),
                 QuantizeNode(bus, QuantizerConfig(alpha=1.0, dither_seed=3), session=session, health_period_s=0.2),
                 src]
        def all_localized() -> bool:  # the localizer's health of each sensor says all 75 frames are out
            return all((h := client.messages(f"/{sensor}/health/localize")) and h[-1]["data"]["frames_out"] == 75
                       for sensor in ("sim0", "sim1"))

        stop = threading.Event()
        threading.Thread(target=stop_when, args=(all_localized, stop, 20), daemon=True).start()
        t0 = time.monotonic()
        run_nodes(nodes, duration_s=25.0, stop=stop)
        seconds = time.monotonic() - t0
        for key, payload in [("radar/bad/targets", b"not json"), ("radar/bad/quantized", b"QRDR\x01"),
                             ("radar/bad/health", b"{}"), ("radar/sim0/targets", TargetsMsg(
                                 "sim1", 0, 1, 0, "pbp", 1, "quantized", []).to_json()),
                             ("radar/sim0/health", json.dumps({"version": 1, "type": "health", "node": "a/b",
                                 "sensor_id": "sim0", "timestamp_ns": 1, "frames_in": 0, "frames_out": 0,
                                 "drops": 0, "decode_errors": 0, "latency_ms": {}, "bytes_in_per_s": 0,
                                 "bytes_out_per_s": 0}).encode())]:
            session.put(key, payload)
        wait_until(lambda: view.totals()["decode_errors"] == 5, 10, "five malformed payloads counted")
        time.sleep(1.0)  # five health periods: the nodes' health of their unknown senders ("_unknown") is health,
        assert view.totals()["decode_errors"] == 5  # not an error, though the view has no state of that sensor
        after = time.time_ns()
        session.put("radar/sim0/targets", TargetsMsg("sim0", 999, after, 0, "pbp", 1, "quantized", []).to_json())
        wait_until(lambda: any(e["data"]["timestamp_ns"] == str(after) for e in client.messages("/sim0/targets")),
                   10, "the view serving after the garbage")
        wait_until(lambda: len(client.messages("/sim1/health/view")) >= 1, 10, "the view's own health")
    finally:
        view.stop()
        reason = client.finish()
    assert reason == "closed by the server" and not view.errors
    # profiles skipped on purpose (4 a second of 50) are not frames missing
    assert view.summary()["profiles_skipped"] > 0 and view.stats["sim1"].frames_missing == 0
    frames = {(m.sensor_id, m.seq): m for m in map(decode_quantized, quantized.of("sim0/quantized")
                                                                        + quantized.of("sim1/quantized"))}
    for sensor in ("sim0", "sim1"):
        profiles = client.messages(f"/{sensor}/range_profile")
        assert 2 <= len(profiles) <= 4.0 * seconds + 1, (len(profiles), seconds)  # at most 4 a second
        for e in profiles:
            p = e["data"]
            assert p == range_profile(frames[(sensor, p["seq"])], RadarConfig())
            assert len(p["range_m"]) == len(p["profile_db"]) == len(p["antenna1_db"]) == 256
            assert int(np.argmax(p["profile_db"])) == 20 and p["range_m"][20] == pytest.approx(12.0)
        nodes_seen = {e["topic"].rsplit("/", 1)[-1] for e in client.messages("") if f"/{sensor}/health/" in e["topic"]}
        assert nodes_seen == {"source", "quantize", "localize", "view"}
        last = [e["data"] for e in client.messages(f"/{sensor}/health/localize")][-1]
        assert last["sensor_id"] == sensor and last["frames_out"] == 75
    tf = {e["data"]["childFrameId"] for e in client.messages("/tf")}
    assert tf >= {"radar_sim0", "radar_sim1"}
    assert all(e["data"]["parentFrameId"] == "world" for e in client.messages("/tf"))


def listening(port: int) -> set[str]:
    """Local addresses (hex, as /proc/net/tcp{,6} write them) of the sockets listening on ``port``."""
    found = set()
    for name in ("tcp", "tcp6"):
        path = Path("/proc/net") / name
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            fields = line.split()
            addr, hex_port = fields[1].split(":")
            if fields[3] == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                found.add(addr)
    return found


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="reads listening sockets from /proc/net/tcp")
def test_qradar_view_listens_on_loopback_only_by_default():
    port = free_port()
    proc = subprocess.Popen([*QRADAR, "view", "--port", str(port), "--duration", "20"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
                            cwd=ROOT, env=os.environ | {"PYTHONPATH": str(ROOT)})
    try:
        wait_until(lambda: listening(port), 15, f"qradar view to listen on port {port}")
        assert listening(port) == {"0100007F"}  # 127.0.0.1 only: not 0.0.0.0, not ::
        proc.terminate()  # SIGTERM ends it cleanly, with its summary
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert proc.returncode == 0, err
    assert f"Foxglove WebSocket server on ws://127.0.0.1:{port}" in err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["node"] == "view" and summary["url"] == f"ws://127.0.0.1:{port}"


def test_a_busy_port_is_one_clear_error(bus):
    port = free_port()
    first = FoxgloveView(bus, ViewConfig(port=port)).start()
    try:
        second = FoxgloveView(bus, ViewConfig(port=port))
        with pytest.raises(ViewError, match=f"127.0.0.1:{port}.*in use"):
            second.start()
        second.stop()
    finally:
        first.stop()


def test_target_points_follow_the_model_convention():
    msg = TargetsMsg("s", 0, 5, 0, "pbp", 2, "quantized", [
        {"range_m": 10.0, "angle_deg": 30.0, "x_m": 0.0, "y_m": 0.0, "amplitude": 0.5, "statistic_db": 20.0},
        {"range_m": 4.0, "angle_deg": -90.0, "x_m": 0.0, "y_m": 0.0, "amplitude": 0.25}])
    pts = target_points(msg)
    assert pts.dtype.itemsize == 4 * len(POINT_FIELDS) and pts.dtype.names == POINT_FIELDS
    assert_allclose(pts["x"], [10 * np.cos(np.pi / 6), 0.0], atol=1e-6)
    assert_allclose(pts["y"], [5.0, -4.0], atol=1e-6)  # positive angle: +y (antenna 2's side)
    assert pts["statistic_db"][0] == 20.0 and np.isnan(pts["statistic_db"][1])
    assert target_points(TargetsMsg("s", 0, 5, 0, "pbp", 2, "quantized", [])).shape == (0,)


def test_view_config_and_endpoints_are_checked():
    assert ViewConfig().host == "127.0.0.1" and ViewConfig().port == 8765
    assert parse_endpoint("9000") == ("127.0.0.1", 9000)
    assert parse_endpoint("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_endpoint("[::1]:9000") == ("::1", 9000)
    for bad in ("x", "host:", "1:70000"):
        with pytest.raises(ParameterError, match="HOST:]PORT"):
            parse_endpoint(bad)
    with pytest.raises(ParameterError, match="port=70000"):
        ViewConfig(port=70000)
    with pytest.raises(ParameterError, match="profile_rate_hz"):
        ViewConfig(profile_rate_hz=-1)
    with pytest.raises(ParameterError, match="host"):
        ViewConfig(host="")
    assert BusConfig().prefix == "radar"


def _tab_panels(layout: dict) -> dict[str, list[str]]:
    """The panels of each tab of the layout's Tab panel, by the tab's title."""
    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    tab = layout["configById"][layout["layout"]]
    return {t["title"]: leaves(t["layout"]) for t in tab["tabs"]}


def _panel_paths(cfg: dict) -> list[str]:
    return (list(cfg.get("topics", {})) + [p["value"] for p in cfg.get("paths", [])]
            + [cfg[k] for k in ("topicPath",) if k in cfg]
            + ([cfg["xAxisPath"]["value"]] if "xAxisPath" in cfg else []))


def test_the_committed_layout_shows_topics_the_view_serves():
    """docs/foxglove-layout.json (docs/stream.md: "Live view in Foxglove"): its tab "live" names
    only topics and frames the view serves for ``qradar run``'s sensor kmd2-0 (its tab
    "recording": test_a_run_recording_shows_itself_in_foxglove)."""
    layout = json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())
    panels = layout["configById"]
    tabs = _tab_panels(layout)
    assert list(tabs) == ["live", "recording"]
    served = set(sensor_topics("radar", "kmd2-0").values()) | {
        health_topic("radar", "kmd2-0", n) for n in ("source", "quantize", "localize", "recorder", "view")}
    named = {p.split(".", 1)[0] for pid in tabs["live"] for p in _panel_paths(panels[pid])}
    assert named and named <= served, named - served
    assert {p.split("!", 1)[0] for p in tabs["live"]} == {"3D", "Plot", "Table", "RawMessages"}
    assert panels["3D!qradar"]["followTf"] == "world"
    profile = panels["Plot!range_profile"]
    assert profile["xAxisVal"] == "currentCustom" and profile["xAxisPath"]["value"].endswith("range_profile.range_m[:]")
    assert sorted(tabs["live"] + tabs["recording"]) == sorted(p for p in panels if not p.startswith("Tab!"))


def mcap_check(node: str, path: Path, tab: str | None = None) -> dict:
    """tests/js/mcap_check.mjs on a recording (and the layout's panels of ``tab``): what
    Foxglove's libraries read in it."""
    args = [node, str(JS / "mcap_check.mjs"), str(path)]
    if tab is not None:
        args += ["--layout", str(ROOT / "docs" / "foxglove-layout.json"), "--tab", tab]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=120)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert proc.returncode == 0 and "error" not in out, (out.get("error"), proc.stderr[-2000:])
    return out


def test_a_run_recording_shows_itself_in_foxglove(node, tmp_path):
    """A ``qradar run --track`` recording read by Foxglove's own libraries (@mcap/core, zstd,
    @foxglove/schemas): every message of a Foxglove schema validates against Foxglove's
    schema, every path of the layout's tab "recording" gives values (range profiles per
    receiver against range, targets, tracks and their σ, health), the point cloud's points
    are the targets and the scene's ellipses are the tracks' 1-σ circles."""
    from pipeline.dsp.track import TrackerConfig

    path = tmp_path / "run.mcap"
    # 80 frames (4 s of sensor time), not 4 s of a host's time: a loaded host made 39 frames in 4 s
    summary = run(RunConfig(duration_s=120.0, frames=80, rate_hz=20.0, record=path, tracking=TrackerConfig()),
                  live=None)
    out = mcap_check(node, path, tab="recording")
    topics = out["topics"]
    schemas = {t: v["schemaName"] for t, v in topics.items()}
    assert schemas == {f"radar/kmd2-0/{k}": v for k, v in {
        "raw": "qradar.RawFrame", "quantized": "qradar.QuantizedFrame", "targets": "qradar.Targets",
        "tracks": "qradar.Tracks", "health": "qradar.Health", "pointcloud": "foxglove.PointCloud",
        "scene": "foxglove.SceneUpdate", "profile": "qradar.RangeProfile"}.items()}
    assert all(v["invalid"] == 0 and not v["errors"] for v in topics.values()), {
        t: v["errors"] for t, v in topics.items() if v["errors"]}
    frames = summary["frames_targets"]
    # the scene: a message per tracks message and one per targets message (cml's targets carry their ellipses)
    assert topics["radar/kmd2-0/pointcloud"]["messages"] == frames >= 20  # a busy host may lose (and count) some
    assert topics["radar/kmd2-0/scene"]["messages"] == 2 * frames
    assert 4 <= topics["radar/kmd2-0/profile"]["messages"] <= 2 * 4.0 + 3  # at most 2 a second of sensor time
    for p, got in out["paths"].items():  # every panel's topic decodes, and its paths give what the panel plots
        assert got["messages"] > 0 and got["values"] > 0, (p, got)
        if "." in p:  # a plotted path: numbers (a first track, confirmed after a few frames, not in every message)
            wanted = 0.8 * got["messages"] if "targets[0]" in p or "profile" in p else 1
            assert got["numbers"] >= wanted, (p, got)
    # the first messages, as Foxglove decoded them
    first = {t.rsplit("/", 1)[-1]: v["first"] for t, v in topics.items()}
    prof = first["profile"]
    assert len(prof["range_m"]) == len(prof["antenna1_db"]) == len(prof["antenna2_db"]) == 128
    assert prof["range_m"][1] == pytest.approx(1.2)  # two 0.6 m bins a value
    targets = first["targets"]["targets"]
    assert [pt["range_m"] for pt in first["pointcloud"]["points"]] == pytest.approx([t["range_m"] for t in targets])
    recorded = {json.loads(m.data)["seq"]: json.loads(m.data) for ch, m in McapFile(path).messages()
                if ch.topic.endswith("/tracks")}
    last = max(recorded)
    assert recorded[last]["tracks"], "no confirmed track in the run: nothing to draw"
    scenes = [json.loads(m.data) for ch, m in McapFile(path).messages() if ch.topic.endswith("/scene")]
    assert sum(any(e["id"] == "target-0" for e in sc["entities"]) for sc in scenes) == frames
    ents = {e["id"]: e for sc in scenes[-2:] for e in sc["entities"]}
    for t in recorded[last]["tracks"]:
        cyl = ents[f"track-{t['track_id']}"]["cylinders"][0]
        assert cyl["size"]["x"] == cyl["size"]["y"] == pytest.approx(max(2 * t["sigma_m"], 0.2))
        assert (cyl["pose"]["position"]["x"], cyl["pose"]["position"]["y"]) == (t["x_m"], t["y_m"])


def test_tracks_as_a_scene_update_and_sensors_at_their_poses(node, bus, zenoh_session, tmp_path):
    """Tracks messages -> foxglove.SceneUpdate, decoded by the foreign client with the
    official schema the server advertises: one entity per track, a sphere at its position
    and a label with its id, speed, radial velocity (the Doppler's) and sigma; each sensor's frame at its pose of the
    sensors file."""
    from pipeline.wire import TracksMsg
    from qradar.view import load_poses, track_label

    poses = tmp_path / "sensors.toml"
    poses.write_text("[trk0]\nx_m = 3.0\ny_m = -2.0\nyaw_deg = 90.0\n\n[trk1]\nyaw_deg = -30\n")
    view = FoxgloveView(bus, ViewConfig(port=0, profile_rate_hz=0.0, poses=load_poses(poses)), session=zenoh_session,
                        health_period_s=0.2)
    view.start()
    client = Client(node, view.url, topic=r"/(tracks|tf)$")
    tracks = [{"track_id": 3, "range_m": 5.0, "angle_deg": 0.0, "x_m": 5.0, "y_m": 0.0, "vx_mps": 1.2,
               "vy_mps": -0.5, "sigma_m": 0.25, "age_s": 2.0, "hits": 40, "static": False, "radial_velocity_mps": 1.187},
              {"track_id": 4, "range_m": 10.0, "angle_deg": 30.0, "x_m": 8.66, "y_m": 5.0, "vx_mps": 0.0,
               "vy_mps": 0.0, "sigma_m": 0.02, "age_s": 9.0, "hits": 180, "static": True}]
    try:
        wait_until(lambda: client.events("open"), 15, "the client to connect")
        for i in range(40):  # until the client has subscribed and got some
            for sid in ("trk0", "trk1"):
                zenoh_session.put(f"radar/{sid}/tracks", TracksMsg(sid, i, 10**18 + i, tracks, 0).to_json())
            time.sleep(0.05)
            if len(client.messages("/trk1/tracks")) >= 3 and len(client.messages("/tf")) >= 2:
                break
        wait_until(lambda: {e["data"]["childFrameId"] for e in client.messages("/tf")} >= {"radar_trk0", "radar_trk1"},
                   10, "both sensors' transforms")
    finally:
        view.stop()
        client.finish()
    assert view.totals()["decode_errors"] == 0
    advertised = {e["topic"]: e for e in client.events("advertise")}
    assert advertised["/radar/trk0/tracks"]["schemaName"] == "foxglove.SceneUpdate"
    assert advertised["/radar/trk0/tracks"]["encoding"] == "protobuf"
    scene = client.messages("/trk1/tracks")[-1]["data"]
    ents = {e["id"]: e for e in scene["entities"]}
    assert set(ents) == {"track-3", "track-4"}
    moving, static = ents["track-3"], ents["track-4"]
    assert moving["frameId"] == "radar_trk1" and moving["frameLocked"]
    assert moving["spheres"][0]["pose"]["position"]["x"] == pytest.approx(5.0)
    assert moving["spheres"][0]["size"]["x"] == pytest.approx(0.5)  # 2 sigma
    assert static["spheres"][0]["size"]["x"] == pytest.approx(0.2)  # at least 0.2 m
    assert static["spheres"][0]["pose"]["position"]["y"] == pytest.approx(5.0)
    assert moving["texts"][0]["text"] == track_label(tracks[0]) == "#3 1.30 m/s radial +1.187 m/s σ 0.250 m"
    assert static["texts"][0]["text"] == "#4 static σ 0.020 m"
    assert static["spheres"][0]["color"]["g"] > static["spheres"][0]["color"]["r"]  # green while static
    tf = {e["data"]["childFrameId"]: e["data"] for e in client.messages("/tf")}
    t0 = tf["radar_trk0"]
    assert t0["parentFrameId"] == "world"
    assert (t0["translation"]["x"], t0["translation"]["y"]) == (pytest.approx(3.0), pytest.approx(-2.0))
    assert (t0["rotation"]["z"], t0["rotation"]["w"]) == (pytest.approx(np.sqrt(0.5)), pytest.approx(np.sqrt(0.5)))
    assert tf["radar_trk1"]["rotation"]["z"] == pytest.approx(np.sin(np.radians(-15.0)))


def test_a_bad_sensors_file_is_one_clear_error(tmp_path):
    from qradar.view import load_poses

    p = tmp_path / "s.toml"
    for text, what in [("[a]\nx_m = 'one'\n", "x_m='one'"), ("[a]\nz_m = 1\n", "unknown keys \\['z_m'\\]"),
                       ("['a/b']\nx_m = 1\n", "sensor_id"), ("a = 1\n", "must be a table"), ("[a\n", "not TOML")]:
        p.write_text(text)
        with pytest.raises(ParameterError, match=what):
            load_poses(p)
    with pytest.raises(ParameterError, match="cannot read"):
        load_poses(tmp_path / "missing.toml")


def test_bad_tracks_messages_are_counted_and_the_view_keeps_serving(bus, zenoh_session):
    """Malformed tracks (not JSON, another sensor's id, a NaN position) are counted in
    the view's decode errors, one each, and a good tracks message after them is served."""
    from pipeline.wire import TracksMsg

    view = FoxgloveView(bus, ViewConfig(port=0, profile_rate_hz=0), session=zenoh_session, health_period_s=0.2)
    view.start()
    try:
        track = {"track_id": 1, "range_m": 5.0, "angle_deg": 10.0, "x_m": 4.92, "y_m": 0.87, "vx_mps": 0.0,
                 "vy_mps": 0.0, "sigma_m": 0.05, "age_s": 1.0, "hits": 20, "static": True}
        good = TracksMsg("t0", 1, time.time_ns(), [track]).to_json()
        bad = [b"not json", TracksMsg("t1", 2, 1, [track]).to_json(),
               good.replace(b'"x_m":4.92', b'"x_m":NaN')]
        for payload in bad:
            zenoh_session.put("radar/t0/tracks", payload)
        wait_until(lambda: view.totals()["decode_errors"] == 3, 10, "three bad tracks messages counted")
        zenoh_session.put("radar/t0/tracks", good)
        wait_until(lambda: view.totals()["frames_out"] >= 1, 10, "the good tracks message served")
        assert view.totals()["decode_errors"] == 3 and not view.errors
    finally:
        view.stop()
