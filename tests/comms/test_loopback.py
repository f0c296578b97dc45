"""LoopbackBus: delivery, fault statistics against the configured rates, determinism,
partitions, presence, queries, isolation and counters."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import Bus
from kimera_multi_py.comms.clouds import pack_cloud
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.loopback import Faults, LoopbackNetwork, Partition
from kimera_multi_py.comms.messages.closures import LoopClosureReply
from kimera_multi_py.comms.messages.pgo import PublicPoses
from kimera_multi_py.comms.messages.team import Heartbeat, Ping
from kimera_multi_py.comms.stream import BusClosedError
from kimera_multi_py.core.errors import ConfigError, MessageError


def ping(robot: int, nonce: int) -> Ping:
    return Ping(robot=robot, nonce=nonce, sent_ns=0)


async def drain(sub) -> list:
    out = []
    while sub.pending():
        out.append(await sub.recv(timeout=1.0))
    return out


async def send_many(faults: Faults, n: int, seed: int = 0) -> tuple[list[int], LoopbackNetwork]:
    net = LoopbackNetwork(seed=seed, faults=faults, queue_size=4 * n)
    a, b = net.bus(0), net.bus(1)
    sub = b.subscribe(keys.topic_all("t0", keys.PING))
    for i in range(n):
        await a.publish(a.key(keys.PING), ping(0, i))
    await net.settle()
    got = [m.nonce for m in await drain(sub)]
    await a.close()
    await b.close()
    return got, net


async def test_pub_sub_delivers_in_order_and_satisfies_the_protocol() -> None:
    net = LoopbackNetwork()
    a, b = net.bus(0), net.bus(1)
    assert isinstance(a, Bus)
    sub_all = b.subscribe(keys.team_all("t0"))
    sub_hb = b.subscribe(keys.topic_all("t0", keys.HEARTBEAT))
    poses = PublicPoses(robot=0, round=1, keys=[7], poses=np.eye(4)[None])
    await a.publish(a.key(keys.PUBLIC_POSES), poses)
    await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=4))
    assert await sub_all.recv(timeout=1) == poses
    assert (await sub_all.recv(timeout=1)).keyframes == 4
    assert (await sub_hb.recv(timeout=1)).keyframes == 4
    assert sub_hb.pending() == 0
    # a robot may only publish on its own keys
    with pytest.raises(MessageError, match="^key"):
        await a.publish(b.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=4))
    with pytest.raises(MessageError):
        await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=1, keyframes=4))
    await a.close()
    await b.close()


async def test_fault_statistics_match_configured_rates() -> None:
    n = 4000
    f = Faults(drop=0.2, duplicate=0.1, reorder=0.1, delay=0.002, jitter=0.001,
               reorder_delay=0.004)
    got, net = await send_many(f, n, seed=5)
    s = net.stats
    assert s.attempted == n
    assert s.dropped + s.delivered == n
    # each rate within 4 binomial standard deviations
    assert abs(s.dropped - 0.2 * n) < 4 * math.sqrt(n * 0.2 * 0.8)
    assert abs(s.duplicated - 0.1 * s.delivered) < 4 * math.sqrt(s.delivered * 0.1 * 0.9)
    copies = s.delivered + s.duplicated
    assert abs(s.reordered - 0.1 * copies) < 4 * math.sqrt(copies * 0.1 * 0.9)
    # what the subscriber saw agrees with the link statistics
    assert len(got) == copies
    assert len(set(got)) == s.delivered
    inversions = sum(1 for x, y in zip(got, got[1:], strict=False) if y < x)
    assert inversions > 0.02 * n  # reordering and jitter really reorder


async def test_no_faults_means_exact_in_order_delivery() -> None:
    got, net = await send_many(Faults(), 500)
    assert got == list(range(500))
    assert net.stats.delayed == 0


async def test_same_seed_same_run_other_seed_other_run() -> None:
    f = Faults(drop=0.3, duplicate=0.2, reorder=0.3, delay=0.001, jitter=0.001)
    first, _ = await send_many(f, 300, seed=11)
    second, _ = await send_many(f, 300, seed=11)
    third, _ = await send_many(f, 300, seed=12)
    assert first == second
    assert first != third


async def test_delay_holds_messages_back() -> None:
    net = LoopbackNetwork(faults=Faults(delay=0.05))
    a, b = net.bus(0), net.bus(1)
    sub = b.subscribe(keys.topic_all("t0", keys.PING))
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    await a.publish(a.key(keys.PING), ping(0, 1))
    assert sub.pending() == 0
    await sub.recv(timeout=1.0)
    assert loop.time() - t0 >= 0.045
    await a.close()
    await b.close()


async def test_partition_window_cuts_links_and_hides_peers() -> None:
    clock = [0.0]
    part = Partition(({0}, {1, 2}), start=10.0, end=20.0)
    net = LoopbackNetwork(faults=Faults(partitions=(part,)), clock=lambda: clock[0])
    a, b, c = net.bus(0), net.bus(1), net.bus(2)
    for bus in (a, b, c):
        await bus.announce()
    sub_b = b.subscribe(keys.topic_all("t0", keys.PING))
    sub_c = c.subscribe(keys.topic_all("t0", keys.PING))
    for t in (5.0, 15.0, 25.0):
        clock[0] = t
        await a.publish(a.key(keys.PING), ping(0, int(t)))
        await b.publish(b.key(keys.PING), ping(1, int(t)))
        if t == 15.0:
            assert b.peers() == {2} and a.peers() == frozenset()
    assert [(m.robot, m.nonce) for m in await drain(sub_b)] == [
        (0, 5), (1, 5), (1, 15), (0, 25), (1, 25)]
    assert [(m.robot, m.nonce) for m in await drain(sub_c)] == [
        (0, 5), (1, 5), (1, 15), (0, 25), (1, 25)]
    assert net.stats.partitioned == 2
    # manual partition and heal
    net.partition([{0, 1}, {2}])
    await a.publish(a.key(keys.PING), ping(0, 99))
    assert sub_c.pending() == 0 and sub_b.pending() == 1
    net.heal()
    await a.publish(a.key(keys.PING), ping(0, 100))
    assert (await sub_c.recv(timeout=1)).nonce == 100
    for bus in (a, b, c):
        await bus.close()


async def test_presence_events_and_close() -> None:
    net = LoopbackNetwork(robots=range(3))
    a, b = net.bus(0), net.bus(1)
    events = b.presence()
    await a.announce()
    await b.announce()
    assert await b.wait_for_peers({0}, timeout=1) == {0}
    assert (await events.recv(timeout=1)).alive
    late = net.bus(2)  # sees those already announced
    assert late.peers() == {0, 1}
    await a.close()
    ev = await events.recv(timeout=1)
    assert (ev.robot, ev.alive) == (0, False)
    await b.wait_for_absent({0}, timeout=1)
    with pytest.raises(TimeoutError):
        await b.wait_for_peers({0}, timeout=0.05)
    with pytest.raises(BusClosedError):
        await a.publish(a.key(keys.PING), ping(0, 0))
    await b.close()
    await late.close()
    assert events.closed


async def test_query_reply_and_failures() -> None:
    net = LoopbackNetwork()
    a, b = net.bus(0), net.bus(1)
    seen = []

    async def serve(key: str, request):
        seen.append((key, request))
        kf = int(key.rsplit("/", 1)[1])
        if kf == 13:
            raise RuntimeError("boom")
        return LoopClosureReply(
            robot=0, request_id=request.nonce if request else 0, keyframe=kf, found=True,
            pose=np.eye(4), num_points=5, cloud=pack_cloud(np.ones((5, 3)), np.arange(5)),
            object_centroids=np.zeros((0, 3), np.float32), object_classes=np.zeros(0, np.int32))

    handle = await a.serve(keys.keyframe_key("t0", 0, "*"), serve)
    replies = await b.query(keys.keyframe_key("t0", 0, 17), ping(1, 9), timeout=1.0)
    assert len(replies) == 1 and replies[0].keyframe == 17 and replies[0].request_id == 9
    assert seen[0][0] == "kmp/t0/r0/keyframe/17" and seen[0][1].robot == 1
    assert await b.query(keys.keyframe_key("t0", 0, 13), timeout=0.2) == []
    assert a.counters.dropped["handler_error"] == 1
    assert await b.query(keys.keyframe_key("t0", 1, 17), timeout=0.2) == []  # nobody serves it
    handle.close()
    assert await b.query(keys.keyframe_key("t0", 0, 17), timeout=0.2) == []
    assert b.counters.received["keyframe"].messages == 1
    assert a.counters.sent["keyframe"].messages == 1
    await a.close()
    await b.close()


async def test_query_times_out_when_links_drop_everything() -> None:
    net = LoopbackNetwork(faults=Faults(drop=1.0))
    a, b = net.bus(0), net.bus(1)
    await a.serve(keys.keyframe_key("t0", 0, "*"), lambda k, r: Heartbeat(robot=0, keyframes=1))
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    assert await asyncio.wait_for(b.query(keys.keyframe_key("t0", 0, 1), timeout=0.1), 60) == []
    assert loop.time() - t0 >= 0.09  # on the loop's clock a lost query waits its timeout (not on a custom one)
    await a.close()
    await b.close()


async def test_foreign_unknown_and_spoofed_senders_are_dropped_and_counted() -> None:
    net = LoopbackNetwork(robots=range(3))
    b = net.bus(1)
    other_team = net.bus(0, team="t1")
    sub = b.subscribe(keys.team_all("t0"))
    # another team's bus cannot even address our keys...
    with pytest.raises(MessageError):
        await other_team.publish(keys.topic_key("t0", 0, keys.PING), ping(0, 1))
    # ...and forged bytes that reach us anyway are dropped and counted
    foreign = Codec("t1", 0).encode(ping(0, 1))
    unknown = Codec("t0", 7).encode(ping(7, 1))
    spoofed = Codec("t0", 2).encode(ping(2, 1))
    garbage = b"\x93\x01\x02"
    assert b.accept("kmp/t0/r0/diag/ping", foreign) is None
    assert b.accept("kmp/t0/r7/diag/ping", unknown) is None
    assert b.accept("kmp/t0/r0/diag/ping", spoofed) is None  # r2 posing as r0
    assert b.accept("kmp/t1/r2/diag/ping", spoofed) is None
    assert b.accept("kmp/t0/r0/diag/ping", garbage) is None
    assert b.counters.dropped == {"team": 2, "src": 1, "key": 1, "invalid": 1}
    assert b.accept("kmp/t0/r2/diag/ping", spoofed) is not None
    assert sub.pending() == 0
    await b.close()
    await other_team.close()


async def test_counters_agree_between_sender_and_receiver() -> None:
    net = LoopbackNetwork()
    a, b = net.bus(0), net.bus(1)
    sub = b.subscribe(keys.team_all("t0"))
    for k in range(5):
        await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=k))
    await a.publish(a.key(keys.PUBLIC_POSES),
                    PublicPoses(robot=0, round=0, keys=np.arange(10),
                                poses=np.random.default_rng(0).normal(size=(10, 4, 4))))
    assert len(await drain(sub)) == 6
    sa, sb = a.counters.snapshot(), b.counters.snapshot()
    assert sa["sent"] == sb["received"]
    assert sa["sent"]["heartbeat"]["messages"] == 5
    assert sa["sent"]["pgo/public_poses"]["bytes"] > 10 * 16 * 8
    assert a.counters.total("sent").messages == 6
    await a.close()
    await b.close()


async def test_full_queue_drops_and_counts_and_close_ends_iteration() -> None:
    net = LoopbackNetwork(queue_size=3)
    a, b = net.bus(0), net.bus(1)
    sub = b.subscribe(keys.team_all("t0"))
    for i in range(5):
        await a.publish(a.key(keys.PING), ping(0, i))
    assert b.counters.dropped["queue_full"] == 2

    async def consume() -> list[int]:
        return [m.nonce async for m in sub]

    task = asyncio.create_task(consume())
    await asyncio.sleep(0)
    sub.close()
    assert await asyncio.wait_for(task, 1.0) in ([], [0], [0, 1], [0, 1, 2])
    await a.close()
    await b.close()


def test_config_errors() -> None:
    with pytest.raises(ConfigError, match="faults.drop"):
        Faults(drop=1.5)
    with pytest.raises(ConfigError, match="faults.delay"):
        Faults(delay=-1)
    net = LoopbackNetwork()
    net.bus(0)
    with pytest.raises(ConfigError, match="robot"):
        net.bus(0)
    with pytest.raises(MessageError, match="robot"):
        LoopbackNetwork(robots={1}).bus(0)


async def test_wait_for_subscribers() -> None:
    net = LoopbackNetwork()
    a, b = net.bus(0), net.bus(1)
    key = a.key(keys.PING)
    with pytest.raises(TimeoutError):
        await a.wait_for_subscribers(key, timeout=0.05)
    waiter = asyncio.create_task(a.wait_for_subscribers(key, timeout=1))
    await asyncio.sleep(0)
    b.subscribe(keys.topic_all("t0", keys.HEARTBEAT))  # does not match
    await asyncio.sleep(0)
    assert not waiter.done()
    b.subscribe(keys.topic_all("t0", keys.PING))
    await asyncio.wait_for(waiter, 1)
    await a.close()
    await b.close()
