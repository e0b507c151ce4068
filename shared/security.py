"""Who may say what on the bus: Zenoh TLS (mutual authentication) and access control from roles.

Security is Zenoh configuration, not code of ours (design.md, "Reliability rules"): every
session presents a certificate signed by the deployment's CA, the router checks it (mTLS),
and the router's ``access_control`` rules, keyed on the certificate's common name (CN),
decide which messages of which identity it forwards.  A refused message is dropped by
Zenoh at the router; it never reaches a subscriber, so no daemon has to filter after the
fact.  This module turns a *security directory* into those configs::

    DIR/ca.pem, DIR/ca.key         the deployment's CA (keep ca.key offline in production)
    DIR/<name>.pem, DIR/<name>.key one certificate per identity, CN = <name>
    DIR/identities.toml            [identities] <name> = "<role>"   (written by `issue`)

An identity's name is its id in the key space (a vehicle's id, a cloud daemon's ``--id``),
so a role's rules name its own keys.  Roles (see :data:`ROLES`):

* ``vehicle``: publishes only ``veh/<id>/imu``, ``ap/*/*/<id>``, ``done/<id>``; receives only
  ``veh/<id>/imu``, ``calib/<id>`` and ``ack/<id>`` (it may subscribe by wildcard, as the edge
  daemon does: the router forwards it nothing else).
* ``edge``: a fleet edge hosting many vehicles' tasks (a depot server, ``driveby run``).
* ``aggregator``: the cloud: AP segments and markers in; calibrations, acks, status, alarms out;
  answers state and its own control queries.
* ``viewer``: reads segments, status, alarms and liveliness; queries state and statistics.
* ``operator``: a viewer that may also replay raw streams (``driveby run``/``fleet``) and ask
  any daemon's control queries (export).
* ``router``: another router of the mesh (scale-out): everything under ``driveby/<net>``.

Zenoh in the eclipse-zenoh wheel has no statistics (its ``stats`` feature is not built in),
so a refusal is counted from Zenoh's own access-control trace: every message the router's
ACL drops is logged as a decision ("... is unauthorized to Put (ingress) on <key>")
followed by "Msg intercepted!".  :class:`DenialCounter` reads those lines; the router
(``python -m shared.transport router --security DIR``) answers the counts on
``driveby/<net>/control/<router id>/denials``.

Certificates are made with the ``openssl`` command line (``python -m shared.security``).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import ipaddress
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from shared.keys import ROOT, check_id, control_key

__all__ = ["ROLES", "MESSAGES", "TlsFiles", "SecurityDir", "DenialCounter", "access_control", "tls_config",
           "router_config", "init_ca", "issue", "main"]

ACL_LOG_DIRECTIVE = "zenoh::net::routing::interceptor=trace"  # the decision and drop lines counted
MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
            "declare_liveliness_subscriber", "liveliness_query")
IDENTITIES_FILE = "identities.toml"
CA_DAYS = 3650
CERT_DAYS = 825

# A grant: (messages, flow, key expressions under driveby/<net>/, "{id}" = the identity's name).
# "ingress" is what the router accepts from the identity, "egress" what it forwards to it.
# Subscribers of one's own keys are forwarded (egress declare_subscriber) so that declared
# publishers and matching status work; they reveal only that someone listens.
_LIVELINESS_WATCH = (
    (("declare_liveliness_subscriber", "liveliness_query"), "ingress", ("alive/**",)),
    (("liveliness_token", "reply"), "egress", ("alive/**",)),
)
_OWN_CONTROL = (  # a daemon's own control queryables (stats, export, ...)
    (("declare_queryable", "reply"), "ingress", ("control/{id}/*",)),
    (("query",), "egress", ("control/{id}/*",)),
)
_READ_ONLY_QUERIES = ("state/**", "control/*/stats", "control/*/status", "control/*/latency", "control/*/denials")
_VIEW = (
    (("declare_subscriber",), "ingress", ("ap/**", "done/*", "ack/*", "calib/*", "status/*", "alarm/*")),
    (("put",), "egress", ("ap/**", "done/*", "ack/*", "calib/*", "status/*", "alarm/*")),
    (("query",), "ingress", _READ_ONLY_QUERIES),
    (("reply", "declare_queryable"), "egress", _READ_ONLY_QUERIES),
    *_LIVELINESS_WATCH,
)
# Raw chunks go through Zenoh's advanced publisher/subscriber (simfleet.replay, edge.node): the
# publisher's heartbeats (put) and its cache (a queryable) live under "<imu key>/@adv/...", a
# verbatim chunk no wildcard matches, so they are granted by name.
_ADV = "imu/@adv/**"


def _imu_publisher(vehicles: str) -> tuple:
    """Grants of a session publishing ``veh/<vehicles>/imu`` through an advanced publisher (its cache
    replies with the chunks' own keys). An edge subscribes and queries by wildcard
    (``veh/*/imu/@adv/...``, naming the publisher's zid): those must reach the publisher; they
    carry no data, and what it may publish or answer stays its own keys."""
    return (
        (("put", "declare_queryable", "reply"), "ingress", (f"veh/{vehicles}/{_ADV}",)),
        (("reply",), "ingress", (f"veh/{vehicles}/imu",)),
        (("declare_subscriber", "query"), "egress", (f"veh/*/{_ADV}",)),
    )


def _imu_recovery(vehicles: str) -> tuple:
    """Grants of an advanced subscriber of ``veh/*/imu`` recovering ``veh/<vehicles>/imu``: heartbeats
    in, queries to the caches out, their replies back."""
    return (
        (("declare_subscriber", "query"), "ingress", (f"veh/*/{_ADV}",)),
        (("put", "declare_queryable", "reply"), "egress", (f"veh/{vehicles}/{_ADV}",)),
        (("reply",), "egress", (f"veh/{vehicles}/imu",)),
    )


ROLES: Mapping[str, tuple] = {
    "vehicle": (
        (("put",), "ingress", ("veh/{id}/imu", "ap/*/*/{id}", "done/{id}")),
        (("declare_subscriber",), "egress", ("veh/*/imu", "ap/**", "done/*")),
        (("declare_subscriber",), "ingress", ("veh/*/imu", "calib/*", "ack/*")),
        (("put",), "egress", ("veh/{id}/imu", "calib/{id}", "ack/{id}")),
        (("liveliness_token",), "ingress", ("alive/edge/{id}", "alive/vehicle/{id}")),
        *_imu_publisher("{id}"),
        *_imu_recovery("{id}"),
        *_LIVELINESS_WATCH,
        *_OWN_CONTROL,
    ),
    "edge": (
        (("declare_subscriber",), "ingress", ("veh/*/imu", "calib/*", "ack/*")),
        (("put",), "egress", ("veh/*/imu", "calib/*", "ack/*")),
        (("put",), "ingress", ("ap/**", "done/*")),
        (("declare_subscriber",), "egress", ("ap/**", "done/*")),
        (("liveliness_token",), "ingress", ("alive/edge/{id}",)),
        *_imu_recovery("*"),
        *_LIVELINESS_WATCH,
        *_OWN_CONTROL,
    ),
    "aggregator": (
        # calib/*: a route shard adopts the calibrations of the vehicles another shard owns.
        (("declare_subscriber",), "ingress", ("ap/**", "done/*", "calib/*")),
        (("put",), "egress", ("ap/**", "done/*", "calib/*")),
        (("put",), "ingress", ("calib/*", "ack/*", "status/{id}", "alarm/*")),
        (("declare_subscriber",), "egress", ("calib/*", "ack/*", "status/*", "alarm/*")),
        (("declare_queryable", "reply"), "ingress", ("state/**", "control/{id}/*")),
        (("query",), "egress", ("state/**", "control/{id}/*")),
        (("liveliness_token",), "ingress", ("alive/cloud/{id}",)),
        *_LIVELINESS_WATCH,
    ),
    "viewer": _VIEW,
    "operator": (
        *_VIEW,
        (("put",), "ingress", ("veh/*/imu",)),
        (("declare_subscriber",), "egress", ("veh/*/imu",)),
        *_imu_publisher("*"),
        (("query",), "ingress", ("control/**",)),
        (("reply", "declare_queryable"), "egress", ("control/**",)),
    ),
    "router": ((MESSAGES, "ingress", ("**",)), (MESSAGES, "egress", ("**",))),
}


class SecurityError(ValueError):
    """A security directory, certificate or role is missing or malformed (one line, naming the file)."""


@dataclasses.dataclass(frozen=True)
class TlsFiles:
    """PEM files of one Zenoh session: the CA that signs every peer, and this session's own
    certificate and key (both or neither; without them a client cannot pass a mTLS router)."""

    ca: Path
    cert: Path | None = None
    key: Path | None = None

    def __post_init__(self) -> None:
        if (self.cert is None) != (self.key is None):
            raise SecurityError("TLS: give both a certificate and its key, or neither")
        for what in ("ca", "cert", "key"):
            path = getattr(self, what)
            if path is not None:
                path = Path(path)
                if not path.is_file():
                    raise SecurityError(f"TLS {what} file {path}: not found")
                object.__setattr__(self, what, path.resolve())


def tls_config(files: TlsFiles, *, listen: bool) -> dict:
    """The ``transport.link.tls`` section for ``files``.

    The certificate is presented both when connecting (client authentication) and, with
    ``listen``, when accepting; a listener then requires its peers' certificates (mTLS).
    """
    conf: dict = {"root_ca_certificate": str(files.ca)}
    if files.cert is not None:
        conf.update(connect_certificate=str(files.cert), connect_private_key=str(files.key), enable_mtls=True)
        if listen:
            conf.update(listen_certificate=str(files.cert), listen_private_key=str(files.key))
    elif listen:
        raise SecurityError("TLS: a listener needs its own certificate and key")
    return conf


def access_control(net: str, identities: Mapping[str, str]) -> dict:
    """The router's ``access_control`` section: deny by default, each identity its role's grants.

    Parameters
    ----------
    net : str
        The network name in the key space (rules cover ``driveby/<net>/...`` only).
    identities : mapping name -> role
        Certificate common names (= ids in the key space) and their roles (:data:`ROLES`).
    """
    check_id(net, "net")
    rules, subjects, policies = [], [], []
    for name, role in sorted(identities.items()):
        check_id(name, "identity")
        if role not in ROLES:
            raise SecurityError(f"identity {name}: unknown role {role!r}; one of {sorted(ROLES)}")
        ids = []
        for i, (messages, flow, exprs) in enumerate(ROLES[role]):
            rule_id = f"{name}/{i}"
            rules.append({"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages),
                          "key_exprs": [f"{ROOT}/{net}/{e.format(id=name)}" for e in exprs]})
            ids.append(rule_id)
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": name, "rules": ids, "subjects": [name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


@dataclasses.dataclass(frozen=True)
class SecurityDir:
    """A security directory (module docstring): the CA, the identities' certificates and roles."""

    path: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        if not (self.path / "ca.pem").is_file():
            raise SecurityError(f"security directory {self.path}: no ca.pem (run `python -m shared.security init`)")

    def identities(self) -> dict[str, str]:
        """``name -> role`` from ``identities.toml``."""
        file = self.path / IDENTITIES_FILE
        try:
            data = tomllib.loads(file.read_text()) if file.exists() else {}
        except (OSError, tomllib.TOMLDecodeError) as e:
            raise SecurityError(f"{file}: {e}") from None
        table = data.get("identities", {})
        if not isinstance(table, dict) or not all(isinstance(v, str) for v in table.values()):
            raise SecurityError(f"{file}: expected [identities] name = \"role\"")
        for name, role in table.items():
            if role not in ROLES:
                raise SecurityError(f"{file}: identity {name}: unknown role {role!r}; one of {sorted(ROLES)}")
        return dict(table)

    def tls(self, name: str | None = None) -> TlsFiles:
        """The CA, with ``name``'s certificate and key if a name is given."""
        if name is None:
            return TlsFiles(self.path / "ca.pem")
        check_id(name, "identity")
        return TlsFiles(self.path / "ca.pem", self.path / f"{name}.pem", self.path / f"{name}.key")


def router_config(security: SecurityDir, net: str, router_id: str, listen: Sequence[str] = (),
                  connect: Sequence[str] = ()) -> dict:
    """A router's zenoh config (JSON-serialisable): TLS only, mutual authentication, and the
    access control of every identity in ``security`` on network ``net``."""
    conf: dict = {
        "mode": "router",
        "transport": {"link": {"protocols": ["tls"], "tls": tls_config(security.tls(router_id), listen=True)}},
        "access_control": access_control(net, security.identities()),
        "scouting": {"multicast": {"enabled": False}},
    }
    if listen:
        conf["listen"] = {"endpoints": list(listen)}
    if connect:
        conf["connect"] = {"endpoints": list(connect)}
    return conf


# -- counting refusals from Zenoh's access-control trace ------------------------------------------

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_DECISION = re.compile(
    r"(?:Using cached result: )?(?P<zid>[0-9a-f]+)(?: on (?P<subject>\S+))? is unauthorized to "
    r"(?P<message>.+?) \((?P<flow>ingress|egress)\) on (?P<key>\S+)")
_CN = re.compile(r"CertCommonName\(([^)]*)\)")


class DenialCounter:
    """Counts the messages Zenoh's access control dropped, from its trace lines.

    Zenoh logs a decision ("<zid> on <subject> is unauthorized to Put (ingress) on <key>", or
    "Using cached result: <zid> is unauthorized ...") and, if it then drops a message,
    "Msg intercepted!" on the same thread.  A denial is an intercepted message, attributed to
    the thread's last decision; decisions computed only to fill Zenoh's cache are not counted.
    Thread-safe: lines are fed by a reader thread, snapshots taken by a query handler.
    """

    RECENT = 100

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: dict[str, tuple[str, str, str, str]] = {}  # thread -> (who, message, flow, key)
        self._names: dict[str, str] = {}  # zid -> certificate common name
        self.total = 0
        self.by: collections.Counter[tuple[str, str, str]] = collections.Counter()  # (who, message, flow)
        self.recent: collections.deque = collections.deque(maxlen=self.RECENT)

    def feed(self, line: str) -> tuple[str, str, str, str] | None:
        """One log line; returns ``(who, message, flow, key)`` if it records a dropped message."""
        if "unauthorized" not in line and "intercepted" not in line:
            return None
        line = _ANSI.sub("", line)
        thread = _THREAD.search(line)
        thread = thread.group(1) if thread else ""
        m = _DECISION.search(line)
        with self._lock:
            if m is not None:
                zid, subject = m.group("zid"), m.group("subject") or ""
                cn = _CN.search(subject)
                if cn:
                    self._names[zid] = cn.group(1)
                who = self._names.get(zid, zid)
                message = m.group("message").lower().replace(" ", "_")
                self._last[thread] = (who, message, m.group("flow"), m.group("key"))
                return None
            if "Msg intercepted!" in line and thread in self._last:
                denial = self._last.pop(thread)
                self.total += 1
                self.by[denial[:3]] += 1
                self.recent.append(denial)
                return denial
        return None

    def snapshot(self) -> dict:
        """JSON-ready counts: ``total``, ``by`` (who/message/flow -> n) and the ``recent`` denials."""
        with self._lock:
            return {"total": self.total,
                    "by": [{"who": w, "message": m, "flow": f, "n": n} for (w, m, f), n in sorted(self.by.items())],
                    "recent": [{"who": w, "message": m, "flow": f, "key": k} for w, m, f, k in self.recent]}


def denials_key(net: str, router_id: str) -> str:
    """``driveby/<net>/control/<router id>/denials``: where a secured router answers its counts."""
    return control_key(net, router_id, "denials")


# -- certificates (openssl command line) ----------------------------------------------------------


def _openssl(*args: str, cwd: Path) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise SecurityError("openssl: command not found (needed to make certificates)")
    res = subprocess.run([exe, *args], cwd=cwd, capture_output=True, text=True)
    if res.returncode != 0:
        raise SecurityError(f"openssl {args[0]}: {res.stderr.strip().splitlines()[-1] if res.stderr else 'failed'}")


def init_ca(path: str | os.PathLike[str], name: str = "driveby-ca", days: int = CA_DAYS) -> SecurityDir:
    """Create a security directory with a new CA (EC P-256). Refuses to overwrite one."""
    d = Path(path)
    d.mkdir(parents=True, exist_ok=True)
    if (d / "ca.pem").exists():
        raise SecurityError(f"{d / 'ca.pem'}: exists; not overwriting a CA")
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", "ca.key", "-out", "ca.pem", "-days", str(days), "-subj", f"/CN={name}",
             "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
             cwd=d)
    os.chmod(d / "ca.key", 0o600)
    if not (d / IDENTITIES_FILE).exists():
        (d / IDENTITIES_FILE).write_text("# certificate common name = role (shared.security.ROLES)\n[identities]\n")
    return SecurityDir(d)


def issue(security: SecurityDir, name: str, role: str, hosts: Iterable[str] = ("localhost", "127.0.0.1"),
          days: int = CERT_DAYS) -> TlsFiles:
    """Issue ``name``'s certificate (CN = name) signed by the directory's CA and record its role.

    ``hosts`` become subject alternative names (DNS names or IP addresses): a router's
    certificate must name the host its clients connect to (Zenoh verifies it).
    """
    check_id(name, "identity")
    if role not in ROLES:
        raise SecurityError(f"identity {name}: unknown role {role!r}; one of {sorted(ROLES)}")
    d = security.path
    if not (d / "ca.key").is_file():
        raise SecurityError(f"{d / 'ca.key'}: not found (the CA's key signs certificates)")
    sans = []
    for h in hosts:
        try:
            sans.append(f"IP:{ipaddress.ip_address(h)}")
        except ValueError:
            sans.append(f"DNS:{h}")
    with tempfile.TemporaryDirectory() as tmp:
        ext, csr = Path(tmp) / "ext.cnf", Path(tmp) / "req.csr"
        ext.write_text("basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n"
                       "extendedKeyUsage=serverAuth,clientAuth\n"
                       + (f"subjectAltName={','.join(sans)}\n" if sans else ""))
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", f"{name}.key",
                 "-out", str(csr), "-subj", f"/CN={name}", cwd=d)
        _openssl("x509", "-req", "-in", str(csr), "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
                 "-out", f"{name}.pem", "-days", str(days), "-extfile", str(ext), cwd=d)
    os.chmod(d / f"{name}.key", 0o600)
    identities = security.identities()
    identities[name] = role
    (d / IDENTITIES_FILE).write_text("# certificate common name = role (shared.security.ROLES)\n[identities]\n"
                                     + "".join(f'"{n}" = "{r}"\n' for n, r in sorted(identities.items())))
    return security.tls(name)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m shared.security {init,issue,router-config} ...``"""
    p = argparse.ArgumentParser(prog="python -m shared.security", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    a = sub.add_parser("init", help="create a security directory with a new CA")
    a.add_argument("dir")
    a = sub.add_parser("issue", help="issue an identity's certificate and record its role")
    a.add_argument("dir")
    a.add_argument("name", help="common name = the id in the key space (vehicle id, daemon --id)")
    a.add_argument("--role", required=True, choices=sorted(ROLES))
    a.add_argument("--host", action="append", help="subject alternative name (DNS or IP; repeatable; "
                                                   "default localhost and 127.0.0.1)")
    a = sub.add_parser("router-config", help="print a router's zenoh JSON5 config (zenohd -c FILE)")
    a.add_argument("dir")
    a.add_argument("--net", default="net")
    a.add_argument("--id", required=True, help="the router's identity (its certificate's name)")
    a.add_argument("--listen", action="append", default=[], help="endpoint, e.g. tls/0.0.0.0:7447")
    a.add_argument("--connect", action="append", default=[], help="another router, e.g. tls/r2:7447")
    args = p.parse_args(argv)
    try:
        if args.command == "init":
            init_ca(args.dir)
        elif args.command == "issue":
            files = issue(SecurityDir(args.dir), args.name, args.role, args.host or ("localhost", "127.0.0.1"))
            print(f"{files.cert}\n{files.key}")
        else:
            conf = router_config(SecurityDir(args.dir), args.net, args.id, args.listen, args.connect)
            print(json.dumps(conf, indent=2))
    except (SecurityError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
