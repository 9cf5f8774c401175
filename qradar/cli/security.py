"""``qradar security``: the certificates and policy of ``--secure`` (:mod:`qradar.security`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.errors import ParameterError
from pipeline.bus.security import CA_KEY, POLICY_FILE, ROLES, Identity, Policy

from .. import security
from .common import DefaultsFormatter, pos_int


def names(text: str) -> list[str]:
    """``a,b`` -> [a, b] (with action=extend, also repeated options)."""
    out = [t.strip() for t in text.split(",") if t.strip()]
    if not out:
        raise argparse.ArgumentTypeError(f"{text!r} names nothing")
    return out


def add_commands(sub) -> None:
    p = sub.add_parser("security", help="certificates and access policy for --secure (mTLS + zenoh access control)",
                       description="A certificate authority of your own and one certificate per node identity, "
                       "for --secure DIR on every node and the router. The CA key (ca.key) stays on the machine "
                       "that runs init; another host gets ca.pem, identities.json and its own NAME.pem, NAME.key.")
    ss = p.add_subparsers(dest="action", required=True, metavar="{init,add,remove,list,check}")

    q = ss.add_parser("init", help="a new CA and the identities router, sensor-<id>, quantizer, localizer, recorder, "
                      "viewer")
    q.add_argument("dir", type=Path, nargs="?", default=security.DEFAULT_DIR,
                   help="the folder to create: CA, identities.json, one NAME.pem + NAME.key each (default "
                   f"{security.DEFAULT_DIR}, outside any checkout; a folder in a git checkout should be one its "
                   ".gitignore covers, as lab-pki/ is qradar's)")
    q.add_argument("--sensors", type=names, action="extend", default=None, metavar="ID[,ID...]",
                   help="sensor ids, one sensor identity each (default: sim0, the first of `qradar source`)")
    _cert_options(q)
    q.add_argument("--ca-days", type=pos_int, default=security.CA_DAYS, help="validity of the CA in days")
    q.add_argument("--force", action="store_true", help="replace a CA (and every identity) already in DIR")
    q.set_defaults(func=cmd_init)

    q = ss.add_parser("add", help="issue one more identity with the CA of DIR (restart the router to apply)")
    q.add_argument("dir", type=Path, help="a folder made by `qradar security init`")
    q.add_argument("--role", choices=ROLES, required=True, help="what the identity may publish and subscribe")
    q.add_argument("--id", type=names, action="extend", default=None, metavar="ID[,ID...]",
                   help="sensor role: the sensor id(s) it publishes; other roles: a label, the name becomes "
                   "<role>-<id>")
    q.add_argument("--sensors", type=names, action="extend", default=None, metavar="ID[,ID...]",
                   help="quantizer or localizer: only these sensors (default: every sensor)")
    q.add_argument("--name", default=None, help="the identity's name (certificate common name); default from "
                   "role and id")
    _cert_options(q)
    q.set_defaults(func=cmd_add)

    q = ss.add_parser("remove", help="withdraw an identity from the policy of DIR (restart the router to apply)")
    q.add_argument("dir", type=Path, help="a folder made by `qradar security init`")
    q.add_argument("name", help="the identity's name, as `qradar security list` shows it")
    q.set_defaults(func=cmd_remove)

    q = ss.add_parser("list", help="the identities of DIR and what each may publish")
    q.add_argument("dir", type=Path, help="a folder made by `qradar security init`")
    q.add_argument("--prefix", default="radar", help="key prefix")
    q.add_argument("--json", action="store_true", help="print the identities as JSON")
    q.set_defaults(func=cmd_list)

    q = ss.add_parser("check", help="every certificate's names and role; flags any but a router's naming hosts",
                      description="Lists, per identity of DIR, the common name, role and host names of its "
                      "certificate, and flags what could pose as the router (an identity other than a router's "
                      "whose certificate names hosts: made before `security add` refused that) or contradicts "
                      "the policy. Exit status 1 when anything is flagged.")
    q.add_argument("dir", type=Path, help="a folder made by `qradar security init`")
    q.add_argument("--json", action="store_true", help="print the findings as JSON")
    q.set_defaults(func=cmd_check)
    for q in ss.choices.values():  # as build_parser does for the first level
        q.formatter_class = DefaultsFormatter
        q.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                       help="debug logging, tracebacks on errors")


def _cert_options(q) -> None:
    q.add_argument("--host", action="append", default=[], metavar="NAME|IP",
                   help="a DNS name or IP address the router's certificate is valid for (repeat; localhost and "
                   "127.0.0.1 always); router identities only: any other is a client and names no host")
    q.add_argument("--days", type=pos_int, default=security.DEFAULT_DAYS, help="validity of a certificate in days")
    q.add_argument("--json", action="store_true", help="print the identities as JSON")


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
