"""A team's certificates for Zenoh over mutual TLS: one CA, one certificate per process.

``kimera-multi certs DIR`` writes ``DIR/ca.pem`` (the team CA, which every process trusts),
``DIR/ca.key`` (keep it off the robots) and, per name, ``NAME.pem`` + ``NAME.key`` signed by the
CA: ``robot0`` .. ``robotN-1``, ``server``, ``router`` and ``observer``. Keys are EC P-256, the
certificates carry SAN ``localhost`` and ``127.0.0.1`` and both server and client use, since a
Zenoh process both listens and connects. With ``enable_mtls`` every link checks both ends, so a
process without a certificate of this CA cannot join, even one that trusts the CA (docs/deployment.md).

:func:`write_zenoh_config` writes one process's ``--zenoh-config`` file (the
``transport/link/tls`` block of :func:`kimera_multi_py.comms.zenoh_bus.tls_settings`); the
router's also carries :func:`access_control`: a certificate speaks only for its own name, so a
member holding ``robot1.pem`` cannot publish as robot 0 or as the server (docs/deployment.md).
"""

from __future__ import annotations

import datetime
import ipaddress
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kimera_multi_py.comms import keys
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.ids import MAX_ROBOTS, SERVER_ID

CA_CERT, CA_KEY = "ca.pem", "ca.key"
DEFAULT_DAYS = 365


@dataclass(frozen=True)
class Identity:
    """One process's PEM files: the CA it trusts and its own certificate and key."""

    ca: Path
    cert: Path
    key: Path


def team_names(robots: int) -> list[str]:
    """The processes of a team of ``robots``: each robot, the server, the router, the observer."""
    if not 1 <= robots <= MAX_ROBOTS:
        raise ConfigError("robots", f"must be in 1..{MAX_ROBOTS}, got {robots}")
    return [f"robot{r}" for r in range(robots)] + ["server", "router", "observer"]


def make_certs(folder: str | Path, names: Iterable[str], days: int = DEFAULT_DAYS,
               hosts: Iterable[str] = ("localhost", "127.0.0.1")) -> dict[str, Identity]:
    """Write a new CA and one certificate per name into ``folder``; return each name's files."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    names = list(names)
    for n in names:
        if not n or not n.replace("_", "").replace("-", "").isalnum() or n == "ca":
            raise ConfigError("certs", f"bad certificate name {n!r} (letters, digits, - and _; not 'ca')")
    if days < 1:
        raise ConfigError("days", f"certificates must be valid for at least a day, got {days}")
    sans: list[x509.GeneralName] = []
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError("certs", f"cannot create {folder}: {exc.strerror}") from None
    now = datetime.datetime.now(datetime.UTC)
    start, end = now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"kimera-multi team CA {folder.name}")])
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
          .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                       content_commitment=False, key_encipherment=False, data_encipherment=False,
                                       key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
          .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
          .sign(ca_key, hashes.SHA256()))

    def write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
        path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
        path.chmod(0o600)

    ca_path = folder / CA_CERT
    ca_path.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    write_key(folder / CA_KEY, ca_key)
    out: dict[str, Identity] = {}
    for n in names:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, n)]))
                .issuer_name(ca_name).public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(start).not_valid_after(end)
                .add_extension(x509.SubjectAlternativeName(sans), critical=False)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                               critical=False)
                .sign(ca_key, hashes.SHA256()))
        ident = Identity(ca_path, folder / f"{n}.pem", folder / f"{n}.key")
        ident.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        write_key(ident.key, key)
        out[n] = ident
    return out


def identity(folder: str | Path, name: str) -> Identity:
    """The files of ``name`` in a certificate folder; :class:`ConfigError` if any is missing."""
    folder = Path(folder)
    ident = Identity(folder / CA_CERT, folder / f"{name}.pem", folder / f"{name}.key")
    for p in (ident.ca, ident.cert, ident.key):
        if not p.is_file():
            raise ConfigError("certs", f"{p} is missing (make the team's certificates with `kimera-multi certs`)")
    return ident


# what a process does with keys: reads anyone's (subscribe, query, watch presence), receives
# anything, and speaks (publish, reply, serve, be present) only for itself
_READ = ["declare_subscriber", "query", "liveliness_query", "declare_liveliness_subscriber"]
_SPEAK = ["put", "delete", "reply", "declare_queryable", "liveliness_token"]  # received by all, sent by one


def speaker_ids(names: Iterable[str]) -> dict[str, int]:
    """The bus id each certificate name speaks for: ``robotI`` -> I, ``server`` -> the server's;
    other names (router, observer) speak for no one."""
    out: dict[str, int] = {}
    for n in names:
        if n == "server":
            out[n] = SERVER_ID
        elif n.startswith("robot") and n[5:].isdigit():
            out[n] = int(n[5:])
    return out


def access_control(team: str, names: Iterable[str]) -> dict[str, Any]:
    """The router's Zenoh ``access_control`` block: default deny; every certificate of the team
    may subscribe, query and receive on ``kmp/{team}/**``; a certificate whose common name is
    ``robotI`` (or ``server``) may publish, reply, serve and hold a presence token only on robot
    I's (the server's) keys. A publication under another id is dropped at the router."""
    names = list(names)
    team_keys = [f"{keys.ROOT}/{keys.check_team(team)}/**"]
    rules: list[dict[str, Any]] = [
        {"id": "read", "permission": "allow", "flows": ["ingress", "egress"], "messages": _READ,
         "key_exprs": team_keys},
        {"id": "deliver", "permission": "allow", "flows": ["egress"], "messages": _SPEAK,
         "key_exprs": team_keys},
    ]
    subjects: list[dict[str, Any]] = [{"id": "team", "cert_common_names": names}]
    policies: list[dict[str, Any]] = [{"id": "team", "rules": ["read", "deliver"], "subjects": ["team"]}]
    for name, robot in speaker_ids(names).items():
        rules.append({"id": f"speak-{name}", "permission": "allow", "flows": ["ingress"], "messages": _SPEAK,
                      "key_exprs": [keys.robot_all(team, robot), keys.alive_key(team, robot)]})
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": name, "rules": [f"speak-{name}"], "subjects": [name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def write_zenoh_config(path: str | Path, ident: Identity, mode: str | None = None, mtls: bool = True,
                       acl: dict[str, Any] | None = None) -> Path:
    """A ``--zenoh-config`` JSON5 file for one process of the team (multicast scouting off);
    ``acl``: an ``access_control`` block (the router's, :func:`access_control`)."""
    from kimera_multi_py.comms.zenoh_bus import tls_settings

    conf: dict[str, Any] = {"scouting": {"multicast": {"enabled": False}},
                            "transport": {"link": {"tls": tls_settings(ident.ca, ident.cert, ident.key, mtls)}}}
    if mode is not None:
        conf["mode"] = mode
    if acl is not None:
        conf["access_control"] = acl
    path = Path(path)
    path.write_text(json.dumps(conf, indent=2))
    return path


def write_team_configs(folder: str | Path, idents: dict[str, Identity], team: str) -> dict[str, Path]:
    """Each process's ``NAME.json5`` in ``folder``; the router's with :func:`access_control`."""
    acl = access_control(team, idents)
    return {name: write_zenoh_config(Path(folder) / f"{name}.json5", ident,
                                     acl=acl if name == "router" else None)
            for name, ident in idents.items()}


__all__ = ["Identity", "access_control", "identity", "make_certs", "speaker_ids", "team_names",
           "write_team_configs", "write_zenoh_config"]
