"""Strangers and a liar against a real ``kimera-multi launch --tls`` team (OS processes).

While the team runs, a stranger without a certificate and one with another CA's are refused
at the handshake (the team router's log names the reason) and hear none of the team's progress
messages while a tool holding the team's observer certificate does; a process holding robot
1's certificate puts progress messages under robot 0's id, and the router drops them. The
team then completes with every keyframe (docs/deployment.md).
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import pytest

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.messages.team import AgentState
from kimera_multi_py.comms.zenoh_bus import Tls, ZenohBus
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.ids import OBSERVER_ID
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.team.certs import identity
from tests.support.router_proc import NO_CERTIFICATE, UNKNOWN_ISSUER, count_lines, wait_for_line

REPO = Path(__file__).resolve().parents[2]
FAULTS = REPO / "sims" / "faults.toml"
TEAM = "t0"
CAP = 120.0  # generous caps on events; nothing here asserts a duration
pytestmark = pytest.mark.integration


async def _wait_file(path: Path, proc: subprocess.Popen[bytes], cap: float = CAP) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + cap
    while not path.exists():
        assert proc.poll() is None, f"launch exited early ({proc.returncode})"
        assert loop.time() < deadline, f"{path} did not appear"
        await asyncio.sleep(0.1)


async def _open_client(robot: int, endpoint: str, tls: Tls, cap: float = CAP) -> ZenohBus:
    """A client session on the team's router, once the router listens (the launcher writes the
    endpoint when it starts the router, which may take a while on a loaded machine)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + cap
    while True:
        try:
            return ZenohBus(TEAM, robot, mode="client", connect=[endpoint], tls=tls)
        except ConfigError:
            if loop.time() > deadline:
                raise
            await asyncio.sleep(0.2)


async def _states_from(sub, robots: set[int], cap: float = CAP) -> list[AgentState]:  # type: ignore[no-untyped-def]
    got: list[AgentState] = []
    while not robots <= {m.robot for m in got}:
        got.append(await sub.recv(timeout=cap))
    return got


async def _probe(out: Path, proc: subprocess.Popen[bytes]) -> None:
    certs = out / "certs"
    await _wait_file(out / "logs" / "endpoint", proc)
    await _wait_file(certs / "observer.json5", proc)
    endpoint = (out / "logs" / "endpoint").read_text().strip()
    log = out / "logs" / "router.log"
    obs, r1 = identity(certs, "observer"), identity(certs, "robot1")
    from kimera_multi_py.team.certs import make_certs

    rogue = make_certs(out / "rogue", ["robot0"])["robot0"]
    tool = await _open_client(OBSERVER_ID - 1, endpoint, Tls(obs.ca, obs.cert, obs.key))
    async with tool:
        sub = tool.subscribe(keys.topic_all(TEAM, keys.AGENT_STATE))
        await _states_from(sub, {0, 1})  # the team runs and a member hears it
        for robot, tls, refusal in ((20, Tls(obs.ca, mtls=False), NO_CERTIFICATE),
                                    (21, Tls(obs.ca, rogue.cert, rogue.key), UNKNOWN_ISSUER)):
            seen = count_lines(log, refusal)
            stranger = ZenohBus(TEAM, robot, mode="peer", connect=[endpoint], tls=tls)
            async with stranger:
                sub_s = stranger.subscribe(keys.topic_all(TEAM, keys.AGENT_STATE))
                await wait_for_line(log, refusal, seen, CAP)
                while sub.pending():
                    sub.try_recv()
                await _states_from(sub, {0, 1})  # fresh progress of both robots, heard by the member
                assert sub_s.pending() == 0
                assert list(stranger.session.info.routers_zid()) == []
        # a member with robot 1's certificate speaks as robot 0: dropped at the router
        liar = ZenohBus(TEAM, OBSERVER_ID - 2, mode="client", connect=[endpoint], tls=Tls(r1.ca, r1.cert, r1.key))
        async with liar:
            forged = Codec(TEAM, 0).encode(AgentState(robot=0, keyframes=10**6, stamp=1e6, finished=False, epoch=0,
                                                      complete=False, closures=0, rounds=0, bytes_sent=0))
            for _ in range(5):
                liar.session.put(keys.topic_key(TEAM, 0, keys.AGENT_STATE), forged)
            got = await _states_from(sub, {0, 1})
            got += await _states_from(sub, {0, 1})
            assert all(m.keyframes < 10**6 for m in got)


@pytest.mark.slow
def test_a_launched_tls_team_refuses_strangers_and_impersonation(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "kimera_multi_py.cli.main", "launch", str(FAULTS), "--robots",
                             "2", "--out", str(out), "--rate", "1", "--tls", "--pgo-period", "20",
                             # robots 0 and 1 of this floor close no loop with each other, so their frames stay
                             # apart and each would wait the whole default cap (60 s) for a frame gap
                             "--linger-max", "5"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=REPO)
    try:
        asyncio.run(_probe(out, proc))
        text, _ = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, text.decode(errors="replace")[-3000:]
    router = json.loads((out / "certs" / "router.json5").read_text())
    assert router["access_control"]["default_permission"] == "deny"
    results = json.loads((out / "results.json").read_text())
    sim = Simulation(load_scenario(FAULTS, robots=2), seed=0)
    assert [r["keyframes"] for r in results["robots"]] == [len(p.stamps) for p in sim.plans]
