"""A robot whose link to the router is cut while the router restarts rejoins once its link
returns: presence, publications both ways and queries (real Zenoh sessions on 127.0.0.1, the
router restarted on its port, the cut made by the launcher's link proxy)."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.clouds import pack_cloud
from kimera_multi_py.comms.messages.closures import LoopClosureReply
from kimera_multi_py.comms.messages.team import Heartbeat, Ping
from kimera_multi_py.comms.zenoh_bus import ZenohBus
from kimera_multi_py.team.link_proxy import LinkProxy
from tests.integration.test_zenoh_bus import probe

pytestmark = pytest.mark.integration
TEAM = "t0"
CAP = 60.0  # s: a generous cap; the events are what is tested


class ProxyThread:
    """A :class:`LinkProxy` on its own event loop, so that a Zenoh session opening through it
    (a blocking call) does not stall the proxy."""

    def __init__(self, port: int) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.proxy = LinkProxy("127.0.0.1", port)
        self.port = asyncio.run_coroutine_threadsafe(self.proxy.start(), self.loop).result(10)

    def call(self, fn) -> None:
        self.loop.call_soon_threadsafe(fn)

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.proxy.close(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


async def _reply(key: str, request) -> LoopClosureReply:
    kf = int(key.rsplit("/", 1)[1])
    return LoopClosureReply(robot=0, request_id=request.nonce if request else 0, keyframe=kf, found=True,
                            pose=np.eye(4), num_points=10,
                            cloud=pack_cloud(np.full((10, 3), kf), np.zeros(10, np.int32)),
                            object_centroids=np.zeros((0, 3), np.float32), object_classes=np.zeros(0, np.int32))


async def _answered(bus: ZenohBus, kf: int) -> bool:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + CAP
    while loop.time() < deadline:  # the queryable's declaration propagates through the new router
        replies = await bus.query(keys.keyframe_key(TEAM, 0, kf), Ping(robot=1, nonce=kf, sent_ns=0), timeout=1)
        if replies:
            return replies[0].keyframe == kf
    return False


async def test_a_robot_cut_off_across_a_router_restart_rejoins(port: int, route_ready) -> None:
    endpoint = f"tcp/127.0.0.1:{port}"
    router = ZenohBus("infra", 0, mode="router", listen=[endpoint])
    proxy = ProxyThread(port)
    a = ZenohBus(TEAM, 0, mode="client", connect=[endpoint])
    b = ZenohBus(TEAM, 1, mode="client", connect=[f"tcp/127.0.0.1:{proxy.port}"])
    try:
        await a.serve(keys.keyframe_key(TEAM, 0, "*"), _reply)
        await a.announce()
        await b.announce()
        await a.wait_for_peers({1}, timeout=CAP)
        await b.wait_for_peers({0}, timeout=CAP)
        assert await _answered(b, 7)

        proxy.call(proxy.proxy.cut)
        await a.wait_for_absent({1}, timeout=CAP)
        await b.wait_for_absent({0}, timeout=CAP)
        await router.close()  # the router restarts while robot 1 is cut off
        router = ZenohBus("infra", 0, mode="router", listen=[endpoint])
        proxy.call(proxy.proxy.restore)

        assert await a.wait_for_peers({1}, timeout=CAP) == {1}
        assert await b.wait_for_peers({0}, timeout=CAP) == {0}
        sub = b.subscribe(keys.topic_all(TEAM, keys.HEARTBEAT))
        await a.wait_for_subscribers(a.key(keys.HEARTBEAT), timeout=CAP)
        await route_ready(probe(a, a.key(keys.HEARTBEAT)), sub)
        await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=5))
        assert (await sub.recv(timeout=CAP)).keyframes == 5
        sub_a = a.subscribe(keys.topic_all(TEAM, keys.HEARTBEAT))
        await b.wait_for_subscribers(b.key(keys.HEARTBEAT), timeout=CAP)
        await route_ready(probe(b, b.key(keys.HEARTBEAT), robot=1), sub_a)
        await b.publish(b.key(keys.HEARTBEAT), Heartbeat(robot=1, keyframes=6))
        assert (await sub_a.recv(timeout=CAP)).keyframes == 6
        assert await _answered(b, 9)
    finally:
        for bus in (a, b, router):
            await bus.close()
        proxy.close()
