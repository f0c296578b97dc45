"""Typed messages, one module per protocol family, and the registry that names them on the wire.

- :mod:`.fields` — field specs and the reference validation;
- :mod:`.base` — :class:`~.base.Message` and the ``@message`` decorator (compiled checks);
- :mod:`.pgo` — distributed PGO (``PublicPoses``, ``PoseDeltas``, ``PgoStatus``, ``PgoCommand``, ``GncWeights``,
  ``PcgState``, ``FrameLandmarks``, ``EdgeVeto``);
- :mod:`.closures` — loop closures (``KeyframeDescriptor``, ``LoopClosureRequest``/``Reply``,
  ``LoopClosures``/``LoopClosuresAck``, ``KeyframeOdometry``);
- :mod:`.maps` — map sharing (``MapDelta``, ``SubmapEvidence``, ``SubmapPoses``, ``MapVersions``,
  ``MapState``, ``RoamMap``, ``ObjectUpdate``, ``PeopleUpdate``);
- :mod:`.team` — team membership and progress (``Heartbeat``, ``Ping``, ``PgoEpoch``, ``AgentState``).

This module holds what the codec needs of all of them: :data:`MESSAGE_TYPES`, every type by
its wire name (``TYPE``), and :data:`SCHEMA_VERSION`, bumped whenever a message layout changes
(the codec refuses other versions).
"""

from __future__ import annotations

from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.closures import (
    KeyframeDescriptor,
    KeyframeOdometry,
    LoopClosureReply,
    LoopClosureRequest,
    LoopClosures,
    LoopClosuresAck,
)
from kimera_multi_py.comms.messages.maps import (
    MapDelta,
    MapState,
    MapVersions,
    ObjectUpdate,
    PeopleUpdate,
    RoamMap,
    SubmapEvidence,
    SubmapPoses,
)
from kimera_multi_py.comms.messages.pgo import (
    EdgeVeto,
    FrameLandmarks,
    GncWeights,
    PcgState,
    PgoCommand,
    PgoStatus,
    PoseDeltas,
    PublicPoses,
)
from kimera_multi_py.comms.messages.team import AgentState, Heartbeat, PgoEpoch, Ping
from kimera_multi_py.core.errors import MessageError

SCHEMA_VERSION = 6

# every message type by its wire name, in the order they were first defined (samples and
# tests iterate it)
MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        PublicPoses, FrameLandmarks, PgoStatus, PcgState, PgoCommand, GncWeights,
        KeyframeDescriptor, LoopClosureRequest, LoopClosureReply, LoopClosures, LoopClosuresAck,
        MapDelta, SubmapEvidence, SubmapPoses, MapVersions, MapState, RoamMap, ObjectUpdate,
        Heartbeat, Ping, KeyframeOdometry, PgoEpoch, AgentState, PoseDeltas, PeopleUpdate, EdgeVeto,
    )
}
# the types whose envelopes the codec compresses (wire.zipped): tables of keys, poses, weights,
# descriptors and objects, which repeat field names and small integers, and the small messages
# sent by the thousand, which are mostly field names; not the map evidence nor the verification
# clouds (compressed inside already)
ZIPPED_TYPES = (PublicPoses, PoseDeltas, GncWeights, EdgeVeto, FrameLandmarks, KeyframeDescriptor, LoopClosures,
                ObjectUpdate, PeopleUpdate, SubmapPoses, MapVersions, PgoEpoch, AgentState, PgoStatus, PgoCommand,
                LoopClosuresAck, LoopClosureRequest, PcgState)
for _cls in ZIPPED_TYPES:
    _cls.ZIP = True
if set(MESSAGE_TYPES.values()) != set(Message.__subclasses__()):  # a type defined but not listed
    raise ImportError(f"message types not in MESSAGE_TYPES: "
                      f"{sorted(c.__name__ for c in set(Message.__subclasses__()) - set(MESSAGE_TYPES.values()))}")


def message_type(name: str) -> type[Message]:
    """The message class registered under ``name``; raise :class:`MessageError` if unknown."""
    try:
        return MESSAGE_TYPES[name]
    except (KeyError, TypeError) as exc:
        raise MessageError(f"type: unknown message type {name!r}") from exc
