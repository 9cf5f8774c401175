"""``qradar ports``: the serial adapters of this host and, with ``--probe``, which of them
answer as a K-MD2 (:mod:`radar_driver.ports`)."""

from __future__ import annotations

import json
from dataclasses import dataclass

from radar_driver import ports
from radar_driver.ports import PROBE_TIMEOUT_S, PROBE_WORKERS, PortInfo, ProbeResult
from radar_driver.options import like, option, pos_float
from radar_driver.session import SessionConfig

from .parts import switches
from .schema import Part, add_command


@dataclass(frozen=True)
class Ports:
    """What ``qradar ports`` probes, and how long it waits."""

    probe: tuple[str, ...] | None = option(None, "write INIT and GBYE to each listed adapter (or to the ports and URLs "
                                           "given) and say which answer as a K-MD2; without --probe nothing is "
                                           "written", many="*", metavar="PORT_OR_URL")
    timeout: float = option(PROBE_TIMEOUT_S, "seconds a probe waits for the RESP to INIT (a silent serial port waits "
                            "twice: once more after resetting a sensor left at another speed)", parse=pos_float)
    profile: str | None = like(SessionConfig, "profile")


def add_commands(sub) -> None:
    add_command(sub, "ports", [Part(Ports), switches(json="print one JSON object: the ports (and probe answers)")],
                cmd_ports, help="the serial adapters of this host; with --probe, which answer as a K-MD2",
                description=DESCRIPTION)


DESCRIPTION = ("Lists the serial adapters pyserial finds (device, USB VID:PID, serial number,\n"
               "manufacturer, description). Without --probe nothing is written to any port.\n\n"
               "--probe WRITES TO EACH PROBED PORT: INIT (asking for the start-up 115200 baud, so no\n"
               "speed switch) and GBYE, the same bytes a session starts and ends with (and, if no RESP\n"
               "comes, GBYE at the other line speeds and a second INIT, for a sensor a crashed host left\n"
               "at another speed). GNFD is never sent: no measurement starts, and a K-MD2 is left at\n"
               "115200. Probed: every listed adapter, or the ports and URLs given (a device path,\n"
               f"socket://HOST:PORT, rfc2217://HOST:PORT), {PROBE_WORKERS} at a time. Each is reported as\n"
               "K-MD2 (it answered INIT with a RESP), not a K-MD2 (bytes came, no RESP: an echo,\n"
               "text, another protocol), silent, busy (held by another program, e.g. a running\n"
               "`qradar run`: its lock is checked first, so the port is neither configured nor\n"
               "written), permission denied, or cannot open; with one line why. Exit status with\n"
               "--probe: 0 when a K-MD2 answered, 1 when none did.")


def table(rows: list[list[str]]) -> str:
    """Rows of cells as left-aligned columns (the last column as it is)."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join([c.ljust(w) for c, w in zip(r, widths)] + [r[-1]]).rstrip() for r in rows)


def cmd_ports(args) -> int:
    listed = ports.list_serial_ports()
    if args.probe is None:
        return show_ports(listed, args.json)
    urls = args.probe or [p.device for p in listed]
    results = ports.probe_ports(urls, profile=args.profile, timeout_s=args.timeout, listed=listed)
    show_probes(results, args.json, given=bool(args.probe))
    return 0 if any(r.is_kmd2 for r in results) else 1


def show_ports(listed: list[PortInfo], as_json: bool) -> int:
    if as_json:
        print(json.dumps({"ports": [p.to_dict() for p in listed]}))
        return 0
    if not listed:
        print("no serial adapter found (a USB-UART shows up as /dev/ttyUSB<n>, a CDC-ACM device as /dev/ttyACM<n>: "
              "is it plugged in? docs/chamber.md, section 1)")
        return 0
    rows = [["DEVICE", "VID:PID", "SERIAL", "MANUFACTURER", "DESCRIPTION"]]
    rows += [[p.device, p.vid_pid or "-", p.serial_number or "-", p.manufacturer or "-", p.description or "-"]
             for p in listed]
    print(table(rows))
    print(f"{len(listed)} serial adapter(s); nothing was written to them (`qradar ports --probe` asks which "
          f"answer as a K-MD2)")
    return 0


def show_probes(results: list[ProbeResult], as_json: bool, given: bool) -> None:
    kmd2 = [r for r in results if r.is_kmd2]
    if as_json:
        out = []
        for r in results:
            entry = r.port.to_dict() if r.port is not None else PortInfo(r.url).to_dict()
            out.append({**entry, "url": r.url, "probe": r.to_dict()})
        print(json.dumps({"ports": out, "kmd2": [r.url for r in kmd2]}))
        return
    if not results:
        print("no serial adapter found to probe (name one: `qradar ports --probe /dev/ttyUSB0` or a "
              "socket:// or rfc2217:// URL)")
        return
    rows = [["PORT", "VID:PID", "SERIAL", "ANSWER", "WHY"]]
    for r in results:
        info = r.port or PortInfo(r.url)
        rows.append([r.url, info.vid_pid or "-", info.serial_number or "-", r.answer.words, r.reason])
    print(table(rows))
    if len(kmd2) == 1:
        print(f"one K-MD2: {kmd2[0].name}; use it with --sensor {kmd2[0].url},id=NAME"
              + ("" if given else " or --sensor auto,id=NAME"))
    elif kmd2:
        print(f"{len(kmd2)} K-MD2s: {', '.join(r.url for r in kmd2)}; give each its --sensor URL,id=NAME")
    else:
        print(f"no K-MD2 answered on the {len(results)} port(s) probed")
