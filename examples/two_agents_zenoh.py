"""Two robots as two AgentNodes over real Zenoh sessions on 127.0.0.1.

Robot 0 listens on a TCP port and robot 1 connects to it: explicit endpoints, multicast
scouting off (ZenohBus's defaults), one Zenoh session per robot, both in this process. Each node
is fed its robot's first keyframes of the two-room simulation (``sims/tiny.toml``) and runs
everything the robot does: loop closures with its peer, the team's PGO epochs and the exact
team map. In deployment each node is its own process (``kimera-multi agent``, docs/deployment.md).

    python examples/two_agents_zenoh.py --keyframes 60 --port 7471
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import time
from pathlib import Path

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.comms.zenoh_bus import ZenohBus
from kimera_multi_py.pgo.params import team_params
from kimera_multi_py.pgo.team import ScheduleParams
from kimera_multi_py.team.build import params_for, source_from_spec

ROOT = Path(__file__).resolve().parents[1]


async def run(scenario: Path, keyframes: int, port: int, team: str) -> dict[int, dict[str, object]]:
    endpoint = f"tcp/127.0.0.1:{port}"
    buses = [ZenohBus(team, 0, robots=(0, 1), listen=[endpoint]),
             ZenohBus(team, 1, robots=(0, 1), connect=[endpoint])]
    sources = [source_from_spec(f"sim:{scenario}", r) for r in (0, 1)]
    schedule = ScheduleParams(period=20.0, round_timeout=0.5, final_grace=1.0)
    nodes = [AgentNode(Agent(r, None, params_for(sources[r])), buses[r], team_params(), schedule)
             for r in (0, 1)]
    try:
        for node in nodes:
            await node.start()
        await buses[0].wait_for_peers({1}, timeout=10)  # presence: liveliness tokens
        await asyncio.gather(*(n.run(itertools.islice(sources[n.robot], keyframes), linger=3.0) for n in nodes))
        return {n.robot: {"keyframes": n.agent.num_keyframes,
                          "inter_robot_edges": len(n.agent.inter_edges),  # PCM-accepted, held by both
                          "pgo_epochs": n.pgo.stats.epochs if n.pgo else 0,
                          "frame": n.frame,
                          "bytes_sent": n.bus.counters.total("sent").bytes}
                for n in nodes}
    finally:
        for node in nodes:
            await node.close()
        for bus in buses:
            await bus.close()


def main(scenario: Path = ROOT / "sims" / "tiny.toml", keyframes: int = 60, port: int = 7471,
         team: str = "example") -> dict[int, dict[str, object]]:
    """Run robots 0 and 1 for ``keyframes`` keyframes each; return what each ended with."""
    return asyncio.run(run(scenario, keyframes, port, team))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", type=Path, default=ROOT / "sims" / "tiny.toml")
    ap.add_argument("--keyframes", type=int, default=60, help="keyframes per robot")
    ap.add_argument("--port", type=int, default=7471, help="TCP port robot 0 listens on (127.0.0.1)")
    ap.add_argument("--team", default="example", help="team id: teams on one network never mix")
    a = ap.parse_args()
    t0 = time.monotonic()
    for robot, summary in main(a.scenario, a.keyframes, a.port, a.team).items():
        print(f"robot {robot}: {summary}")
    print(f"{time.monotonic() - t0:.1f} s")
