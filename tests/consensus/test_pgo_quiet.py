"""Lost messages cost rounds, not wall time: on the in-process network a round's wait ends when
the team is quiet (pgo/runtime.py), so a lossy run is the same on every run, whatever the
wall-clock ``round_timeout`` and however loaded the machine."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np

from kimera_multi_py.comms.loopback import Faults, LoopbackNetwork
from kimera_multi_py.pgo.gn import make_agent
from kimera_multi_py.pgo.local_graph import split_local
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.runtime import run_team
from kimera_multi_py.workflow.pgo_benchmark import load_graph, run_pgo


def _run(pgo_data: Path, round_timeout: float, method: str = "block_sor"):  # type: ignore[no-untyped-def]
    graph, robots, rounds = ("smallGrid3D", 4, 300) if method == "block_sor" else ("tinyGrid3D", 3, 600)
    return run_pgo([pgo_data / f"{graph}.g2o"], robots=robots, drop=0.1, seed=3, max_rounds=rounds,
                   round_timeout=round_timeout, params=PgoParams(method=method))  # type: ignore[arg-type]


def test_a_lossy_run_is_deterministic_and_ignores_the_wall_clock(pgo_data: Path) -> None:
    a = _run(pgo_data, 0.05)
    b = _run(pgo_data, 0.05)
    tiny = _run(pgo_data, 1e-9)  # a wall-clock timeout that would expire at once
    assert a.dropped > 0 and a.timeouts > 0  # losses happened and cost timeouts
    for other in (b, tiny):
        assert (other.rounds, other.timeouts, other.dropped) == (a.rounds, a.timeouts, a.dropped)
        np.testing.assert_array_equal(other.history, a.history)
        np.testing.assert_array_equal(other.poses, a.poses)
    assert abs(a.relative_gap) <= 1e-4


def test_gn_pcg_lossy_run_is_deterministic(pgo_data: Path) -> None:
    a = _run(pgo_data, 0.02, "gn_pcg")
    b = _run(pgo_data, 10.0, "gn_pcg")
    assert a.dropped > 0
    assert (a.rounds, a.timeouts) == (b.rounds, b.timeouts)
    np.testing.assert_array_equal(a.history, b.history)
    assert abs(a.relative_gap) <= 1e-6


async def _team_on_a_custom_clock(pgo_data: Path) -> tuple[int, int, np.ndarray]:
    """smallGrid3D, 4 robots, over a loopback network on a frozen custom clock with 10 % loss and
    delays: the rounds, the timeouts and the final poses."""
    graph = load_graph([pgo_data / "smallGrid3D.g2o"], 4)
    agents = [make_agent(local, PgoParams(max_rounds=300)) for local in split_local(graph)]
    net = LoopbackNetwork(seed=3, faults=Faults(drop=0.1, delay=0.01, jitter=0.005), clock=lambda: 0.0,
                          robots=[a.robot for a in agents])
    buses = [net.bus(a.robot) for a in agents]
    # a round timeout that would never end on the wall clock, under a generous hang guard
    stats = await asyncio.wait_for(run_team(agents, buses, 300, round_timeout=1e6), 600)
    for b in buses:
        await b.close()
    assert net.stats.dropped > 0 and net.stats.delayed > 0
    poses = np.empty_like(graph.poses)
    for a in agents:
        poses[graph.robot_indices(a.robot)] = a.state.poses
    return stats.rounds, stats.timeouts, poses


async def test_delays_on_a_custom_clock_are_made_when_the_team_waits(pgo_data: Path) -> None:
    """On a custom clock the delayed deliveries wait for the team: a robot that waits with the
    whole team makes the next ones (no wall time), so the run ends and is the same every time."""
    a = await _team_on_a_custom_clock(pgo_data)
    b = await _team_on_a_custom_clock(pgo_data)
    assert a[1] > 0  # losses cost timeouts
    assert a[:2] == b[:2]
    np.testing.assert_array_equal(a[2], b[2])
