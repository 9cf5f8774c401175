"""``qradar security``: the certificates and policy of ``--secure`` (:mod:`qradar.security`)."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from pipeline.bus.security import CA_KEY, POLICY_FILE, ROLES, Identity, Policy
from pipeline.errors import ParameterError
from radar_driver.options import OptionValueError, option, pos_int

from .. import security
from .common import DefaultsFormatter
from .parts import switches
from .schema import Part, add_command


def names(text: str) -> list[str]:
    """``a,b`` -> [a, b] (repeated options add up)."""
    out = [t.strip() for t in text.split(",") if t.strip()]
    if not out:
        raise OptionValueError("names nothing")
    return out


DIR_HELP = "a folder made by `qradar security init`"
JSON_HELP = "print the identities as JSON"


@dataclass(frozen=True)
class Folder:
    """The folder of the CA, the identities and the policy."""

    dir: Path = option(help=DIR_HELP, positional=True, required=True)


@dataclass(frozen=True)
class Certs:
    """What a new certificate says and how long it lasts."""

    host: tuple[str, ...] = option((), "a DNS name or IP address the router's certificate is valid for (repeat; "
                                   "localhost and 127.0.0.1 always); router identities only: any other is a client and "
                                   "names no host", many="append", metavar="NAME|IP")
    days: int = option(security.DEFAULT_DAYS, "validity of a certificate in days", parse=pos_int)


@dataclass(frozen=True)
class Init:
    """``security init``."""

    dir: Path = option(security.DEFAULT_DIR, f"the folder to create: CA, identities.json, one NAME.pem + NAME.key "
                       f"each (default {security.DEFAULT_DIR}, outside any checkout; a folder in a git checkout "
                       "should be one its .gitignore covers, as lab-pki/ is qradar's)", positional=True)
    sensors: tuple[str, ...] | None = option(None, "sensor ids, one sensor identity each (default: sim0, the first "
                                             "of `qradar source`)", many="extend", parse=names, metavar="ID[,ID...]")
    ca_days: int = option(security.CA_DAYS, "validity of the CA in days", parse=pos_int)
    force: bool = option(False, "replace a CA (and every identity) already in DIR")


@dataclass(frozen=True)
class Add:
    """``security add``."""

    role: str = option(help="what the identity may publish and subscribe", choices=ROLES, required=True)
    id: tuple[str, ...] | None = option(None, "sensor role: the sensor id(s) it publishes; other roles: a label, the "
                                        "name becomes <role>-<id>", many="extend", parse=names, metavar="ID[,ID...]")
    sensors: tuple[str, ...] | None = option(None, "quantizer or localizer: only these sensors (default: every "
                                             "sensor)", many="extend", parse=names, metavar="ID[,ID...]")
    name: str | None = option(None, "the identity's name (certificate common name); default from role and id")


@dataclass(frozen=True)
class Remove:
    """``security remove``."""

    name: str = option(help="the identity's name, as `qradar security list` shows it", positional=True,
                       required=True)


@dataclass(frozen=True)
class Listing:
    """``security list``."""

    prefix: str = option("radar", "key prefix")


def add_commands(sub) -> None:
    p = sub.add_parser("security", help="certificates and access policy for --secure (mTLS + zenoh access control)",
                       description="A certificate authority of your own and one certificate per node identity, "
                       "for --secure DIR on every node and the router. The CA key (ca.key) stays on the machine "
                       "that runs init; another host gets ca.pem, identities.json and its own NAME.pem, NAME.key.")
    ss = p.add_subparsers(dest="action", required=True, metavar="{init,add,remove,list,check}")
    json_part = switches(json=JSON_HELP)
    add_command(ss, "init", [Part(Init, only=("dir", "sensors")), Part(Certs), json_part,
                             Part(Init, only=("ca_days", "force"))], cmd_init,
                help="a new CA and the identities router, sensor-<id>, quantizer, localizer, recorder, viewer")
    add_command(ss, "add", [Part(Folder), Part(Add), Part(Certs), json_part], cmd_add,
                help="issue one more identity with the CA of DIR (restart the router to apply)")
    add_command(ss, "remove", [Part(Folder), Part(Remove)], cmd_remove,
                help="withdraw an identity from the policy of DIR (restart the router to apply)")
    add_command(ss, "list", [Part(Folder), Part(Listing), json_part], cmd_list,
                help="the identities of DIR and what each may publish")
    add_command(ss, "check", [Part(Folder), switches(json="print the findings as JSON")], cmd_check,
                help="every certificate's names and role; flags any but a router's naming hosts",
                description="Lists, per identity of DIR, the common name, role and host names of its certificate, "
                "and flags what could pose as the router (an identity other than a router's whose certificate names "
                "hosts: made before `security add` refused that) or contradicts the policy. Exit status 1 when "
                "anything is flagged.")
    for q in ss.choices.values():  # as build_parser does for the first level
        q.formatter_class = DefaultsFormatter
        q.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                       help="debug logging, tracebacks on errors")


def cmd_init(args) -> int:
    directory = Path(args.dir).expanduser()
    policy = security.init(directory, args.sensors or ["sim0"], args.host, days=args.days, ca_days=args.ca_days,
                           force=args.force)
    _show(args, policy.identities, f"made a CA and {len(policy.identities)} identities in {directory}")
    key = (directory / CA_KEY).resolve()
    print(f"the CA's private key is {key}: it signs every identity, so keep it on this machine only (another host "
          f"gets ca.pem, {POLICY_FILE} and its own NAME.pem, NAME.key)", file=sys.stderr)
    checkout = security.git_exposure(directory)
    if checkout is not None:
        print(f"warning: {directory} is inside the git checkout {checkout} and no .gitignore covers it: the CA's "
              f"private key could be committed; add {directory.name}/ to .gitignore or move it out", file=sys.stderr)
    return 0


def cmd_add(args) -> int:
    role = args.role
    if role == "sensor":
        if not args.id:
            raise ParameterError("a sensor identity needs --id SENSOR_ID (the sensor it publishes)")
        if args.sensors:
            raise ParameterError("--sensors is for quantizer and localizer identities; a sensor's ids are --id")
        sensors, default = tuple(args.id), f"sensor-{args.id[0]}"
    else:
        if args.id is not None and len(args.id) > 1:
            raise ParameterError(f"a {role} identity takes one --id label, not {args.id}")
        sensors = tuple(args.sensors or ())
        default = f"{role}-{args.id[0]}" if args.id else role
    ident = security.add(args.dir, Identity(args.name or default, role, sensors, tuple(args.host)), days=args.days)
    _show(args, [ident], f"issued {ident.name} in {args.dir}; copy ca.pem, {POLICY_FILE}, {ident.name}.pem and "
          f"{ident.name}.key to its host, {POLICY_FILE} to the router's, and restart the router")
    return 0


def cmd_remove(args) -> int:
    security.remove(args.dir, args.name)
    print(f"removed {args.name} from {args.dir / POLICY_FILE}; copy it to the router's host and restart the router")
    return 0


def cmd_list(args) -> int:
    policy = Policy.load(args.dir)
    _show(args, policy.identities, f"{len(policy.identities)} identities in {args.dir}"
          + ("" if (Path(args.dir) / CA_KEY).exists() else " (no CA key here: add issues nothing)"))
    return 0


def cmd_check(args) -> int:
    found = security.check(args.dir)
    flagged = [c for c in found if c.problems]
    if args.json:
        print(json.dumps([c.to_dict() for c in found]))
        return 1 if flagged else 0
    print(f"{len(found)} certificates in {args.dir}: "
          + (f"{len(flagged)} flagged" if flagged else "none but a router's names hosts"))
    for c in found:
        hosts = "not on this host" if c.hosts is None else ("hosts " + ", ".join(c.hosts) if c.hosts else "no hosts")
        print(f"  {c.name:<20} {c.role:<10} CN={c.common_name or '?'}; {hosts}"
              + "".join(f"\n    FLAGGED: {p}" for p in c.problems))
    return 1 if flagged else 0


def _show(args, idents, head: str) -> None:
    prefix = getattr(args, "prefix", "radar")
    if args.json:
        print(json.dumps([{**i.to_dict(), "publishes": i.publishes(prefix)} for i in idents]))
        return
    print(head)
    for i in idents:
        print(f"  {i.name:<20} {i.role:<10} publishes {', '.join(i.publishes(prefix))}; hosts {', '.join(i.hosts)}; "
              f"expires {i.not_after or '?'}")
