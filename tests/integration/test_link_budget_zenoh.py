"""ZenohBus under a link budget, two real sessions on 127.0.0.1 (scouting off): a PGO status
published after a backlog of map traffic overtakes it; with FIFO it arrives last. Queries and
replies cross the budgeted link, and the link's figures match the counters."""

from __future__ import annotations

import numpy as np
import pytest
import zenoh

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.link_budget import LinkBudget
from kimera_multi_py.comms.messages.maps import MapDelta
from kimera_multi_py.comms.messages.pgo import PgoStatus
from kimera_multi_py.comms.messages.team import Ping
from kimera_multi_py.comms.zenoh_bus import ZenohBus

pytestmark = pytest.mark.integration
TEAM = "t0"
MAPS = 12


def _delta(n: int) -> MapDelta:
    return MapDelta(robot=0, round=n, frame=0, resolution=0.1, depth=16, full=False,
                    keys=np.arange(n, dtype=np.int64), logodds=np.ones((n, 4), np.int8), scale=1.0)


async def _backlog_then_status(port: int, policy: str, route_ready) -> list[str]:
    """Robot 0 publishes MAPS map deltas (~22 kB each, each put alone) then one PGO status at 100 kB/s; the
    order robot 1 receives them in."""
    budget = LinkBudget(100, policy=policy)  # type: ignore[arg-type]
    a = ZenohBus(TEAM, 0, listen=[f"tcp/127.0.0.1:{port}"], budget=budget)
    b = ZenohBus(TEAM, 1, connect=[f"tcp/127.0.0.1:{port}"], budget=budget)
    async with a, b:
        sub = b.subscribe(keys.team_all(TEAM))
        probe = Codec(TEAM, 0).encode(Ping(robot=0, nonce=1, sent_ns=0))
        for topic in (keys.MAP_DELTA, keys.PGO_STATUS):
            await a.wait_for_subscribers(a.key(topic), timeout=5)
        await route_ready(lambda: a.session.put(a.key(keys.PING), probe,
                                                congestion_control=zenoh.CongestionControl.BLOCK), sub, reset=(a, b))
        for i in range(MAPS):
            await a.publish(a.key(keys.MAP_DELTA), _delta(1800 + i))
        await a.publish(a.key(keys.PGO_STATUS), PgoStatus(robot=0, round=1, ready=False, cost=1.0, rel_change=0.1))
        got = [type(await sub.recv(timeout=30)).__name__ for _ in range(MAPS + 1)]
        rep = a.link_report()["0->*"]
        sent = a.counters.total("sent")
        assert rep["bytes"] == sent.bytes and rep["queued_messages"] == 0 and rep["dropped_messages"] == 0
        assert rep["queue_delay_max_s"] > 0
        assert b.counters.dropped == {}
    return got


async def test_pgo_overtakes_map_backlog_on_zenoh(port: int, route_ready) -> None:
    got = await _backlog_then_status(port, "priority", route_ready)
    assert sorted(got) == sorted(["MapDelta"] * MAPS + ["PgoStatus"])
    # at most the transfers the link had started before the status was published went first
    assert got.index("PgoStatus") <= 3, got


async def test_fifo_lets_the_map_backlog_go_first(port: int, route_ready) -> None:
    got = await _backlog_then_status(port, "fifo", route_ready)
    assert got.index("PgoStatus") == MAPS, got


async def test_queries_cross_the_budgeted_link(port: int) -> None:
    budget = LinkBudget(50)
    a = ZenohBus(TEAM, 0, listen=[f"tcp/127.0.0.1:{port}"], budget=budget)
    b = ZenohBus(TEAM, 1, connect=[f"tcp/127.0.0.1:{port}"], budget=budget)
    async with a, b:
        await a.serve(keys.keyframe_key(TEAM, 0, "*"), lambda key, req: _delta(3000))
        replies = []
        for _ in range(50):  # until the queryable's route is up
            replies = await b.query(keys.keyframe_key(TEAM, 0, 7), timeout=2.0)
            if replies:
                break
        assert len(replies) == 1 and isinstance(replies[0], MapDelta) and len(replies[0].keys) == 3000
        rep = a.link_report()["0->*"]
        assert rep["messages"] >= 1 and rep["bytes"] >= 3000 * 5  # the reply's bytes crossed the link
        assert rep["bytes"] == a.counters.total("sent").bytes
