"""The loopback network on a custom clock (the simulation's): no wait is a wall-clock wait.

Fault delays run on the network's event time and wait for the owner (``step``, ``settle``); a
query's wait ends when its reply is in or can no longer arrive, whatever its timeout. Each wait
below runs under a generous cap that a wall-clock wait of its timeout would exceed."""

from __future__ import annotations

import asyncio

import numpy as np

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.clouds import pack_cloud
from kimera_multi_py.comms.loopback import Faults, LoopbackNetwork
from kimera_multi_py.comms.messages.closures import LoopClosureReply
from kimera_multi_py.comms.messages.team import Ping

CAP = 60.0  # s: a hang guard; every timeout passed below is far longer
FOREVER = 1e6  # s: a query timeout that would never end on the wall clock


def _reply(key: str, request: Ping | None) -> LoopClosureReply:
    kf = int(key.rsplit("/", 1)[1])
    if kf % 7 == 6:
        raise RuntimeError("no answer")  # the handler fails: nothing is sent back
    return LoopClosureReply(robot=0, request_id=request.nonce if request else 0, keyframe=kf, found=True,
                            pose=np.eye(4), num_points=3, cloud=pack_cloud(np.ones((3, 3)), np.arange(3)),
                            object_centroids=np.zeros((0, 3), np.float32), object_classes=np.zeros(0, np.int32))


async def _queries(faults: Faults, n: int, seed: int = 0) -> tuple[list[int], LoopbackNetwork]:
    """``n`` queries from robot 1 to robot 0 on a frozen custom clock: the keyframes answered."""
    net = LoopbackNetwork(seed=seed, faults=faults, clock=lambda: 0.0)
    a, b = net.bus(0), net.bus(1)
    await a.serve(keys.keyframe_key("t0", 0, "*"), _reply)
    answered = []
    for kf in range(n):
        replies = await asyncio.wait_for(
            b.query(keys.keyframe_key("t0", 0, kf), Ping(robot=1, nonce=kf, sent_ns=0), timeout=FOREVER), CAP)
        answered += [r.keyframe for r in replies]
    assert net.in_flight == 0
    await a.close()
    await b.close()
    return answered, net


async def test_lost_queries_end_at_once_and_answered_ones_get_their_reply() -> None:
    n = 60
    answered, net = await _queries(Faults(drop=0.3), n)
    # every query either got its one reply or was lost: request or reply dropped, or no answer
    assert len(answered) == len(set(answered))
    lost = n - len(answered)
    failed = sum(1 for kf in range(n) if kf % 7 == 6)
    assert not any(kf % 7 == 6 for kf in answered)
    assert net.stats.dropped > 0 and lost >= failed + 1
    # a request is one attempt, a reply another: each answered query crossed both links
    assert net.stats.delivered >= 2 * len(answered)
    again, _ = await _queries(Faults(drop=0.3), n)
    assert again == answered  # deterministic for a seed


async def test_a_delayed_reply_arrives_on_event_time_whatever_the_timeout() -> None:
    # a delay much longer than the query's (wall-clock) timeout: on a custom clock it is event time
    answered, net = await _queries(Faults(delay=5.0, jitter=1.0), 5)
    assert answered == [0, 1, 2, 3, 4]
    assert net.stats.delayed == 10  # request and reply of each


async def test_delayed_deliveries_wait_for_the_owner_and_come_in_due_order() -> None:
    async def run(seed: int) -> list[int]:
        net = LoopbackNetwork(seed=seed, faults=Faults(delay=0.05, jitter=0.04, reorder=0.3), clock=lambda: 0.0,
                              queue_size=100)
        a, b = net.bus(0), net.bus(1)
        sub = b.subscribe(keys.topic_all("t0", keys.PING))
        for i in range(40):
            await a.publish(a.key(keys.PING), Ping(robot=0, nonce=i, sent_ns=0))
        await asyncio.sleep(0.1)  # longer than every delay: still nothing moves by itself
        assert sub.pending() == 0 and net.in_flight == 40
        first = net.step()
        assert first >= 1 and sub.pending() == first and net.in_flight == 40 - first
        await asyncio.wait_for(net.settle(timeout=FOREVER), CAP)
        got = [sub.try_recv().nonce for _ in range(40)]  # type: ignore[union-attr]
        assert net.in_flight == 0 and sub.pending() == 0
        await a.close()
        await b.close()
        return got

    got = await run(3)
    assert sorted(got) == list(range(40)) and got != list(range(40))  # all of them, reordered by their delays
    assert await run(3) == got  # the same order for a seed
    assert await run(4) != got
