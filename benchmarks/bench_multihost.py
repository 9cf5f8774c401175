#!/usr/bin/env python3
"""The chain across three "hosts": network namespaces this benchmark creates (as root) and
always deletes.

    qr-sensor-XXXX  10.A.B.2  ── veth ──  10.A.B.1    qr-router-XXXX   10.A.B+1.1 ── veth ── 10.A.B+1.2  qr-loc-XXXX
    qradar source [--quantized]           qradar router --listen both               qradar localize [--shard i/n] ...
    (central: + qradar quantize)                                                    the sink (radar/*/targets)

Every node is a zenoh client of the router; nothing routes between the two links but
zenoh. ``--netem-delay-ms 0.2`` adds that delay to every veth end (a LAN's). The figures
are bench_stream's (frames lost, latency p50/p99/max, CPU per process), for each
``--localizers`` count (1 2 by default: sharded by ``--shard i/n``).

    sudo .venv/bin/python benchmarks/bench_multihost.py --sensors 100 --seconds 30
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import streamlib as sl

PORT = 7447
#: where each role runs: the sensor host, the router, the localizer host
ROLE_HOST = {"source": "sensor", "quantize": "sensor", "router": "router", "localize": "loc", "sink": "loc"}


class NetnsError(RuntimeError):
    pass


def ip(*args: str, ns: str | None = None) -> None:
    cmd = (["ip", "netns", "exec", ns] if ns else []) + list(args)
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=20)
    if r.returncode != 0:
        raise NetnsError(f"{' '.join(cmd)}: {r.stderr.strip() or r.returncode}")


def netns_list() -> list[str]:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=20).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


class Netns(sl.Topology):
    """Three namespaces joined at the router's by two veth pairs; a context manager that
    deletes them (and so their interfaces) on exit, whatever happened."""

    def __init__(self, netem_delay_ms: float | None = None):
        tag = secrets.token_hex(2)
        self.ns = {h: f"qr-{h}-{tag}" for h in ("sensor", "router", "loc")}
        a, b = 100 + secrets.randbelow(150), 2 * secrets.randbelow(100)
        self.net = {"sensor": f"10.{a}.{b}", "loc": f"10.{a}.{b + 1}"}
        self.veth = {h: (f"qr{h[0]}{tag}h", f"qr{h[0]}{tag}r") for h in ("sensor", "loc")}  # (host end, router end)
        self.netem_delay_ms = netem_delay_ms
        self.created: list[str] = []

    def __enter__(self) -> "Netns":
        try:
            for name in self.ns.values():
                ip("ip", "netns", "add", name)
                self.created.append(name)
                ip("ip", "link", "set", "lo", "up", ns=name)
            for h, (host_if, router_if) in self.veth.items():
                ip("ip", "link", "add", host_if, "netns", self.ns[h], "type", "veth", "peer", "name", router_if,
                   "netns", self.ns["router"])
                for ns, ifname, addr in ((self.ns[h], host_if, 2), (self.ns["router"], router_if, 1)):
                    ip("ip", "addr", "add", f"{self.net[h]}.{addr}/24", "dev", ifname, ns=ns)
                    ip("ip", "link", "set", ifname, "up", ns=ns)
                    if self.netem_delay_ms:
                        try:
                            ip("tc", "qdisc", "add", "dev", ifname, "root", "netem", "delay",
                               f"{self.netem_delay_ms}ms", ns=ns)
                        except NetnsError as exc:
                            raise NetnsError(f"--netem-delay-ms: {exc} (the kernel lacks sch_netem?)") from None
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for name in reversed(self.created):
            subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=20)
        self.created = []

    def left(self) -> list[str]:
        """Our namespaces that still exist."""
        return [n for n in netns_list() if n in self.ns.values()]

    # -- Topology ----------------------------------------------------------------------------
    def prefix(self, role: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns[ROLE_HOST[role]]]

    def listen(self, role: str) -> list[str]:
        if role != "router":
            raise NetnsError(f"only the router listens here, not {role}")
        return [f"tcp/{self.net[h]}.1:{PORT}" for h in ("sensor", "loc")]

    def connect(self, role: str) -> str:
        return f"tcp/{self.net['loc' if ROLE_HOST[role] == 'loc' else 'sensor']}.1:{PORT}"


def check_can_run() -> str | None:
    """Why this benchmark cannot run here, or None."""
    if os.geteuid() != 0:
        return "needs root (network namespaces)"
    if shutil.which("ip") is None:
        return "needs the `ip` command (iproute2)"
    return None


def run(args) -> dict:
    """Every step in fresh namespaces; the rows and what was left behind."""
    rows, left = [], []
    for n_loc in args.localizers:
        for n in args.sensors:
            spec = sl.StepSpec(case=args.case, send=args.send, algo=args.algo, sensors=n, seconds=args.seconds,
                               warmup_s=args.warmup, localizers=n_loc, alpha=args.alpha, hub="router")
            label = f"{args.case}/{args.send}/{args.algo} {n_loc} localizer{'s' if n_loc > 1 else ''}"
            with Netns(args.netem_delay_ms) as topo:
                r = {"label": label, "namespaces": list(topo.ns.values()), "netem_delay_ms": args.netem_delay_ms,
                     **sl.run_step(spec, topo, progress=sys.stderr.isatty())}
            r["namespaces_left"] = topo.left()
            left += r["namespaces_left"]
            rows.append(r)
            print(sl.step_line(r), file=sys.stderr, flush=True)
    return {"steps": rows, "namespaces_left": left}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", choices=["central", "edge"], default="edge",
                    help="edge: the sensor host publishes 1-bit frames; central: raw, quantized on the sensor host")
    ap.add_argument("--send", choices=["burst", "spread"], default="burst")
    ap.add_argument("--algo", choices=["pbp", "qiht", "cml"], default="pbp")
    ap.add_argument("--sensors", type=int, nargs="+", default=[100])
    ap.add_argument("--localizers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--warmup", type=float, default=5.0)
    ap.add_argument("--alpha", type=float, default=1.0)
    ap.add_argument("--netem-delay-ms", type=float, default=None, help="add this delay on every veth end (e.g. 0.2)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    why = check_can_run()
    if why:
        sys.exit(f"bench_multihost: {why}")
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))  # clean up as on Ctrl-C
    result = run(args)
    print(sl.markdown(sl.STEP_COLUMNS[:-1], [sl.step_cells(r)[:-1] for r in result["steps"]]))
    print(f"\nnamespaces left after the run: {result['namespaces_left'] or 'none'}")
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1))
    if result["namespaces_left"]:
        sys.exit(1)


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        sys.exit("interrupted: every process stopped" + (" and every namespace deleted" if "multihost" in __file__
                                                         else ""))
