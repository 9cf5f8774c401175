"""Certificates for ``--secure``: a certificate authority of the project's own and one
certificate per identity, made with the ``openssl`` command (OpenSSL 1.1.1 or later).

``init`` makes the CA (``ca.pem``, ``ca.key``) and the identities of a pipeline —
``router``, ``sensor-<id>`` per sensor, ``quantizer``, ``localizer``, ``recorder``,
``viewer`` — and their policy (``identities.json``, see :mod:`pipeline.bus.security`);
``add`` issues one more with the CA key, ``remove`` withdraws one. Keys are EC P-256, written 0600 in a 0700
directory; the CA key never needs to leave the machine that issues certificates: a host
gets ``ca.pem``, ``identities.json`` and its own ``<name>.pem`` / ``<name>.key``.

A certificate names its hosts (subjectAltName: DNS names and IP addresses) so that a
node connecting to a listener can check the listener's name. Only the router's names
hosts (``--host`` and ``localhost``, ``127.0.0.1``); ``init`` and ``add`` refuse host names
on any other identity (a sensor, a quantizer, ... is a client and needs none): a node dials
the router and checks that its certificate names the host dialled and that its common
name is a router identity (:mod:`pipeline.bus.router_check`), so no other identity's key (a
stolen sensor's, the viewer's) can pose as the router. ``check`` lists every
certificate's names and role and flags any other identity that names hosts (issued
before this rule) or a certificate that contradicts the policy.
"""

from __future__ import annotations

import ipaddress
import os
import re
import secrets
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import BusError, ParameterError
from pipeline.bus.security import CA_CERT, CA_KEY, POLICY_FILE, Identity, Policy

DEFAULT_HOSTS = ("localhost", "127.0.0.1")
DEFAULT_DAYS = 365
CA_DAYS = 3650
_DNS = re.compile(r"(\*\.)?([A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?\.)*[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


def san_entry(host: str) -> str:
    """``IP:…`` for an address, ``DNS:…`` for a host name; anything else is an error."""
    try:
        return f"IP:{ipaddress.ip_address(host)}"
    except ValueError:
        pass
    if len(host) <= 253 and _DNS.fullmatch(host):
        return f"DNS:{host}"
    raise ParameterError(f"host {host!r} is neither an IP address nor a DNS name")


def _hosts(extra) -> tuple[str, ...]:
    out = list(DEFAULT_HOSTS)
    for h in extra:
        san_entry(h)
        if h not in out:
            out.append(h)
    return tuple(out)


def _openssl(*args: str, cwd: Path) -> str:
    exe = shutil.which("openssl")
    if exe is None:
        raise BusError("the openssl command is not installed (e.g. apt-get install openssl); "
                       "qradar security uses it to make certificates")
    proc = subprocess.run([exe, *args], cwd=cwd, capture_output=True, text=True, timeout=60)
    if proc.returncode != 0:
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        raise BusError(f"openssl {args[0]} failed in {cwd}: {lines[-1] if lines else f'exit code {proc.returncode}'}")
    return proc.stdout


def _new_key(path: Path) -> None:
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", path.name,
             cwd=path.parent)
    path.chmod(0o600)


def _serial() -> str:
    return "0x" + secrets.token_hex(15)


def make_ca(directory: Path, days: int = CA_DAYS) -> None:
    """``ca.key`` and a self-signed ``ca.pem`` (unique subject, so two CAs never look alike)."""
    _new_key(directory / CA_KEY)
    _openssl("req", "-x509", "-new", "-key", CA_KEY, "-sha256", "-days", str(days), "-set_serial", _serial(),
             "-subj", f"/O=qradar/CN=qradar CA {secrets.token_hex(4)}",
             "-addext", "basicConstraints=critical,CA:TRUE,pathlen:0",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", "-out", CA_CERT, cwd=directory)


def issue(directory: Path, ident: Identity, days: int = DEFAULT_DAYS) -> Identity:
    """``<name>.key`` and ``<name>.pem`` signed by the CA in ``directory``; returns the
    identity with its expiry filled in."""
    directory = Path(directory)
    for path in (directory / CA_CERT, directory / CA_KEY):
        if not path.is_file():
            raise BusError(f"{path} is missing: certificates are issued where `qradar security init` made the CA")
    name = ident.name
    ext = "\n".join([
        "basicConstraints=critical,CA:FALSE",
        "keyUsage=critical,digitalSignature",
        "extendedKeyUsage=serverAuth,clientAuth",
        "subjectKeyIdentifier=hash",
        "authorityKeyIdentifier=keyid",
        *(["subjectAltName=" + ",".join(san_entry(h) for h in ident.hosts)] if ident.hosts else []),
    ]) + "\n"
    _new_key(directory / f"{name}.key")
    with tempfile.TemporaryDirectory(prefix="qradar-csr-") as tmp:
        csr, extfile = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        extfile.write_text(ext)
        _openssl("req", "-new", "-key", f"{name}.key", "-subj", f"/O=qradar/OU={ident.role}/CN={name}",
                 "-out", str(csr), cwd=directory)
        _openssl("x509", "-req", "-in", str(csr), "-CA", CA_CERT, "-CAkey", CA_KEY, "-set_serial", _serial(),
                 "-days", str(days), "-sha256", "-extfile", str(extfile), "-out", f"{name}.pem", cwd=directory)
    end = _openssl("x509", "-in", f"{name}.pem", "-noout", "-enddate", cwd=directory).strip()
    return Identity(ident.name, ident.role, ident.sensors, ident.hosts, end.partition("=")[2])


def default_identities(sensors, hosts=()) -> list[Identity]:
    """The identities of one pipeline: a router, a sensor per id, one quantizer and one
    localizer serving every sensor, a recorder and a viewer."""
    return [Identity("router", "router", hosts=_hosts(hosts)),  # the only one naming the router's hosts
            *(Identity(f"sensor-{s}", "sensor", (s,)) for s in sensors),
            Identity("quantizer", "quantizer"), Identity("localizer", "localizer"),
            Identity("recorder", "recorder"), Identity("viewer", "viewer")]


#: where ``qradar security init`` makes its CA without a folder given: outside any checkout
DEFAULT_DIR = Path("~/.qradar-pki")


def init(directory: Path, sensors, hosts=(), days: int = DEFAULT_DAYS, ca_days: int = CA_DAYS,
         force: bool = False) -> Policy:
    """A new CA and the :func:`default_identities` in ``directory`` (made 0700 if missing,
    when its parent exists); refuses a directory that has a CA already unless ``force``
    (which replaces the CA and every identity)."""
    directory = Path(directory).expanduser()
    _check_days(days, ca_days)
    if not force and ((directory / CA_KEY).exists() or (directory / CA_CERT).exists()
                      or (directory / POLICY_FILE).exists()):
        raise BusError(f"{directory} has a CA already; add identities with `qradar security add {directory} ...`, "
                       "choose another directory, or replace it with --force")
    idents = default_identities(sensors, hosts)
    Policy(tuple(idents))  # duplicate names (a sensor id given twice) before anything is written
    if not directory.parent.is_dir():
        raise BusError(f"cannot make {directory}: {directory.parent} does not exist (qradar makes only its output's "
                       "own folder)")
    try:
        directory.mkdir(mode=0o700, exist_ok=True)
        os.chmod(directory, 0o700)
    except OSError as exc:
        raise BusError(f"cannot make {directory}: {exc.strerror}") from None
    make_ca(directory, ca_days)
    policy = Policy(tuple(issue(directory, i, days) for i in idents))
    policy.save(directory)
    return policy


def git_exposure(path: Path) -> str | None:
    """The git checkout ``path`` lies in when no ``.gitignore`` covers it (its files could be
    committed), else None (outside a checkout, ignored there, or no ``git`` to ask)."""
    path = Path(path).resolve()
    try:
        top = subprocess.run(["git", "-C", str(path), "rev-parse", "--show-toplevel"], capture_output=True, text=True,
                             timeout=10)
        if top.returncode != 0:
            return None  # not in a work tree
        ignored = subprocess.run(["git", "-C", str(path), "check-ignore", "-q", str(path / CA_KEY)],
                                 capture_output=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return None if ignored.returncode == 0 else top.stdout.strip()


def check_hosts(ident: Identity) -> None:
    """Host names go on a router identity only (ParameterError otherwise, naming why)."""
    if ident.hosts and ident.role != "router":
        raise ParameterError(f"identity {ident.name!r}: host names ({', '.join(ident.hosts)}) go on a router "
                             f"identity only: a {ident.role} is a client of the router and needs none, and a "
                             f"certificate naming a host could pose as the router there; drop --host (a host "
                             f"that serves others runs `qradar router`, with an identity of --role router)")


def add(directory: Path, ident: Identity, days: int = DEFAULT_DAYS) -> Identity:
    """Issue one more identity with the CA in ``directory`` and add it to the policy
    (host names only on a router identity: :func:`check_hosts`)."""
    directory = Path(directory)
    _check_days(days, days)
    check_hosts(ident)
    policy = Policy.load(directory)
    policy.with_identity(ident)  # refuses an existing name before a key is overwritten
    hosts = _hosts(ident.hosts) if ident.role == "router" else ()  # see the module's docstring
    ident = Identity(ident.name, ident.role, ident.sensors, hosts)
    issued = issue(directory, ident, days)
    policy.with_identity(issued).save(directory)
    return issued


@dataclass(frozen=True)
class CertificateCheck:
    """What ``security check`` finds of one identity: its ``role`` in the policy, the
    certificate's ``common_name``, ``unit`` (the role it was issued for) and ``hosts``
    (subjectAltName) — None when its certificate is not on this host — and ``problems``."""

    name: str
    role: str
    common_name: str | None = None
    unit: str | None = None
    hosts: tuple[str, ...] | None = None
    problems: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        return {"name": self.name, "role": self.role, "common_name": self.common_name, "unit": self.unit,
                "hosts": None if self.hosts is None else list(self.hosts), "problems": list(self.problems)}


def _certificate(path: Path) -> tuple[str | None, str | None, tuple[str, ...]]:
    """(common name, organizational unit, subjectAltName entries) of a PEM certificate."""
    text = _openssl("x509", "-in", path.name, "-noout", "-subject", "-ext", "subjectAltName", "-nameopt",
                    "sep_multiline,sname", cwd=path.parent)
    cn = re.search(r"^\s*CN=(.*)$", text, re.M)
    ou = re.search(r"^\s*OU=(.*)$", text, re.M)
    san = re.search(r"Subject Alternative Name:.*\n\s*(.+)", text)
    hosts = tuple(h.strip().split(":", 1)[1].strip() for h in san.group(1).split(",")) if san else ()
    return (cn.group(1).strip() if cn else None), (ou.group(1).strip() if ou else None), hosts


def check(directory: Path) -> list[CertificateCheck]:
    """Every identity of the policy in ``directory`` with what its certificate says, and
    its problems: a non-router identity whose certificate (or policy entry) names hosts
    (it could pose as the router: issued before ``add`` refused that), a common name or a
    role other than the policy's; and certificates of no identity of the policy."""
    directory = Path(directory)
    policy = Policy.load(directory)
    out = []
    for ident in policy.identities:
        path = directory / f"{ident.name}.pem"
        problems = []
        if ident.role != "router" and ident.hosts:
            problems.append(f"its policy entry names hosts ({', '.join(ident.hosts)})")
        if not path.is_file():
            out.append(CertificateCheck(ident.name, ident.role, problems=tuple(problems)))
            continue
        cn, unit, hosts = _certificate(path)
        if cn != ident.name:
            problems.append(f"its certificate's common name is {cn!r}, not {ident.name!r}")
        if unit is not None and unit != ident.role:
            problems.append(f"its certificate was issued for the role {unit!r}, the policy says {ident.role!r}")
        if ident.role != "router" and hosts:
            problems.append(f"its certificate names hosts ({', '.join(hosts)}): it can pose as the router on them "
                            f"(made before qradar refused host names there); issue it again: `qradar security "
                            f"remove {directory} {ident.name}`, then `qradar security add {directory} --role "
                            f"{ident.role} ...` without --host")
        out.append(CertificateCheck(ident.name, ident.role, cn, unit, hosts, tuple(problems)))
    known = {i.name for i in policy.identities} | {"ca"}
    for path in sorted(directory.glob("*.pem")):
        if path.stem not in known:
            cn, unit, hosts = _certificate(path)
            out.append(CertificateCheck(path.stem, "?", cn, unit, hosts,
                                        ("a certificate of no identity of the policy: remove it",)))
    return out


def remove(directory: Path, name: str) -> None:
    """Withdraw an identity: out of the policy, its certificate and key deleted. A router
    restarted with this policy denies it everything (there is no revocation list: the
    certificate itself stays valid for TLS until it expires)."""
    directory = Path(directory)
    Policy.load(directory).without(name).save(directory)
    for suffix in (".pem", ".key"):
        (directory / f"{name}{suffix}").unlink(missing_ok=True)


def _check_days(days: int, ca_days: int) -> None:
    if not (isinstance(days, int) and days >= 1 and isinstance(ca_days, int) and ca_days >= 1):
        raise ParameterError(f"validity days={days!r}, ca_days={ca_days!r} must be integers >= 1")
