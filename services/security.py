"""Security between hosts: TLS with client certificates, user/password authentication and
Zenoh access control, all configured from a stack file's [security] table.

Topology (docs/security.md): every service listens on its own host's loopback only, so the
only door from another host is that host's router. Routers link to each other over TLS with
client certificates (mutual TLS) signed by the stack's own CA; every session (router, service,
tool) also presents its machine's user/password. The router that accepts a link is the
enforcement point: its access control lets each other machine publish only the keys of the
services the stack file places on that machine. The services' own 400 Hz peer-to-peer links
stay on loopback and pay nothing per message.

Files (made by `zenpilot certs DIR --stack FILE`, one set per [machines.NAME]):

    ca.pem              the stack's certificate authority (every machine needs it)
    ca.key              its private key: only to make certificates, keep it off the vehicle
    NAME.pem, NAME.key  the machine's TLS certificate (CN = NAME) and private key
    NAME.login          "NAME:password": what the machine's sessions present
    NAME.users          the users the machine's router accepts (its own, plus every machine's
                        when its router accepts links: `listen` is set)

Copy ca.pem and a machine's NAME.* files to that machine; nothing secret is in the stack file.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from services.stack import Stack

# What each service publishes (topics below zp/<vehicle>/), besides what every service
# publishes: its health, in lockstep its sync, in real time its beat. tests/unit/services/test_security.py checks this
# against the services' code (every rt.publisher(schemas.X) call).
PUBLISHES: dict[str, tuple[str, ...]] = {
    "sim": ("sim/imu", "sim/baro", "sim/mag", "sim/camera", "sim/@image", "sim/truth", "sim/battery",
            "@lockstep/clock/*"),
    "motors": ("motors/pwm",),
    "attitude": ("att/command", "att/state"),
    "position": ("pos/setpoint", "pos/state", "pos/ekf_health"),
    "vision": ("vision/pose",),
    "planner": ("planner/setpoint", "planner/plan", "planner/flip_prediction", "planner/flip_status"),
    "recorder": (),
    "mavlink": ("planner/command", "planner/mission", "param/set"),
}

# Zenoh access-control message kinds (zenoh 1.10) other than data
DECLARATIONS = ["declare_subscriber", "declare_queryable", "query", "reply",
                "liveliness_query", "declare_liveliness_subscriber"]
ALL_MESSAGES = ["put", "delete", "liveliness_token", *DECLARATIONS]


class SecurityError(ValueError):
    """A [security] table, key file or link that cannot be used; the message says what and where."""


@dataclass(frozen=True)
class Security:
    dir: Path   # where `zenpilot certs` wrote the files

    def ca(self) -> Path:
        return self.dir / "ca.pem"

    def certificate(self, machine: str) -> Path:
        return self.dir / f"{machine}.pem"

    def private_key(self, machine: str) -> Path:
        return self.dir / f"{machine}.key"

    def login_file(self, machine: str) -> Path:
        return self.dir / f"{machine}.login"

    def users_file(self, machine: str) -> Path:
        return self.dir / f"{machine}.users"

    def login(self, machine: str) -> tuple[str, str]:
        path = self.login_file(machine)
        try:
            user, sep, password = path.read_text().strip().partition(":")
        except OSError as exc:
            raise SecurityError(f"{path}: cannot read the login of machine {machine!r} ({exc.strerror}); "
                                f"make it with `zenpilot certs {self.dir} --stack STACK`") from None
        if not sep or not user or not password:
            raise SecurityError(f"{path}: expected one line USER:PASSWORD")
        return user, password

    def need(self, *paths: Path) -> None:
        for p in paths:
            if not p.is_file():
                raise SecurityError(f"{p}: missing; make the stack's keys with "
                                    f"`zenpilot certs {self.dir} --stack STACK` and copy them to this machine")


def parse_security(table: object, stack_path: Path) -> Security:
    """The [security] table of a stack file; SecurityError names the file and the key."""
    where = f"{stack_path}: [security]"
    if not isinstance(table, dict):
        raise SecurityError(f"{where}: expected a table")
    unknown = set(table) - {"dir", "description"}
    if unknown:
        raise SecurityError(f"{where}: unknown key(s) {sorted(unknown)} (known: dir)")
    d = table.get("dir")
    if not isinstance(d, str) or not d:
        raise SecurityError(f"{where} dir: expected the folder `zenpilot certs` wrote, e.g. dir = \"keys\"")
    path = Path(os.path.expanduser(d))
    return Security(path if path.is_absolute() else stack_path.parent / path)


def endpoint_host(endpoint: str) -> tuple[str, str, str]:
    """(protocol, host, port) of a Zenoh endpoint such as tls/10.0.0.1:7448, tcp/[::1]:0 or
    tcp/10.0.0.1:7449?prio=7-7 (metadata after `?`, configuration after `#`)."""
    proto, sep, rest = endpoint.partition("/")
    host, sep2, port = rest.split("#")[0].split("?")[0].rpartition(":")
    if not sep or not sep2 or not proto or not host:
        raise ValueError(f"endpoint {endpoint!r}: expected PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447")
    return proto, host.strip("[]"), port


def is_loopback(endpoint: str) -> bool:
    host = endpoint_host(endpoint)[1]
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# ---------------------------------------------------------------- Zenoh configuration
def machine_of(stack: "Stack", endpoint: str) -> str:
    """The machine a tool connecting to `endpoint` acts as: the one whose router it is (on two
    hosts both routers may be tcp/127.0.0.1:7447: the one whose login is on this host)."""
    mine = [m.name for m in stack.machines.values() if m.router == endpoint]
    sec = stack.security
    here = [m for m in mine if sec is not None and sec.login_file(m).is_file()]
    if here or mine:
        return (here or mine)[0]
    raise SecurityError(f"{stack.path}: no machine has router {endpoint!r}: with [security] a tool "
                        f"connects to its own machine's router")


def tls_config(sec: Security, machine: str) -> dict:
    sec.need(sec.ca(), sec.certificate(machine), sec.private_key(machine))
    cert, key = str(sec.certificate(machine)), str(sec.private_key(machine))
    return {"root_ca_certificate": str(sec.ca()), "enable_mtls": True,
            "listen_certificate": cert, "listen_private_key": key,
            "connect_certificate": cert, "connect_private_key": key,
            "verify_name_on_connect": True}


def apply_session(conf, sec: Security, machine: str) -> None:
    """A service's or tool's session: it presents its machine's login, and accepts on its own
    (loopback) listener only sessions of its own machine (no other machine's user is in the
    dictionary it checks), so a link from elsewhere has only the router's door."""
    user, password = sec.login(machine)
    conf.insert_json5("transport/auth/usrpwd", json.dumps(
        {"user": user, "password": password, "dictionary_file": str(sec.login_file(machine))}))
    conf.insert_json5("transport/link/tls", json.dumps(tls_config(sec, machine)))
    # Two peers that open a link to each other at once, with user/password, may both be refused
    # for good (zenoh issue 2577; docs/security.md): only the peer with the greater id opens.
    conf.insert_json5("scouting/gossip/autoconnect_strategy",
                      '{peer: {to_router: "always", to_peer: "greater-zid"}}')


def router_acl(stack: "Stack", machine: str) -> dict:
    """Access control for `machine`'s router: its own machine's sessions may do anything; any
    other machine may put only the keys of the services the stack places on it (health, sync and
    liveliness of those services included), declare subscriptions and queries, and receive data.
    Default deny: an allow-list, so a put on a wildcard key (zp/0/**) is not let through."""
    prefix = f"zp/{stack.vehicle_id}"
    # `**` never matches a verbatim chunk: the lockstep handshake's keys are named apart
    every_key = ["**", f"{prefix}/@lockstep/**", f"{prefix}/@beat/**"]
    rules: list[dict] = [
        # the camera's images (sim/@image) pass only between the router's own machine's sessions:
        # they never cross the link to another host (the vision service runs beside the camera)
        {"id": "everything", "messages": ALL_MESSAGES, "flows": ["ingress", "egress"],
         "permission": "allow", "key_exprs": every_key + [f"{prefix}/sim/@image"]},
        {"id": "declarations", "messages": DECLARATIONS, "flows": ["ingress", "egress"],
         "permission": "allow", "key_exprs": every_key},
        {"id": "receive", "messages": ["put", "delete", "liveliness_token"], "flows": ["egress"],
         "permission": "allow", "key_exprs": every_key},
    ]
    subjects = [{"id": f"machine-{machine}", "usernames": [machine]}]
    policies = [{"id": f"own-{machine}", "rules": ["everything"], "subjects": [f"machine-{machine}"]}]
    for other in stack.machines:
        if other == machine:
            continue
        services = [n for n, s in stack.services.items() if s.machine == other]
        keys = sorted({f"{prefix}/{t}" for n in services for t in PUBLISHES.get(n, ())}
                      | {f"{prefix}/{n}/health" for n in services} | {f"{prefix}/@lockstep/sync/{n}" for n in services}
                      | {f"{prefix}/@beat/{n}" for n in services})
        subjects.append({"id": f"machine-{other}", "usernames": [other]})
        # the check of a link from `other` (deploy/router.py, CheckedLink): its ping in, the echo out
        link = f"{prefix}/@link/{other}"
        rules.append({"id": f"link-{other}", "messages": ["put", "declare_subscriber"], "flows": ["ingress", "egress"],
                      "permission": "allow", "key_exprs": [f"{link}/ping", f"{link}/echo"]})
        ids = ["declarations", "receive", f"link-{other}"]
        if keys:
            rules.append({"id": f"publish-{other}", "messages": ["put"], "flows": ["ingress"],
                          "permission": "allow", "key_exprs": keys})
            rules.append({"id": f"alive-{other}", "messages": ["liveliness_token"], "flows": ["ingress"],
                          "permission": "allow", "key_exprs": [f"{prefix}/alive/{n}" for n in services]})
            ids += [f"publish-{other}", f"alive-{other}"]
        policies.append({"id": f"from-{other}", "rules": ids, "subjects": [f"machine-{other}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def apply_router(conf, stack: "Stack", machine: str) -> None:
    sec = stack.security
    assert sec is not None
    user, password = sec.login(machine)
    sec.need(sec.users_file(machine))
    conf.insert_json5("transport/auth/usrpwd", json.dumps(
        {"user": user, "password": password, "dictionary_file": str(sec.users_file(machine))}))
    conf.insert_json5("transport/link/tls", json.dumps(tls_config(sec, machine)))
    if stack.machines[machine].listen:
        # the router that accepts other hosts enforces; one that only connects out has no
        # user name for the router it reached (Zenoh learns the user of the side that connects)
        # and trusts it by its certificate, checked against the CA and the address
        conf.insert_json5("access_control", json.dumps(router_acl(stack, machine)))


# ---------------------------------------------------------------- certificates
def make_keys(out: Path, stack: "Stack", days: int = 825) -> list[Path]:
    """The stack's CA, a certificate per machine (CN = the machine's name; its names and
    addresses: the machine's name and the hosts of its `listen` endpoints, so a router that
    connects checks it reached the right host), and the logins and user lists. Refuses to
    overwrite: keys are made once and copied."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    names = list(stack.machines)
    targets = [out / "ca.pem", out / "ca.key"] + [out / f"{m}.{ext}" for m in names
                                                  for ext in ("pem", "key", "login", "users")]
    existing = [p for p in targets if p.exists()]
    if existing:
        raise SecurityError(f"{existing[0]}: already exists; keys are never overwritten "
                            f"(remove the folder's files to make new ones)")
    out.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.timezone.utc)
    valid_from, valid_to = now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)

    def pem_key(key) -> bytes:
        return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption())

    def write(path: Path, data: bytes, secret: bool) -> None:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600 if secret else 0o644)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"zenpilot {stack.path.stem} CA")])
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name)
          .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
          .not_valid_before(valid_from).not_valid_after(valid_to)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                       data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                       crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
          .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
          .sign(ca_key, hashes.SHA256()))
    write(out / "ca.pem", ca.public_bytes(serialization.Encoding.PEM), secret=False)
    write(out / "ca.key", pem_key(ca_key), secret=True)
    passwords = {m: secrets.token_urlsafe(24) for m in names}
    accepts_all = {m for m in names if stack.machines[m].listen}
    for m in names:
        key = ec.generate_private_key(ec.SECP256R1())
        alt: list = [x509.DNSName(m), x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
        for endpoint in stack.machines[m].listen:
            host = endpoint_host(endpoint)[1]
            try:
                alt.append(x509.IPAddress(ipaddress.ip_address(host)))
            except ValueError:
                alt.append(x509.DNSName(host))
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, m)]))
                .issuer_name(ca_name).public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(valid_from).not_valid_after(valid_to)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.SubjectAlternativeName(list(dict.fromkeys(alt))), critical=False)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                               critical=False)
                .sign(ca_key, hashes.SHA256()))
        write(out / f"{m}.pem", cert.public_bytes(serialization.Encoding.PEM), secret=False)
        write(out / f"{m}.key", pem_key(key), secret=True)
        write(out / f"{m}.login", f"{m}:{passwords[m]}\n".encode(), secret=True)
        users = names if m in accepts_all else [m]
        write(out / f"{m}.users", "".join(f"{u}:{passwords[u]}\n" for u in users).encode(), secret=True)
    return targets
