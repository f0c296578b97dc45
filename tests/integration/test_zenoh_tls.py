"""Two ZenohBus sessions over TLS on loopback, with certificates made in the test; a session
that does not trust the team's CA cannot join: its own session fails to open. Strangers refused
by the other end (mutual TLS), and what they hear, are in test_tls_refusal.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.messages.team import Heartbeat
from kimera_multi_py.comms.zenoh_bus import ZenohBus
from kimera_multi_py.core.errors import ConfigError

pytestmark = pytest.mark.integration
TEAM = "t0"


def write_config(
    path: Path, mode: str, endpoints: dict[str, list[str]], tls: dict[str, str]
) -> Path:
    """A --zenoh-config file: where TLS goes."""
    conf = {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}},
        **{k: {"endpoints": v} for k, v in endpoints.items()},
        "transport": {"link": {"tls": tls}},
    }
    path.write_text(json.dumps(conf, indent=2))
    return path


async def test_tls_sessions_talk_and_a_stranger_cannot_join(
    tmp_path: Path, port: int, pki, rogue_pki, wait_until, heartbeat_link
) -> None:
    endpoint = f"tls/localhost:{port}"
    listener = write_config(tmp_path / "listener.json5", "peer", {"listen": [endpoint]}, {
        "root_ca_certificate": str(pki.ca),
        "listen_private_key": str(pki.key),
        "listen_certificate": str(pki.cert),
    })
    member = write_config(tmp_path / "member.json5", "peer", {"connect": [endpoint]},
                          {"root_ca_certificate": str(pki.ca)})
    stranger_client = write_config(tmp_path / "stranger_client.json5", "client",
                                   {"connect": [endpoint]},
                                   {"root_ca_certificate": str(rogue_pki.ca)})

    a = ZenohBus(TEAM, 0, config_file=listener)
    b = ZenohBus(TEAM, 1, config_file=member)
    async with a, b:
        sub = await heartbeat_link(a, b, timeout=5)
        await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=5, status="tls"))
        got = await sub.recv(timeout=5)
        assert (got.robot, got.keyframes, got.status) == (0, 5, "tls")

        # a client that does not trust the team CA fails to open at all
        with pytest.raises(ConfigError, match="cannot open a session"):
            ZenohBus(TEAM, 2, config_file=stranger_client)
