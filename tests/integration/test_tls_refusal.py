"""Mutual TLS through a router process: who is refused, and who may speak for whom.

- A stranger (no certificate, or one of another CA), even one that trusts the team CA, is
  refused at the TLS handshake: the router's own log names the reason, the stranger's session
  has no router, and it receives none of the team's messages while a member does.
- A member cannot speak for another robot: with the router's access control
  (``team/certs.py``) a process holding robot 1's certificate that puts on robot 0's keys is
  dropped at the router; without it the same put arrives (the test can fail).

Waits are on events (a log line, a message) with generous caps; docs/deployment.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.messages.team import Heartbeat
from kimera_multi_py.comms.zenoh_bus import Tls, ZenohBus
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.ids import SERVER_ID
from kimera_multi_py.team.certs import Identity, make_certs, team_names, write_team_configs
from tests.support.router_proc import NO_CERTIFICATE, UNKNOWN_ISSUER, count_lines, router_process, wait_for_line

pytestmark = pytest.mark.integration
TEAM = "t0"
CAP = 60.0  # seconds: generous on a loaded 2-core machine; the outcome is asserted, not the time


def member(robot: int, ident: Identity, endpoint: str) -> ZenohBus:
    return ZenohBus(TEAM, robot, mode="client", connect=[endpoint], tls=Tls(ident.ca, ident.cert, ident.key))


async def recv_until(sub, cond, cap: float = CAP) -> list:  # type: ignore[no-untyped-def]
    """Messages of ``sub`` up to and including the first for which ``cond`` holds."""
    got = []
    while True:
        msg = await sub.recv(timeout=cap)
        got.append(msg)
        if cond(msg):
            return got


async def test_strangers_are_refused_at_the_handshake_and_hear_nothing(tmp_path: Path, port: int,
                                                                       heartbeat_link) -> None:
    idents = make_certs(tmp_path / "team", team_names(2))
    configs = write_team_configs(tmp_path / "team", idents, TEAM)
    rogue = make_certs(tmp_path / "rogue", ["robot2"])
    endpoint = f"tls/localhost:{port}"
    log = tmp_path / "router.log"
    with router_process(endpoint, configs["router"], log):
        a, b = member(0, idents["robot0"], endpoint), member(1, idents["robot1"], endpoint)
        async with a, b:
            sub = await heartbeat_link(a, b, timeout=CAP)
            ca = idents["robot0"].ca  # both strangers trust the team CA: only their own end is wrong
            strangers = ((2, Tls(ca, mtls=False), NO_CERTIFICATE),
                         (3, Tls(ca, rogue["robot2"].cert, rogue["robot2"].key), UNKNOWN_ISSUER))
            for robot, tls, refusal in strangers:
                seen = count_lines(log, refusal)
                # a client must reach the router to open: its own session fails
                with pytest.raises(ConfigError, match="cannot open a session"):
                    ZenohBus(TEAM, robot, mode="client", connect=[endpoint], tls=tls)
                await wait_for_line(log, refusal, seen, CAP)
                # a peer opens and keeps retrying in the background; each try is refused
                seen = count_lines(log, refusal)
                c = ZenohBus(TEAM, robot, mode="peer", connect=[endpoint], tls=tls)
                async with c:
                    sub_c = c.subscribe(keys.topic_all(TEAM, keys.HEARTBEAT))
                    await c.announce()
                    await wait_for_line(log, refusal, seen, CAP)
                    await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=100 + robot))
                    got = await recv_until(sub, lambda m, r=robot: m.keyframes == 100 + r)
                    assert got[-1].robot == 0  # a member hears the team
                    assert sub_c.pending() == 0  # the stranger heard nothing
                    assert list(c.session.info.routers_zid()) == [] and list(c.session.info.peers_zid()) == []
                    assert robot not in b.peers() and c.peers() == frozenset()
            assert count_lines(log, "invalid peer certificate") >= 1


def _forge(bus: ZenohBus, robot: int, keyframes: int) -> None:
    """Put a well-formed heartbeat under ``robot``'s key and sender id on ``bus``'s session,
    bypassing the bus's own sender check: what a process holding another certificate could do."""
    data = Codec(TEAM, robot).encode(Heartbeat(robot=robot, keyframes=keyframes, status="forged"))
    bus.session.put(keys.topic_key(TEAM, robot, keys.HEARTBEAT), data)


@pytest.mark.parametrize("acl", [True, False], ids=["router-acl", "no-acl"])
async def test_a_member_cannot_speak_for_another_robot(tmp_path: Path, port: int, heartbeat_link,
                                                       acl: bool) -> None:
    idents = make_certs(tmp_path / "team", team_names(3))
    configs = write_team_configs(tmp_path / "team", idents, TEAM)
    router = configs["router"]
    if not acl:  # the control: the same router without the access-control block
        conf = json.loads(router.read_text())
        conf.pop("access_control")
        router = tmp_path / "router_open.json5"
        router.write_text(json.dumps(conf))
    assert ("access_control" in json.loads(router.read_text())) == acl
    endpoint = f"tls/localhost:{port}"
    with router_process(endpoint, router, tmp_path / "router.log"):
        a = member(0, idents["robot0"], endpoint)
        liar = member(1, idents["robot1"], endpoint)  # a team member with robot 1's certificate
        watcher = member(2, idents["robot2"], endpoint)
        async with a, liar, watcher:
            sub = await heartbeat_link(a, watcher, timeout=CAP)
            await liar.announce()
            await watcher.wait_for_peers({1}, timeout=CAP)
            await liar.wait_for_subscribers(liar.key(keys.HEARTBEAT), timeout=CAP)
            # the liar speaks as robot 0 and as the server, then as itself (a marker on the same
            # link: the router handles one link's messages in order)
            for _ in range(3):
                _forge(liar, 0, 666)
                _forge(liar, SERVER_ID, 667)
            await liar.publish(liar.key(keys.HEARTBEAT), Heartbeat(robot=1, keyframes=7, status="marker"))
            got = await recv_until(sub, lambda m: m.robot == 1 and m.status == "marker")
            # robot 0 itself still speaks
            await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=8, status="real"))
            got += await recv_until(sub, lambda m: m.robot == 0 and m.status == "real")
            forged = [m for m in got if m.status == "forged"]
            if acl:
                assert forged == []  # dropped at the router
                assert 0 in watcher.peers() and 1 in watcher.peers()
            else:
                assert {m.robot for m in forged} == {0, SERVER_ID}
