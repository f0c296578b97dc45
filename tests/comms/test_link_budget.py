"""Link budget: the token bucket, the priority scheduler against FIFO (map traffic must never
starve the pose-graph optimisation), drops past the queue's cap, and the budgeted loopback."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.link_budget import (
    CONTROL,
    MAP,
    OBJECTS,
    LinkBudget,
    LinkQueue,
    TokenBucket,
    budget_of,
    priority_of,
)
from kimera_multi_py.comms.loopback import Faults, LoopbackNetwork
from kimera_multi_py.comms.messages.maps import MapDelta
from kimera_multi_py.comms.messages.pgo import PgoStatus
from kimera_multi_py.core.errors import ConfigError


# ---------------------------------------------------------------------------- token bucket
def test_bucket_burst_then_rate() -> None:
    b = TokenBucket(rate=1000.0, burst=500.0)
    assert b.send(400, 0.0) == 0.0  # within the burst: at once
    assert b.send(100, 0.0) == 0.0
    assert b.send(1000, 0.0) == pytest.approx(1.0)  # the bucket is empty: at the rate
    assert b.send(500, 1.0) == pytest.approx(1.5)  # starts when the last ended
    # idle for long: refills to the burst, never beyond
    assert b.refill(100.0) == pytest.approx(500.0)
    assert b.send(2500, 100.0) == pytest.approx(102.0)  # larger than the bucket: still goes


def test_bucket_long_run_rate() -> None:
    b = TokenBucket(rate=2000.0, burst=1000.0)
    end = 0.0
    for _ in range(100):
        end = b.send(1000, 0.0)
    # 100 kB through a 2 kB/s link after a 1 kB burst
    assert end == pytest.approx((100_000 - 1000) / 2000.0)


def test_budget_validation() -> None:
    for bad in (0.0, -5.0, math.inf, math.nan):
        with pytest.raises(ConfigError):
            LinkBudget(bad)
    with pytest.raises(ConfigError):
        LinkBudget(50, policy="lifo")  # type: ignore[arg-type]
    assert budget_of(None) is None and budget_of(0) is None
    assert budget_of(50).rate == 50_000.0  # type: ignore[union-attr]


def test_priority_table() -> None:
    assert priority_of(keys.topic_key("t0", 1, keys.PGO_STATUS)) == CONTROL
    assert priority_of(keys.keyframe_key("t0", 1, 17)) == CONTROL
    assert priority_of(keys.topic_key("t0", 1, keys.OBJECTS)) == OBJECTS
    assert priority_of(keys.topic_key("t0", 1, keys.MAP_EVIDENCE)) == MAP
    assert priority_of(keys.MAP_EVIDENCE) == MAP


# ---------------------------------------------------------------------------- scheduling
def _flood(policy: str) -> tuple[dict[str, float], LinkQueue]:
    """Forty 10 kB map messages, then a PGO status, then objects, all at t=0 on a 20 kB/s link.
    Returns each message's delivery time."""
    q = LinkQueue(LinkBudget(20, burst_s=0.0, policy=policy))  # type: ignore[arg-type]
    for i in range(40):
        q.push(f"map{i}", 10_000, MAP, 0.0)
    q.push("objects", 2_000, OBJECTS, 0.0)
    q.push("pgo", 200, CONTROL, 0.0)
    q.push("map_late", 10_000, MAP, 1.0)
    q.push("pgo_late", 200, CONTROL, 1.0)
    return {item: end for item, end in q.advance(1e9)}, q


def test_pgo_not_starved_by_map_traffic() -> None:
    """Under a budget, a PGO message waits for at most the one message under way, however much
    map traffic is queued before it. (With FIFO it waits for the whole flood: see below.)"""
    done, q = _flood("priority")
    one_map = 10_000 / 20_000
    assert done["pgo"] <= one_map + 200 / 20_000 + 1e-9
    assert done["pgo_late"] <= 1.0 + one_map + 200 / 20_000 + 1e-9
    assert done["objects"] < min(v for k, v in done.items() if k.startswith("map") and k != "map0")
    assert all(done[f"map{i}"] < done[f"map{i + 1}"] for i in range(39))  # within a class: in order
    assert q.stats.delay_max_by_class[CONTROL] < 1.0
    assert q.pending() == (0, 0)


def test_fifo_starves_pgo() -> None:
    """The baseline the priority scheduler exists for: FIFO delivers the PGO status after all
    forty map messages (20 s at 20 kB/s). The test above fails under this policy."""
    done, _ = _flood("fifo")
    assert done["pgo"] > 20.0
    with pytest.raises(AssertionError):
        assert done["pgo"] <= 10_000 / 20_000 + 200 / 20_000 + 1e-9


def test_deliveries_in_time_order_and_delays() -> None:
    q = LinkQueue(LinkBudget(1, burst_s=0.0))  # 1 kB/s
    q.push("a", 500, MAP, 0.0)
    assert q.advance(0.4) == []
    assert q.next_done() == pytest.approx(0.5)
    q.push("b", 500, CONTROL, 0.45)  # waits for "a": never interrupts a transfer
    assert q.advance(2.0) == [("a", pytest.approx(0.5)), ("b", pytest.approx(1.0))]
    rep = q.report()
    assert rep["messages"] == 2 and rep["bytes"] == 1000
    assert rep["queue_delay_max_s"] == pytest.approx(0.55)
    assert rep["queue_delay_mean_s"] == pytest.approx((0.5 + 0.55) / 2)
    assert rep["queued_messages"] == 0 and rep["dropped_messages"] == 0


def test_queue_cap_drops_lowest_class_first() -> None:
    q = LinkQueue(LinkBudget(1, burst_s=0.0, queue_s=10.0))  # at most 10 kB queued
    assert q.push("m0", 4_000, MAP, 0.0)  # under way at once
    for i in range(1, 4):
        assert q.push(f"m{i}", 4_000, MAP, 0.0) == (i < 3)  # m3 does not fit: dropped
    assert q.push("pgo", 4_000, CONTROL, 0.0)  # evicts the newest map message (m2)
    assert q.stats.dropped_messages == 2 and q.stats.dropped_bytes == 8_000
    assert q.pending() == (3, 12_000)  # m0 under way, m1 and pgo queued
    assert [item for item, _ in q.advance(1e6)] == ["m0", "pgo", "m1"]


# ---------------------------------------------------------------------------- the loopback network
class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t


def _map_delta(robot: int, n: int) -> MapDelta:
    return MapDelta(robot=robot, round=0, frame=robot, resolution=0.1, depth=16, full=False,
                    keys=np.arange(n, dtype=np.int64), logodds=np.ones((n, 4), np.int8), scale=1.0)


async def test_loopback_budget_on_the_simulated_clock() -> None:
    clock = _Clock()
    net = LoopbackNetwork(clock=clock.now, budget=LinkBudget(20, burst_s=0.0), queue_size=1000)
    a, b = net.bus(0), net.bus(1)
    sub = b.subscribe(keys.team_all("t0"))
    for i in range(10):
        await a.publish(a.key(keys.MAP_DELTA), _map_delta(0, 1000 + i))
    await a.publish(a.key(keys.PGO_STATUS), PgoStatus(robot=0, round=1, ready=False, cost=1.0, rel_change=0.1))
    await net.settle()  # nothing moves without the clock
    assert net.pump() == 0 and sub.pending() == 0
    first = net.next_delivery()
    assert first is not None and first > 0
    clock.t = first
    assert net.pump() == 1
    clock.t = first + 0.05  # the status goes next, before the nine other map messages
    net.pump()
    got = [sub.try_recv() for _ in range(sub.pending())]
    assert [type(m).__name__ for m in got] == ["MapDelta", "PgoStatus"]
    clock.t = 1e4
    net.pump()
    assert sub.pending() == 9
    rep = net.link_report()["0->1"]
    assert rep["messages"] == 11 and rep["queued_messages"] == 0
    assert rep["bytes"] == a.counters.total("sent").bytes
    # 10 map messages of ~5 kB at 20 kB/s: the last one waited about their whole transfer
    assert rep["queue_delay_max_s"] == pytest.approx(rep["bytes"] / 20_000, rel=1e-6)


async def test_loopback_budget_on_the_loop_clock() -> None:
    net = LoopbackNetwork(budget=LinkBudget(500, burst_s=0.0), queue_size=1000)
    a, b = net.bus(0), net.bus(1)
    sub = b.subscribe(keys.team_all("t0"))
    for i in range(5):
        await a.publish(a.key(keys.MAP_DELTA), _map_delta(0, 500 + i))
    assert sub.pending() == 0
    await net.settle(timeout=5.0)
    assert sub.pending() == 5
    assert net.link_report()["0->1"]["messages"] == 5


def test_budget_refuses_fault_delays() -> None:
    with pytest.raises(ConfigError):
        LoopbackNetwork(faults=Faults(delay=0.01), budget=LinkBudget(50))


@pytest.mark.parametrize("policy", ["priority", "fifo"])
def test_a_link_never_beats_its_rate(policy: str) -> None:
    """Random traffic: by any time t the link has finished at most burst + rate * t bytes, and
    every message is delivered once, or dropped, never both."""
    rng = np.random.default_rng(3)
    budget = LinkBudget(10, burst_s=0.5, queue_s=30.0, policy=policy)  # type: ignore[arg-type]
    q = LinkQueue(budget)
    t, sizes, done = 0.0, {}, []
    for i in range(600):
        t += float(rng.exponential(0.05))
        sizes[i] = int(rng.integers(10, 8000))
        q.push(i, sizes[i], int(rng.integers(0, 3)), t)
        done += q.advance(t)
    done += q.advance(1e9)
    ends = np.array([end for _, end in done])
    assert np.all(np.diff(ends) >= 0)
    finished = np.cumsum([sizes[item] for item, _ in done])
    assert np.all(finished <= budget.burst + budget.rate * ends + 1e-6)
    items = [item for item, _ in done]
    assert len(set(items)) == len(items)
    assert len(items) + q.stats.dropped_messages == len(sizes) and q.stats.dropped_messages > 0
