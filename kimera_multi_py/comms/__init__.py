"""Communication between robots: typed messages, a validated codec and one async Bus.

Modules:

- :mod:`.keys` — every key expression (``kmp/{team}/r{robot}/{topic}``, presence, keyframes);
- :mod:`.messages` — frozen dataclasses with a schema version (``PublicPoses``, ``PgoStatus``,
  ``PgoCommand``, ``GncWeights``, ``KeyframeDescriptor``, ``LoopClosureRequest``/``Reply``,
  ``LoopClosures``/``LoopClosuresAck``, ``MapDelta``, ``ObjectUpdate``, ``Heartbeat``, ``Ping``);
- :mod:`.codec` — ``encode``/``decode`` (msgpack + numpy ext); ``decode`` raises only
  ``MessageError``;
- :mod:`.bus` — the ``Bus`` Protocol, ``Subscription`` streams, ``TrafficCounters``;
- :mod:`.loopback` — ``LoopbackNetwork``/``LoopbackBus``, in-process, with fault injection;
- :mod:`.zenoh_bus` — ``ZenohBus`` over eclipse-zenoh 1.x (imported lazily: the core never
  imports zenoh).

Usage (identical for both buses; every call runs on the asyncio thread)::

    import numpy as np
    from kimera_multi_py.comms import keys, LoopbackNetwork, Faults, PublicPoses

    net = LoopbackNetwork(team="t0", seed=0, faults=Faults(drop=0.05, delay=0.002))
    bus0, bus1 = net.bus(0), net.bus(1)
    # or: bus0 = ZenohBus("t0", 0, listen=["tcp/127.0.0.1:7447"]) in another process

    await bus0.announce(); await bus1.announce()
    await bus1.wait_for_peers({0}, timeout=5.0)

    sub = bus1.subscribe(keys.topic_all("t0", keys.PUBLIC_POSES))  # declared immediately
    poses = PublicPoses(robot=0, round=3, keys=[1, 2], poses=np.tile(np.eye(4), (2, 1, 1)))
    await bus0.publish(bus0.key(keys.PUBLIC_POSES), poses)  # on kmp/t0/r0/pgo/public_poses
    msg = await sub.recv(timeout=1.0)        # or: async for msg in sub: ...
    assert msg.robot == 0                    # msg.robot is the validated sender

    # request/reply for large data
    async def serve_keyframe(key: str, request):  # key = kmp/t0/r0/keyframe/17
        return LoopClosureReply(robot=0, ...)
    handle = await bus0.serve(keys.keyframe_key("t0", 0, "*"), serve_keyframe)
    replies = await bus1.query(keys.keyframe_key("t0", 0, 17), timeout=1.0)
    handle.close()

    bus1.counters.snapshot()  # {"sent": {topic: {messages, bytes}}, "received", "dropped"}
    await bus0.close(); await bus1.close()
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import Bus, PresenceEvent, Subscription
from kimera_multi_py.comms.codec import Codec, CodecError, Envelope, decode, encode
from kimera_multi_py.comms.counters import TopicCount, TrafficCounters
from kimera_multi_py.comms.loopback import (
    Faults,
    FaultStats,
    LoopbackBus,
    LoopbackNetwork,
    Partition,
)
from kimera_multi_py.comms.messages import MESSAGE_TYPES, SCHEMA_VERSION
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.closures import (
    KeyframeDescriptor,
    LoopClosureReply,
    LoopClosureRequest,
    LoopClosures,
    LoopClosuresAck,
)
from kimera_multi_py.comms.messages.maps import MapDelta, ObjectUpdate
from kimera_multi_py.comms.messages.pgo import FrameLandmarks, GncWeights, PgoCommand, PgoStatus, PublicPoses
from kimera_multi_py.comms.messages.team import Heartbeat, Ping
from kimera_multi_py.comms.stream import BusClosedError, Stream

if TYPE_CHECKING:
    from kimera_multi_py.comms.zenoh_bus import ZenohBus as ZenohBus


def __getattr__(name: str) -> Any:
    # ZenohBus is imported on first use so that importing comms never loads zenoh.
    if name == "ZenohBus":
        from kimera_multi_py.comms.zenoh_bus import ZenohBus

        return ZenohBus
    raise AttributeError(name)


__all__ = [
    "MESSAGE_TYPES",
    "SCHEMA_VERSION",
    "Bus",
    "BusClosedError",
    "Codec",
    "CodecError",
    "Envelope",
    "FaultStats",
    "Faults",
    "FrameLandmarks",
    "GncWeights",
    "Heartbeat",
    "KeyframeDescriptor",
    "LoopClosureReply",
    "LoopClosureRequest",
    "LoopClosures",
    "LoopClosuresAck",
    "LoopbackBus",
    "LoopbackNetwork",
    "MapDelta",
    "Message",
    "ObjectUpdate",
    "Partition",
    "PgoCommand",
    "PgoStatus",
    "Ping",
    "PresenceEvent",
    "PublicPoses",
    "Stream",
    "Subscription",
    "TopicCount",
    "TrafficCounters",
    "decode",
    "encode",
    "keys",
]
