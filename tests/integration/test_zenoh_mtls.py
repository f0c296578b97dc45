"""Mutual TLS between ZenohBus sessions: both ends present a certificate of the team CA.

A process that trusts the team CA but presents no certificate, or one signed by another CA,
cannot join: refused at the handshake, as the router's log shows, it receives nothing
(test_tls_refusal.py, and test_team_tls_strangers.py against a launched team).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from kimera_multi_py.comms.zenoh_bus import Tls, ZenohBus, tls_settings
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.team.certs import make_certs

pytestmark = pytest.mark.integration
TEAM = "t0"


def test_tls_settings_name_zenohs_keys_and_refuse_half_identities(tmp_path: Path) -> None:
    s = tls_settings("ca.pem", "me.pem", "me.key")
    assert s == {"root_ca_certificate": "ca.pem", "listen_certificate": "me.pem", "listen_private_key": "me.key",
                 "connect_certificate": "me.pem", "connect_private_key": "me.key", "enable_mtls": True}
    assert tls_settings("ca.pem", mtls=False) == {"root_ca_certificate": "ca.pem"}
    with pytest.raises(ConfigError, match="both"):
        tls_settings("ca.pem", "me.pem")
    with pytest.raises(ConfigError, match="mutual TLS needs"):
        tls_settings("ca.pem")
    with pytest.raises(ConfigError, match="not a file"):
        Tls(tmp_path / "nope.pem", tmp_path / "a.pem", tmp_path / "a.key").settings()


async def test_mutual_tls_admits_team_certificates(tmp_path: Path, port: int, heartbeat_link) -> None:
    team = make_certs(tmp_path / "team", ["robot0", "robot1"])
    endpoint = f"tls/localhost:{port}"

    def tls(ident, **kw) -> Tls:
        return Tls(ident.ca, ident.cert, ident.key, **kw)

    a = ZenohBus(TEAM, 0, listen=[endpoint], tls=tls(team["robot0"]))
    b = ZenohBus(TEAM, 1, connect=[endpoint], tls=tls(team["robot1"]))
    async with a, b:
        await heartbeat_link(a, b, timeout=10)
        # a member of the team joins over the same endpoint
        d = ZenohBus(TEAM, 4, connect=[endpoint], tls=tls(team["robot1"]))
        async with d:
            await d.announce()
            await a.wait_for_peers({4}, timeout=10)
