"""Only the router is the router: ``security add``/``init`` put host names on router
identities only, ``security check`` flags a certificate of another role that names hosts
(made before that rule), and every node under ``--secure`` refuses, with one line, a peer
it dialled whose certificate is not a router identity's (pipeline.bus.router_check): an
impostor router started with each non-router identity, with and without host names, at
open and when a node reconnects after its router went away. Real zenoh sessions over
127.0.0.1, real certificates (openssl); every wait bounded."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import zenoh

from pipeline.bus.audit import admin_links
from pipeline.bus.security import Identity, Policy, SecureConfig
from pipeline.bus.session import BusConfig
from pipeline.dsp.quantize import QuantizerConfig
from pipeline.errors import BusError, ParameterError
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode
from qradar import security
from qradar.cli import main
from qradar.view import FoxgloveView, ViewConfig
from radar_driver.scene import resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource
from replay.recorder import RecorderNode
from zenoh_helpers import QRADAR, free_port, wait_port, wait_until

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="makes certificates with openssl")

#: each node kind, the identity it speaks as, and how to make one on ``bus``
NODE_KINDS = {
    "source": ("sensor-s0", lambda bus, tmp: SourceNode(bus, SimulatedSource(SimSourceConfig(resolve_scene("single"), id_prefix="s")))),
    "quantize": ("quantizer", lambda bus, tmp: QuantizeNode(bus, QuantizerConfig())),
    "localize": ("localizer", lambda bus, tmp: LocalizeNode(bus, LocalizerConfig(k=1))),
    "record": ("recorder", lambda bus, tmp: RecorderNode(bus, tmp / f"r{time.monotonic_ns()}.mcap")),
    "view": ("viewer", lambda bus, tmp: FoxgloveView(bus, ViewConfig(port=0))),
}
NON_ROUTERS = ("sensor-s0", "sensor-s1", "quantizer", "localizer", "recorder", "viewer")


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    """``lab``: a pipeline's identities as `security init` makes them now (only the router
    names hosts); ``old``: the same CA with every other identity issued again naming
    localhost and 127.0.0.1, as before that rule (or as a stolen key signed so)."""
    root = tmp_path_factory.mktemp("routerid")
    lab, old = root / "lab", root / "old"
    security.init(lab, ["s0", "s1"])
    shutil.copytree(lab, old)
    for ident in Policy.load(old).identities:
        if ident.role != "router":
            security.issue(old, Identity(ident.name, ident.role, ident.sensors, security.DEFAULT_HOSTS))
    return lab, old


def impostor(directory: Path, name: str, port: int) -> zenoh.Session:
    """A zenoh router with ``name``'s certificate on 127.0.0.1:port (opened as an
    attacker would, without qradar's own checks)."""
    return zenoh.open(BusConfig(mode="router", listen=(f"tls/127.0.0.1:{port}",),
                                secure=SecureConfig(directory, name)).zenoh_config())


def client(lab: Path, identity: str, port: int, mode: str = "client") -> BusConfig:
    return BusConfig(mode=mode, connect=(f"tls/127.0.0.1:{port}",), secure=SecureConfig(lab, identity))


def test_host_names_go_on_router_identities_only(dirs, tmp_path, capsys):
    lab, _ = dirs
    for role, extra in (("sensor", ["--id", "s7"]), ("quantizer", []), ("viewer", ["--id", "v2"])):
        assert main(["security", "add", str(lab), "--role", role, *extra, "--host", "10.0.0.7"]) == 2
        err = capsys.readouterr().err.strip()
        assert "go on a router identity only" in err and "\n" not in err, err
    assert Policy.load(lab).get("sensor-s7") is None and not (lab / "sensor-s7.pem").exists()  # nothing issued
    with pytest.raises(ParameterError, match="router identity only"):
        security.add(lab, Identity("recorder-2", "recorder", hosts=("rec.lab",)))
    # a second router (another host that serves others) may name its hosts
    copy = tmp_path / "lab"
    shutil.copytree(lab, copy)
    ident = security.add(copy, Identity("router-b", "router", hosts=("10.0.0.9",)))
    assert ident.hosts == ("localhost", "127.0.0.1", "10.0.0.9")


def test_security_check_lists_names_and_flags_any_but_a_router_naming_hosts(dirs, capsys):
    lab, old = dirs
    assert main(["security", "check", str(lab)]) == 0
    out = capsys.readouterr().out
    assert "none but a router's names hosts" in out and "FLAGGED" not in out
    assert "router" in out and "hosts localhost, 127.0.0.1" in out and "sensor-s0" in out
    assert main(["security", "check", str(old), "--json"]) == 1
    found = {c["name"]: c for c in json.loads(capsys.readouterr().out)}
    assert set(found) == {"router", *NON_ROUTERS}
    assert not found["router"]["problems"] and found["router"]["hosts"] == ["localhost", "127.0.0.1"]
    for name in NON_ROUTERS:  # every one flagged, with its names and the way out
        c = found[name]
        assert c["common_name"] == name and c["unit"] == c["role"] and c["hosts"] == ["localhost", "127.0.0.1"]
        assert len(c["problems"]) == 1 and "can pose as the router" in c["problems"][0], c
        assert f"security remove {old} {name}" in c["problems"][0]


def test_an_impostor_router_is_refused_by_every_node_kind(dirs, tmp_path):
    """Each non-router identity as the router, without host names (zenoh's TLS refuses:
    the certificate names no host dialled) and with them (the node's own check refuses:
    not a router identity), met by each node kind as a zenoh client (and a quantize node as
    a peer, and a router identity dialling it, by the impostors that name hosts). Each
    refusal is one BusError line."""
    lab, old = dirs
    refused = {}
    cases = [(directory, hosts, name, free_port()) for directory, hosts in ((lab, False), (old, True))
             for name in NON_ROUTERS]
    with ThreadPoolExecutor(len(cases)) as pool:  # a router takes 0.5 s to open: all at once
        imps = list(pool.map(lambda c: impostor(c[0], c[2], c[3]), cases))
    try:
        for _, hosts, name, port in cases:
            wait_port(port)
            for kind, (identity, make) in NODE_KINDS.items():
                for mode in ("client", "peer") if hosts and kind == "quantize" else ("client",):
                    with pytest.raises(BusError) as exc:
                        node = make(client(lab, identity, port, mode), tmp_path)
                        node.stop()  # not reached: the node's session refuses the impostor
                    line = str(exc.value)
                    assert "\n" not in line
                    if hosts:
                        assert f"presents the certificate of {name!r}, not a router identity" in line, line
                    else:
                        assert "cannot open zenoh session" in line and "only the router's own" in line, line
                    refused[(name, hosts, kind, mode)] = True
            if hosts:  # a router identity that dials (qradar run --connect, routers joined) checks whom too
                with pytest.raises(BusError, match=f"presents the certificate of {name!r}"):
                    client(lab, "router", port, "peer").open().close()
    finally:
        for imp in imps:
            imp.close()
    assert len(refused) == len(NON_ROUTERS) * (2 * len(NODE_KINDS) + 1)


def test_the_real_router_is_accepted_and_an_impostor_after_it_is_refused(dirs, tmp_path):
    """A quantize node joined to the router; the router goes away and a sensor's old
    certificate (naming the host) takes its address: the node refuses it when it
    reconnects, closes its session (nothing more goes to the impostor) and its error ends
    it; its first session reached the real router."""
    lab, old = dirs
    port = free_port()
    router = BusConfig(mode="router", listen=(f"tls/127.0.0.1:{port}",), secure=SecureConfig(lab, "router")).open()
    imp = None
    q = QuantizeNode(client(lab, "quantizer", port), QuantizerConfig()).start()
    try:
        assert [link.auth_identifier for link in q.session.info.links()] == ["router"]
        # what the check reads where zenoh-python has no SessionInfo.links : the same
        assert [(str(link["dst"]), link["auth_identifier"]) for link in admin_links(q.session)] == \
            [(str(link.dst), link.auth_identifier) for link in q.session.info.links()]
        assert not q.errors
        router.close()
        imp = impostor(old, "sensor-s1", port)
        wait_until(lambda: q.errors, 20, "the node to refuse the impostor it reconnected to")
        assert isinstance(q.errors[0], BusError) and "'sensor-s1', not a router identity" in str(q.errors[0])
        wait_until(lambda: q.session.is_closed(), 10, "the node's session closed")
    finally:
        q.stop()
        if imp is not None:
            imp.close()


def test_commands_refuse_an_impostor_naming_the_host_in_one_line(dirs):
    """The issue's case: a sensor certificate naming the router's hosts, started as the
    router on the endpoint the nodes dial: quantize, localize and source end at once,
    status 2, with one line."""
    lab, old = dirs
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    imp = impostor(old, "sensor-s1", port)
    try:
        wait_port(port)
        for args in (("quantize",), ("localize", "--K", "1"), ("source", "--id-prefix", "s", "--frames", "3")):
            out = subprocess.run([*QRADAR, *args, "--secure", str(lab), "--mode", "client",
                                  "--connect", ep, "--duration", "20"], capture_output=True, text=True, timeout=60)
            line = out.stderr.strip()
            assert out.returncode == 2 and "\n" not in line, (args[0], out.stderr)
            assert "'sensor-s1', not a router identity" in line, line
    finally:
        imp.close()


def test_a_publisher_the_policy_denies_says_so_in_one_line(dirs):
    """A source speaking as sensor-s1 publishes sensor s0's frames through the real router
    under --secure: the router would drop every put, so none is sent; the source says so in
    one line and its summary counts them in denied_puts, not as frames sent; a subscriber
    sees none. The same source speaking as sensor-s0 sends all 20."""
    lab, _ = dirs
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    router = BusConfig(mode="router", listen=(ep,), secure=SecureConfig(lab, "router")).open()
    viewer = client(lab, "viewer", port).open()
    got = []
    sub = viewer.declare_subscriber("radar/*/raw", lambda s: got.append(str(s.key_expr)))
    try:
        runs = {}
        for identity in ("sensor-s1", "sensor-s0"):
            out = subprocess.run([*QRADAR, "source", "--secure", str(lab), "--identity",
                                  identity, "--mode", "client", "--connect", ep, "--id-prefix", "s", "--frames",
                                  "20", "--rate", "100"], capture_output=True, text=True, timeout=60)
            assert out.returncode == 0, out.stderr
            runs[identity] = (json.loads(out.stdout.strip().splitlines()[-1]), out.stderr)
        denied, err = runs["sensor-s1"]
        assert denied["frames_out"] == 0 and denied["denied_puts"] >= 20, denied
        lines = [ln for ln in err.splitlines() if "denied" in ln]
        assert len(lines) == 1 and "access policy" in lines[0] and "'sensor-s1'" in lines[0], err
        assert "radar/s0/raw" in lines[0] and "counted in denied_puts" in lines[0]
        ok, err = runs["sensor-s0"]
        assert ok["frames_out"] == 20 and ok["denied_puts"] == 0 and "access policy" not in err
        wait_until(lambda: len(got) == 20, 10, "the 20 frames the policy allows")
        assert set(got) == {"radar/s0/raw"}
    finally:
        sub.undeclare()
        viewer.close()
        router.close()
