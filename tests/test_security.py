"""Security of the bus: no node listens unless asked, the router honours its config file,
``qradar security`` issues certificates, and ``--secure`` (mutual TLS + zenoh access
control) keeps strangers and identities of the wrong role from publishing anything the
pipeline consumes. Real processes and sessions over 127.0.0.1; every wait is bounded."""

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from pipeline.bus.session import BusConfig
from pipeline.errors import BusError, ParameterError
from pipeline.bus.security import Identity, Policy, SecureConfig
from pipeline.wire import (
    QuantizedFrameMsg,
    RawFrameMsg,
    TargetsMsg,
    decode_targets,
    encode_quantized,
    encode_raw,
)
from qradar.cli import main
from radar_driver.scene import resolve_scene
from test_nodes import truth_error
from zenoh_helpers import (QRADAR, RUNTIME_DECODER, Collector, alive_nodes, free_port, listening_sockets, wait_port,
                           wait_until)

pytestmark = pytest.mark.skipif(not Path("/proc/self/net/tcp").exists() or shutil.which("openssl") is None,
                                reason="reads listening sockets from /proc; makes certificates with openssl")

LOOPBACK4 = "0100007F"  # 127.0.0.1 as /proc/net/tcp writes it
FAKE_SEQ = 10_000  # every forged message carries a seq from here on


def qradar(*args: str) -> subprocess.Popen:
    return subprocess.Popen([*QRADAR, *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def stop(procs, timeout_s=20):
    """SIGTERM each process and collect (stdout, stderr); one still running after
    ``timeout_s`` is killed."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
    outs = []
    for p in procs:
        try:
            outs.append(p.communicate(timeout=timeout_s))
        except subprocess.TimeoutExpired:
            p.kill()
            outs.append(p.communicate(timeout=timeout_s))
    return outs


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    """The lab's CA (init with sensor s1, then s0 added) and an attacker's CA of its own."""
    root = tmp_path_factory.mktemp("pki")
    lab, other = root / "lab", root / "other"
    for argv in (["init", lab, "--sensors", "s1"], ["add", lab, "--role", "sensor", "--id", "s0"],
                 ["init", other, "--sensors", "s0"]):
        proc = subprocess.run([*QRADAR, "security", *map(str, argv)], capture_output=True,
                              text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
    return lab, other


# -- no listener unless asked; the router's config file ------------------------------------

def test_a_session_has_no_implicit_listener(tmp_path):
    for bus in (BusConfig(), BusConfig(connect=("tcp/127.0.0.1:1",)), BusConfig(mode="client", connect=("tcp/h:1",)),
                BusConfig(mode="router")):
        assert json.loads(bus.zenoh_config().get_json("listen/endpoints")) == [], bus
    # a config file's own listeners are honoured, per mode too
    f = tmp_path / "z.json5"
    f.write_text('{listen: {endpoints: {router: ["tcp/127.0.0.1:7001"], peer: ["tcp/127.0.0.1:7002"]}}}')
    assert BusConfig(mode="router", config_file=f).listen_endpoints() == ["tcp/127.0.0.1:7001"]
    assert BusConfig(config_file=f).listen_endpoints() == ["tcp/127.0.0.1:7002"]
    assert BusConfig(config_file=f, listen=("tcp/127.0.0.1:7003",)).listen_endpoints() == ["tcp/127.0.0.1:7003"]


def test_nodes_listen_on_nothing_unless_asked(tmp_path, free_port, connect_when_ready):
    ep = f"tcp/127.0.0.1:{free_port}"
    asked = free_port_other(free_port)
    # (--duration: caps, beyond the test's own waits; stop() ends them all, normally)
    router = qradar("router", "--listen", ep, "--duration", "120")
    nodes = []
    try:
        session = connect_when_ready(ep, timeout_s=30, mode="client")  # a client needs its router up
        nodes += [qradar("quantize", "--connect", ep, "--duration", "120"),  # a peer, as the README used to say
                  qradar("localize", *RUNTIME_DECODER, "--mode", "client", "--connect", ep, "--duration", "120"),
                  qradar("record", "--connect", ep, "-o", tmp_path / "r.mcap", "--topics", "radar/*/targets",
                         "--duration", "120"),
                  qradar("source", "--connect", ep, "--listen", f"tcp/127.0.0.1:{asked}", "--rate", "1",
                         "--duration", "120")]
        seen = []
        wait_until(lambda: {"quantize", "localize", "record", "source"} <= set(seen.append(alive_nodes(session))
                                                                              or seen[-1]), 30,
                   "the four nodes alive")
        assert listening_sockets(router.pid) == {("tcp", LOOPBACK4, free_port)}
        assert [listening_sockets(p.pid) for p in nodes[:3]] == [set(), set(), set()]
        assert listening_sockets(nodes[3].pid) == {("tcp", LOOPBACK4, asked)}  # asked for: there and only there
    finally:
        outs = stop([router, *nodes])
    for p, (_, err) in zip([router, *nodes], outs):
        assert p.returncode == 0, err


def free_port_other(port: int) -> int:
    for _ in range(20):
        other = free_port()
        if other != port:
            return other
    pytest.fail("no second free port")


def test_router_listens_where_its_config_file_says(tmp_path, free_port, connect_when_ready):
    conf = tmp_path / "router.json5"
    conf.write_text(f'{{ listen: {{ endpoints: ["tcp/127.0.0.1:{free_port}"] }} }}')
    router = qradar("router", "--zenoh-config", conf, "--duration", "120")  # a cap: stop() ends it
    try:
        assert f"listening on ['tcp/127.0.0.1:{free_port}']" in first_line(router, 30)
        connect_when_ready(f"tcp/127.0.0.1:{free_port}", timeout_s=30, mode="client")
        assert listening_sockets(router.pid) == {("tcp", LOOPBACK4, free_port)}  # not tcp/0.0.0.0:7447 instead
    finally:
        [(_, err)] = stop([router])
    assert router.returncode == 0, err


def first_line(proc: subprocess.Popen, timeout_s: float) -> str:
    """The first line ``proc`` writes on stdout, waiting at most ``timeout_s``."""
    line = []
    reader = threading.Thread(target=lambda: line.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    if not line:
        pytest.fail(f"no line on stdout within {timeout_s} s", pytrace=False)
    return line[0]


# -- certificates -------------------------------------------------------------------------

def openssl(*args) -> subprocess.CompletedProcess:
    return subprocess.run(["openssl", *map(str, args)], capture_output=True, text=True, timeout=30)


def test_security_init_and_add_make_a_ca_and_certificates(pki, tmp_path, capsys, monkeypatch):
    lab, other = pki
    assert os.stat(lab).st_mode & 0o777 == 0o700
    policy = Policy.load(lab)
    roles = {i.name: (i.role, i.sensors) for i in policy.identities}
    assert roles == {"router": ("router", ()), "sensor-s1": ("sensor", ("s1",)), "quantizer": ("quantizer", ("*",)),
                     "localizer": ("localizer", ("*",)), "recorder": ("recorder", ()), "viewer": ("viewer", ()),
                     "sensor-s0": ("sensor", ("s0",))}
    for name in [*roles, "ca"]:
        assert os.stat(lab / f"{name}.key").st_mode & 0o777 == 0o600
        assert openssl("verify", "-CAfile", lab / "ca.pem", lab / f"{name}.pem").returncode == 0
    assert openssl("verify", "-CAfile", other / "ca.pem", lab / "sensor-s0.pem").returncode != 0  # another CA
    text = openssl("x509", "-in", lab / "sensor-s0.pem", "-noout", "-subject", "-ext", "subjectAltName").stdout
    assert "CN = sensor-s0" in text and "DNS:" not in text and "IP Address" not in text  # only the router names hosts
    text = openssl("x509", "-in", lab / "router.pem", "-noout", "-subject", "-ext", "subjectAltName").stdout
    assert "CN = router" in text and "DNS:localhost" in text and "IP Address:127.0.0.1" in text

    # a sensor on another host, with its own SANs; the CA's copy of the directory
    copy = tmp_path / "lab"
    shutil.copytree(lab, copy)
    monkeypatch.chdir(tmp_path)  # a relative directory
    assert main(["security", "add", "lab", "--role", "sensor", "--id", "s3", "--host", "10.0.0.5"]) == 2
    assert "router identity only" in capsys.readouterr().err  # a sensor is a client: no host names
    assert main(["security", "add", "lab", "--role", "sensor", "--id", "s3"]) == 0
    assert "sensor-s3" in capsys.readouterr().out
    text = openssl("x509", "-in", copy / "sensor-s3.pem", "-noout", "-ext", "subjectAltName").stdout
    assert "DNS:" not in text and "IP Address" not in text
    assert Policy.load(copy).get("sensor-s3").publishes("radar") == ["radar/s3/raw", "radar/s3/quantized",
                                                                      "radar/s3/health"]
    # refused, each with one line: a name that exists, a CA that exists, a wildcard sensor id, no CA key
    (copy / "ca.key").rename(tmp_path / "ca.key")
    for argv, what in ((["add", copy, "--role", "sensor", "--id", "s3"], "exists already"),
                       (["init", copy], "has a CA already"),
                       (["add", lab, "--role", "sensor", "--id", "s*"], "sensor_id='s*'"),
                       (["add", copy, "--role", "viewer", "--id", "v2"], "ca.key is missing")):
        assert main(["security", *map(str, argv)]) == 2
        err = capsys.readouterr().err
        assert what in err and len(err.strip().splitlines()) == 1, err


def test_identity_and_secure_config_errors(pki):
    lab, _ = pki
    with pytest.raises(ParameterError, match="needs its sensor ids"):
        Identity("sensor-x", "sensor")
    with pytest.raises(ParameterError, match="role='admin'"):
        Identity("x", "admin")
    with pytest.raises(BusError, match="no identity 'sensor-s9'"):
        SecureConfig(lab, "sensor-s9")
    with pytest.raises(BusError, match="no such directory"):
        SecureConfig(lab / "nope", "router")


def test_secure_refuses_plaintext_endpoints(pki, tmp_path, capsys):
    lab, _ = pki
    secure = SecureConfig(lab, "quantizer")
    with pytest.raises(ParameterError, match="not encrypted"):
        BusConfig(connect=("tcp/127.0.0.1:7447",), secure=secure)
    conf = tmp_path / "plain.json5"
    conf.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7447"] } }')
    with pytest.raises(ParameterError, match="zenoh config file .* listen endpoint 'tcp/127.0.0.1:7447'"):
        BusConfig(config_file=conf, secure=secure).zenoh_config()
    for argv, what in ((["quantize", "--secure", lab, "--connect", "udp/127.0.0.1:7447"], "not encrypted"),
                       (["source", "--secure", lab, "--sensors", "2"], "needs --identity"),
                       (["run", "--secure", lab, "--mode", "client", "--connect", "tls/127.0.0.1:7447"],
                        "drop --mode client"),
                       (["localize", "--identity", "localizer"], "--identity is for --secure")):
        assert main([*map(str, argv), "--duration", "1"]) == 2
        err = capsys.readouterr().err
        assert what in err and len(err.strip().splitlines()) == 1, err


# -- the secure pipeline and its attackers --------------------------------------------------

def forgeries(scene) -> list[tuple[str, bytes]]:
    """One of each message the pipeline consumes, for sensor s0, forged (seq >= FAKE_SEQ,
    a target 99 m away)."""
    rng = np.random.default_rng(7)
    cid, m = scene.radar.config_id(), scene.radar.ramps_per_frame * 256
    raw = (rng.standard_normal((m, 2)) + 1j * rng.standard_normal((m, 2))).astype(np.complex64) * 0.1
    quant = QuantizedFrameMsg("s0", FAKE_SEQ, time.time_ns(), cid, 1, 0.0, 1.0, 0, np.zeros((m, 2, 2), np.uint8))
    target = {"range_m": 99.0, "angle_deg": 45.0, "x_m": 70.0, "y_m": 70.0, "amplitude": 1.0}
    targets = TargetsMsg("s0", FAKE_SEQ, time.time_ns(), cid, "pbp", 1, "quantized", [target])
    return [("radar/s0/raw", encode_raw(RawFrameMsg("s0", FAKE_SEQ, time.time_ns(), cid, raw))),
            ("radar/s0/quantized", encode_quantized(quant)), ("radar/s0/targets", targets.to_json()),
("radar/*/raw", encode_raw(RawFrameMsg(
                "s0", FAKE_SEQ + 1, time.time_ns(), cid, raw))), ("radar/evil/raw", encode_raw(RawFrameMsg(
                    "evil", FAKE_SEQ, time.time_ns(), cid, raw)))]


def attack(sessions, fakes, stop_evt, rounds=60, period_s=0.025) -> None:
    """Each of ``sessions`` ({label: session}) puts every forgery and a health message
    signed with its label, ``rounds`` times."""
    for _ in range(rounds):
        if stop_evt.is_set():
            return
        for label, s in sessions.items():
            for key, payload in [*fakes, ("radar/s0/health", json.dumps({"forged": label}).encode())]:
                try:
                    s.put(key, payload)
                except zenoh.ZError:
                    pass
        time.sleep(period_s)


def test_secure_pipeline_keeps_out_strangers_and_wrong_roles(pki, tmp_path, free_port, connect_when_ready, capsys):
    lab, other = pki
    ep = f"tls/127.0.0.1:{free_port}"
    frames = 20
    scene = resolve_scene("single")
    routers = tmp_path / "router-pki"  # the router's copy, where the recorder has been withdrawn
    shutil.copytree(lab, routers)
    assert main(["security", "remove", str(routers), "recorder"]) == 0
    # (--duration: caps, beyond the test's own waits, which add up to more than a minute; stop() ends them)
    router = qradar("router", "--secure", routers, "--listen", ep, "--duration", "180")
    procs, attackers = [router], {}
    try:
        viewer = connect_when_ready(ep, timeout_s=30, mode="client", secure=SecureConfig(lab, "viewer"))
        procs += [qradar("quantize", "--secure", lab, "--connect", ep, "--alpha", "0.5", "--duration", "180"),  # peer
                  qradar("localize", *RUNTIME_DECODER, "--secure", lab, "--mode", "client", "--connect", ep, "--K", "1",
                         "--duration", "180")]
        col = Collector(viewer, "radar/**")
        wait_until(lambda: {"quantize", "localize"} <= set(alive_nodes(viewer)), 30, "quantize and localize alive")

        # (a) no certificate: plaintext, or TLS without a client certificate; (b) another CA's certificate
        nocert = tmp_path / "nocert.json5"
        nocert.write_text(json.dumps({"transport": {"link": {"tls": {"root_ca_certificate": str(lab / "ca.pem")}}}}))
        refused = [BusConfig(mode="client", connect=(f"tcp/127.0.0.1:{free_port}",)),
                   BusConfig(mode="client", connect=(ep,), config_file=nocert),
                   BusConfig(mode="client", connect=(ep,), secure=SecureConfig(other, "sensor-s0"))]
        for bus in refused:
            with pytest.raises(BusError, match="cannot open zenoh session"):
                bus.open().close()
        # ... which as peers open (a peer does not need its connections) but reach no one
        attackers["nocert-peer"] = BusConfig(connect=(ep,), config_file=nocert).open()
        attackers["otherca-peer"] = BusConfig(connect=(ep,), secure=SecureConfig(other, "sensor-s0")).open()
        # (c) valid certificates of the wrong role: sensor s1 (as a client, and as a listening peer), the viewer
        attackers["s1-client"] = BusConfig(mode="client", connect=(ep,), secure=SecureConfig(lab, "sensor-s1")).open()
        attackers["s1-peer"] = BusConfig(connect=(ep,), listen=(f"tls/127.0.0.1:{free_port_other(free_port)}",),
                                         secure=SecureConfig(lab, "sensor-s1")).open()
        attackers["viewer"] = BusConfig(mode="client", connect=(ep,), secure=SecureConfig(lab, "viewer")).open()
        # ... and a withdrawn one (still signed by the CA)
        attackers["removed"] = BusConfig(mode="client", connect=(ep,), secure=SecureConfig(lab, "recorder")).open()
        tokens = [s.liveliness().declare_token("radar/alive/localize/forged") for s in attackers.values()]

        stop_evt = threading.Event()
        attacker = threading.Thread(target=attack, args=(attackers, forgeries(scene), stop_evt), daemon=True)
        attacker.start()
        source = qradar("source", "--secure", lab, "--mode", "client", "--connect", ep, "--scene", "single",
                        "--id-prefix", "s", "--frames", frames, "--duration", "120")
        procs.append(source)
        wait_until(lambda: len(col.of("s0/targets")) >= frames, 40, f"{frames} targets of s0")
        attacker.join(10)
        stop_evt.set()
        time.sleep(1.0)  # anything forged still on its way arrives by now
        assert alive_nodes(viewer).count("localize") == 1  # not the forged token
        for t in tokens:
            t.undeclare()
    finally:
        for s in attackers.values():
            s.close()
        outs = stop(procs)
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err
    totals = {json.loads(out.strip().splitlines()[-1])["node"]: json.loads(out.strip().splitlines()[-1])
              for out, _ in outs[1:]}

    # only the real frames went in and came out
    assert totals["quantize"]["frames_in"] == frames and totals["localize"]["frames_in"] == frames
    assert totals["source"]["frames_out"] == frames
    with col.lock:
        keys = {k for k, _ in col.items}
    assert keys <= {"radar/s0/raw", "radar/s0/quantized", "radar/s0/targets", "radar/s0/health"}, keys
    forged = [(k, p[:80]) for k, p in col.items if b"forged" in p or b'"range_m":99.0' in p or b"evil" in p]
    # only health, which every role may publish for every sensor it serves (a viewer: all), and which no
    # node consumes (docs/security.md)
    assert forged and {p for _, p in forged} == {b'{"forged": "viewer"}'}, forged
    targets = [decode_targets(p) for p in col.of("s0/targets")]
    assert sorted(t.seq for t in targets) == list(range(frames))
    assert np.percentile(truth_error(scene, targets), 90) < 1.0


def test_run_secure_serves_other_nodes_over_tls_only(pki, free_port, connect_when_ready):
    """``qradar run --secure --listen tls/...``: its drivers (local, over a unix socket)
    publish, a viewer on TLS reads, a sensor of another id cannot inject."""
    lab, _ = pki
    ep = f"tls/127.0.0.1:{free_port}"
    run = qradar("run", *RUNTIME_DECODER, "--secure", lab, "--listen", ep, "--scene", "single", "--K", "1",
                 "--frames", "100", "--no-record", "--json")
    attacker = None
    try:
        viewer = connect_when_ready(ep, timeout_s=30, mode="client", secure=SecureConfig(lab, "viewer"))
        col = Collector(viewer, "radar/*/targets")
        attacker = BusConfig(mode="client", connect=(ep,), secure=SecureConfig(lab, "sensor-s1")).open()
        fakes = [(k.replace("s0", "kmd2-0"), p) for k, p in forgeries(resolve_scene("single"))]
        stop_evt = threading.Event()
        attack({"s1-client": attacker}, fakes, stop_evt, rounds=40)
        wait_until(lambda: run.poll() is not None, 60, "qradar run to end after 100 frames")
    finally:
        if attacker is not None:
            attacker.close()
        [(out, err)] = stop([run])
    assert run.returncode == 0, err
    summary = json.loads(out)
    assert summary["frames_raw"] == summary["frames_targets"] == 100
    assert summary["position_error_m"]["median"] < 1.0
    seen = [decode_targets(p) for p in col.of("kmd2-0/targets")]
    assert seen and all(t.seq < FAKE_SEQ and t.sensor_id == "kmd2-0" for t in seen)
    assert not any(k.endswith("evil/targets") for k, _ in col.items)


def test_only_the_router_is_the_router(pki, free_port):
    """A router started with another identity's key (the viewer's, a sensor's) is refused
    by every node that dials it, in one line: only the router's certificate names the
    router's hosts, and a node checks the name of the host it dials."""
    lab, _ = pki
    for name in ("viewer", "sensor-s0", "quantizer"):
        san = subprocess.run(["openssl", "x509", "-in", str(lab / f"{name}.pem"), "-noout", "-ext", "subjectAltName"],
                             capture_output=True, text=True, timeout=30)
        assert "127.0.0.1" not in san.stdout and "localhost" not in san.stdout, (name, san.stdout)
    ep = f"tls/127.0.0.1:{free_port}"
    impostor = qradar("router", "--secure", lab, "--identity", "viewer", "--listen", ep, "--duration", "60")
    try:
        wait_port(free_port)
        nodes = [("localize", *RUNTIME_DECODER, "--secure", lab, "--mode", "client", "--connect", ep,
                  "--duration", "5"),
                 ("quantize", "--secure", lab, "--mode", "client", "--connect", ep, "--duration", "5"),
                 ("source", "--secure", lab, "--mode", "client", "--connect", ep, "--id-prefix", "s",
                  "--frames", "3")]
        for args in nodes:
            out = subprocess.run([*QRADAR, *map(str, args)], capture_output=True, text=True,
                                 timeout=60)
            line = out.stderr.strip()
            assert out.returncode == 2 and "\n" not in line, (args[0], out.stderr)
            assert "only the router's own certificate" in line and "cannot open zenoh session" in line
    finally:
        stop([impostor])


def test_every_role_security_knows_has_a_node_class_of_that_liveliness_name():
    """The node each role runs is the node class that declares that role (Node.role), and
    its liveliness name (Node.name) is the one the policy lets the role declare."""
    import pipeline.nodes.stream  # noqa: F401  (the node classes, by layer)
    import qradar.view  # noqa: F401
    import replay.recorder  # noqa: F401
    from pipeline.nodes.runtime import Node
    from pipeline.bus.security import ROLE_NODE, ROLES

    def subclasses(cls):
        for sub in cls.__subclasses__():
            yield sub
            yield from subclasses(sub)

    declared = {}
    for cls in subclasses(Node):
        if "role" in vars(cls) and cls.role is not None:
            declared.setdefault(cls.role, set()).add(cls.name)
    assert declared == {role: {name} for role, name in ROLE_NODE.items()}
    assert set(ROLES) == {"router", *declared}  # the router runs no node of ours
    for role, name in ROLE_NODE.items():
        assert Identity("x", role, ("s1",) if role == "sensor" else ()).liveliness("radar") == [f"radar/alive/{name}/*"]
