"""Fixtures for Zenoh, TLS and multi-process tests: free loopback ports, condition waits and
a throw-away certificate authority. Everything stays on 127.0.0.1."""

from __future__ import annotations

import asyncio
import datetime
import ipaddress
import socket
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from kimera_multi_py.comms.counters import TrafficCounters

pytestmark = pytest.mark.integration


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago."""
    return free_port()


async def _wait_until(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not cond():
        if loop.time() > deadline:
            raise TimeoutError(f"condition not met within {timeout} s")
        await asyncio.sleep(0.01)


@pytest.fixture
def wait_until() -> Callable[[Callable[[], bool], float], Awaitable[None]]:
    """``await wait_until(cond, timeout)``: poll a condition, fail with TimeoutError."""
    return _wait_until


async def _route_ready(
    put: Callable[[], object], sub: Any, reset: Iterable[Any] = (), timeout: float = 10.0
) -> None:
    """Put probes until ``sub`` receives one; then drop what it received and zero ``reset``'s
    counters.

    Zenoh can lose the first publications on a fresh route even after the publisher reports a
    matching subscriber (seen about once in ten fresh processes on this 2-core machine under CPU
    load: a whole first burst vanished, a put 5 s later arrived). Tests that count exactly what
    arrives make the route carry one message first. ``put`` puts one valid probe on the key.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        put()
        try:
            await sub.recv(timeout=0.2)
            break
        except TimeoutError:
            if loop.time() > deadline:
                raise TimeoutError(f"no probe arrived within {timeout} s") from None
    await asyncio.sleep(0.3)  # probes still in flight
    while sub.pending():
        await sub.recv()
    for bus in reset:
        bus.counters = TrafficCounters()


@pytest.fixture
def route_ready() -> Callable[..., Awaitable[None]]:
    """``await route_ready(put, sub, reset=(buses...))``: see :func:`_route_ready`."""
    return _route_ready


async def _heartbeat_link(a: Any, b: Any, timeout: float = 10.0) -> Any:
    """Announce buses ``a`` and ``b`` (already open), wait until ``b`` sees robot ``a`` and a
    heartbeat route from ``a`` to ``b`` carries messages; return ``b``'s heartbeat subscription."""
    from kimera_multi_py.comms import keys
    from kimera_multi_py.comms.codec import Codec
    from kimera_multi_py.comms.messages.team import Heartbeat

    await a.announce()
    await b.announce()
    await b.wait_for_peers({a.robot}, timeout=timeout)
    sub = b.subscribe(keys.topic_all(a.team, keys.HEARTBEAT))
    await a.wait_for_subscribers(a.key(keys.HEARTBEAT), timeout=5)
    probe = Codec(a.team, a.robot).encode(Heartbeat(robot=a.robot, keyframes=0, status="probe"))
    await _route_ready(lambda: a.session.put(a.key(keys.HEARTBEAT), probe), sub)
    return sub


@pytest.fixture
def heartbeat_link() -> Callable[..., Awaitable[Any]]:
    """``sub = await heartbeat_link(a, b, timeout)``: see :func:`_heartbeat_link`."""
    return _heartbeat_link


@dataclass(frozen=True)
class Pki:
    """PEM files of one certificate authority and a leaf for localhost / 127.0.0.1."""

    ca: Path
    cert: Path
    key: Path


def make_pki(folder: Path, name: str) -> Pki:
    """An EC P-256 CA and a leaf with SAN localhost and 127.0.0.1 (docs/deployment.md)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.UTC)
    valid = (now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=1))
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"{name} test CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(valid[0])
        .not_valid_after(valid[1])
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, key_cert_sign=True, crl_sign=True,
                content_commitment=False, key_encipherment=False, data_encipherment=False,
                key_agreement=False, encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), False)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    leaf = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(valid[0])
        .not_valid_after(valid[1])
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), False
        )
        .sign(ca_key, hashes.SHA256())
    )
    folder.mkdir(parents=True, exist_ok=True)
    pki = Pki(folder / "ca.pem", folder / "cert.pem", folder / "key.pem")
    pki.ca.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    pki.cert.write_bytes(leaf.public_bytes(serialization.Encoding.PEM))
    pki.key.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return pki


@pytest.fixture
def pki(tmp_path: Path) -> Pki:
    return make_pki(tmp_path / "pki", "team")


@pytest.fixture
def rogue_pki(tmp_path: Path) -> Pki:
    return make_pki(tmp_path / "rogue", "rogue")
