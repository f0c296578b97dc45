"""ZenohBus with two (or three) real sessions on free loopback ports."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest
import zenoh

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import Bus
from kimera_multi_py.comms.clouds import pack_cloud
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.messages.closures import LoopClosureReply
from kimera_multi_py.comms.messages.team import Heartbeat, Ping
from kimera_multi_py.comms.stream import BusClosedError
from kimera_multi_py.comms.zenoh_bus import ZenohBus
from kimera_multi_py.core.errors import ConfigError, MessageError
from tests.support.samples import all_random_messages

pytestmark = pytest.mark.integration
TEAM = "t0"


def probe(bus: ZenohBus, key: str, robot: int = 0, team: str = TEAM):
    """A put of one valid Ping from ``robot`` on ``key`` straight into ``bus``'s session."""
    data = Codec(team, robot).encode(Ping(robot=robot, nonce=2**40, sent_ns=0))
    return lambda: bus.session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)


def pair(port: int, **kw) -> tuple[ZenohBus, ZenohBus]:
    a = ZenohBus(TEAM, 0, listen=[f"tcp/127.0.0.1:{port}"], **kw)
    b = ZenohBus(TEAM, 1, connect=[f"tcp/127.0.0.1:{port}"], **kw)
    return a, b


async def test_pub_sub_delivers_every_type_and_counters_agree(port: int, route_ready) -> None:
    a, b = pair(port, robots=range(3))
    async with a, b:
        assert isinstance(a, Bus)
        sub = b.subscribe(keys.team_all(TEAM))
        msgs = all_random_messages(seed=1, robot=0)
        for msg in msgs:
            await a.wait_for_subscribers(a.key(msg.TOPIC), timeout=5)
            await route_ready(probe(a, a.key(msg.TOPIC)), sub, reset=(a, b))
        for msg in msgs:
            await a.publish(a.key(msg.TOPIC), msg)
        got = [await sub.recv(timeout=5) for _ in msgs]
        assert sorted(got, key=lambda m: m.TYPE) == sorted(msgs, key=lambda m: m.TYPE)
        sent, received = a.counters.snapshot()["sent"], b.counters.snapshot()["received"]
        assert sent == received and len(sent) == len(msgs)
        assert all(c["bytes"] > 0 for c in sent.values())
        assert b.counters.dropped == {}


async def test_query_reply(port: int) -> None:
    a, b = pair(port)
    async with a, b:
        async def serve(key: str, request):
            kf = int(key.rsplit("/", 1)[1])
            return LoopClosureReply(
                robot=0, request_id=request.nonce if request else 0, keyframe=kf, found=True,
                pose=np.eye(4), num_points=100,
                cloud=pack_cloud(np.full((100, 3), kf), np.zeros(100, np.int32)),
                object_centroids=np.zeros((0, 3), np.float32), object_classes=np.zeros(0, np.int32))

        await a.serve(keys.keyframe_key(TEAM, 0, "*"), serve)
        await a.announce()
        await b.wait_for_peers({0}, timeout=5)
        replies: list = []
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 5
        while not replies and loop.time() < deadline:  # the queryable's declaration propagates
            replies = await b.query(keys.keyframe_key(TEAM, 0, 42), Ping(robot=1, nonce=7,
                                                                            sent_ns=0), timeout=1)
        assert len(replies) == 1
        assert replies[0].keyframe == 42 and replies[0].request_id == 7
        points, _ = replies[0].points()
        assert points.shape == (100, 3) and float(points[0, 0]) == 42.0
        assert a.counters.received["keyframe"].messages >= 1
        assert b.counters.received["keyframe"].messages == 1
        # nobody serves r2: the query ends by its own timeout (the cap only guards against a hang)
        assert await asyncio.wait_for(b.query(keys.keyframe_key(TEAM, 2, 1), timeout=2), 60) == []


async def test_presence_appears_and_disappears_after_close(port: int) -> None:
    a, b = pair(port)
    events = b.presence()
    await a.announce()
    await b.announce()
    assert await b.wait_for_peers({0}, timeout=5) == {0}
    assert await a.wait_for_peers({1}, timeout=5) == {1}
    ev = await events.recv(timeout=1)
    assert (ev.robot, ev.alive) == (0, True)
    await a.close()
    await b.wait_for_absent({0}, timeout=30)  # a generous cap: the event is what is tested
    ev = await events.recv(timeout=1)
    assert (ev.robot, ev.alive) == (0, False)
    assert a.session.is_closed()
    with pytest.raises(BusClosedError):
        await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=1))
    await b.close()
    await b.close()  # idempotent
    assert events.closed


async def test_another_team_cannot_inject(port: int, wait_until, route_ready) -> None:
    a, b = pair(port, robots=range(3))
    intruder = ZenohBus("t1", 0, connect=[f"tcp/127.0.0.1:{port}"])
    async with a, b, intruder:
        await intruder.announce()
        await a.announce()
        await b.wait_for_peers({0}, timeout=5)
        sub = b.subscribe(keys.team_all(TEAM))
        target = keys.topic_key(TEAM, 0, keys.PING)
        await intruder.wait_for_subscribers(target, timeout=5)
        await route_ready(probe(intruder, target), sub, reset=(b,))
        # the API refuses to address another team's keys
        with pytest.raises(MessageError):
            await intruder.publish(target, Ping(robot=0, nonce=1, sent_ns=0))
        # its own topics never match ours
        await intruder.publish(intruder.key(keys.PING), Ping(robot=0, nonce=2, sent_ns=0))
        # forged bytes put straight into the session are dropped and counted
        forged = {
            "team": Codec("t1", 0).encode(Ping(robot=0, nonce=3, sent_ns=0)),
            "src": Codec(TEAM, 9).encode(Ping(robot=9, nonce=4, sent_ns=0)),  # unknown robot
            "key": Codec(TEAM, 2).encode(Ping(robot=2, nonce=5, sent_ns=0)),  # r2 posing as r0
            "invalid": b"\x81\xa1v\x01",
        }
        for data in forged.values():
            # BLOCK: the default congestion control (DROP) may drop these on a loaded machine
            intruder.session.put(target, data, congestion_control=zenoh.CongestionControl.BLOCK)
        await wait_until(lambda: sum(b.counters.dropped.values()) >= 4, 5)
        assert b.counters.dropped == {"team": 1, "src": 1, "key": 1, "invalid": 1}
        await a.wait_for_subscribers(a.key(keys.PING), timeout=10)
        await route_ready(probe(a, a.key(keys.PING)), sub)
        await a.publish(a.key(keys.PING), Ping(robot=0, nonce=6, sent_ns=0))
        assert (await sub.recv(timeout=10)).nonce == 6
        assert sub.pending() == 0
        assert b.peers() == {0}  # team t1's robot 0 is not our robot 0... only a's token counts
        await a.close()
        await b.wait_for_absent({0}, timeout=3)  # the intruder's token does not keep r0 alive


async def test_config_file_and_errors(port: int, tmp_path: Path) -> None:
    conf = tmp_path / "zenoh.json5"
    conf.write_text(json.dumps({
        "mode": "peer",
        "scouting": {"multicast": {"enabled": False}},
        "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
    }))
    a = ZenohBus(TEAM, 0, config_file=conf)
    b = ZenohBus(TEAM, 1, config_file=conf, listen=["tcp/127.0.0.1:0"],
                 connect=[f"tcp/127.0.0.1:{port}"])  # explicit arguments override the file
    async with a, b:
        await a.announce()
        await b.wait_for_peers({0}, timeout=5)
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(ConfigError, match="zenoh-config"):
        ZenohBus(TEAM, 0, config_file=bad)
    with pytest.raises(ConfigError, match="mode"):
        ZenohBus(TEAM, 0, mode="satellite")
    closed_port = port  # a and b are closed: nothing listens there any more
    with pytest.raises(ConfigError, match="zenoh"):
        ZenohBus(TEAM, 0, mode="client", connect=[f"tcp/127.0.0.1:{closed_port}"])


def test_needs_a_running_loop() -> None:
    with pytest.raises(ConfigError, match="loop"):
        ZenohBus(TEAM, 0)


async def test_client_mode_through_a_router(port: int, route_ready) -> None:
    """Two robots in client mode reach each other only through a router (zenohd's role)."""
    router = ZenohBus("infra", 0, mode="router", listen=[f"tcp/127.0.0.1:{port}"])
    async with router:
        a = ZenohBus(TEAM, 0, mode="client", connect=[f"tcp/127.0.0.1:{port}"])
        b = ZenohBus(TEAM, 1, mode="client", connect=[f"tcp/127.0.0.1:{port}"])
        async with a, b:
            await a.announce()
            await b.announce()
            await b.wait_for_peers({0}, timeout=5)
            sub = b.subscribe(keys.topic_all(TEAM, keys.HEARTBEAT))
            await a.wait_for_subscribers(a.key(keys.HEARTBEAT), timeout=5)
            await route_ready(probe(a, a.key(keys.HEARTBEAT)), sub)
            await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=9))
            assert (await sub.recv(timeout=5)).keyframes == 9
            assert router.peers() == frozenset()  # another team: invisible to the router's bus


async def test_bursts_are_coalesced_in_order_and_counted_per_message(port: int, route_ready) -> None:
    """A burst (no await yielding between publishes) goes out as few batch puts; every message
    arrives validated, in publication order across keys, and the byte counters still agree."""
    a, b = pair(port, robots=range(3), block_on_congestion=True)
    async with a, b:
        sub = b.subscribe(keys.team_all(TEAM))
        for topic in (keys.PING, keys.HEARTBEAT):
            await a.wait_for_subscribers(a.key(topic), timeout=5)
            await route_ready(probe(a, a.key(topic)), sub, reset=(a, b))
        puts = []
        real_put = a._put
        a._put = lambda key, data, n: (puts.append(n), real_put(key, data, n))  # type: ignore
        payload = np.arange(1000, dtype=np.uint8)
        sent = []
        for i in range(300):
            msg = (Heartbeat(robot=0, keyframes=i) if i % 50 == 49
                   else Ping(robot=0, nonce=i, sent_ns=0, payload=payload))
            sent.append(msg)
            await a.publish(a.key(msg.TOPIC), msg)
        got = [await sub.recv(timeout=5) for _ in sent]
        assert got == sent
        assert sum(puts) == len(sent) and len(puts) < len(sent) // 10  # batched
        assert puts[0] == 1  # the first message of the burst went out at once
        assert a.counters.snapshot()["sent"] == b.counters.snapshot()["received"]
        assert a.counters.sent["diag/ping"].messages == 294
        # runs of pings went as columnar batches: fewer bytes than 294 separate envelopes
        alone = len(a.codec.encode(sent[0]))
        assert a.counters.sent["diag/ping"].bytes < 294 * (alone - 40)
        # a lone message is not held back: it is put before publish() returns
        n = len(puts)
        await asyncio.sleep(0)
        await a.publish(a.key(keys.PING), Ping(robot=0, nonce=1, sent_ns=0))
        assert len(puts) == n + 1
        assert (await sub.recv(timeout=5)).nonce == 1


async def test_a_forged_batch_element_is_dropped_alone(port: int, wait_until, route_ready) -> None:
    a, b = pair(port, robots=range(3))
    async with a, b:
        sub = b.subscribe(keys.team_all(TEAM))
        target = a.key(keys.HEARTBEAT)
        await a.wait_for_subscribers(target, timeout=5)
        await route_ready(probe(a, target), sub, reset=(b,))
        c0, c2 = Codec(TEAM, 0), Codec(TEAM, 2)
        parts = [c0.encode(Heartbeat(robot=0, keyframes=1)),
                 c2.encode(Heartbeat(robot=2, keyframes=2)),  # r2 posing as r0
                 c0.encode(Heartbeat(robot=0, keyframes=3))]
        a.session.put(target, codec_batch(parts), congestion_control=zenoh.CongestionControl.BLOCK)
        assert [(await sub.recv(timeout=5)).keyframes for _ in range(2)] == [1, 3]
        await wait_until(lambda: b.counters.dropped == {"key": 1}, 5)
        assert b.counters.received["heartbeat"].messages == 2


def codec_batch(parts: list[bytes]) -> bytes:
    from kimera_multi_py.comms.codec import batch_header

    return batch_header(len(parts)) + b"".join(parts)
