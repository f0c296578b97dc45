"""The loop-closure protocol (docs/architecture.md): place descriptors, the request and reply that
fetch a keyframe for geometric verification, verified closures sent until acknowledged, and in
centralised mode the keyframe odometry a robot streams to the server (with the closures, the
server's pose graph).
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.clouds import MAX_POINTS, unpack_cloud
from kimera_multi_py.comms.messages.base import Message, message
from kimera_multi_py.comms.messages.fields import (
    Array,
    Bool,
    Float,
    Int,
    Str,
    arr,
    count,
    robot_id,
    spec_field,
)


@message("KeyframeDescriptor", keys.DESCRIPTORS)
class KeyframeDescriptor(Message):
    """A compact place descriptor of one keyframe (flattened); full data is served on request."""

    robot: int = robot_id()
    keyframe: int = spec_field(Int())
    stamp: float = spec_field(Float())
    kind: str = spec_field(Str(max_len=64))
    descriptor: np.ndarray = arr("float32", "d")


@message("LoopClosureRequest", keys.LC_REQUEST)
class LoopClosureRequest(Message):
    """Ask ``target`` for keyframe ``keyframe`` to verify it against our ``query_keyframe``."""

    robot: int = robot_id()
    target: int = robot_id()
    request_id: int = count()
    keyframe: int = spec_field(Int())
    query_keyframe: int = spec_field(Int())


@message("LoopClosureReply", keys.LC_REPLY)
class LoopClosureReply(Message):
    """A keyframe's data for geometric verification: semantic points and objects.

    ``pose`` is the keyframe's pose in the owner's odometry frame; points and object centroids
    are in the keyframe's frame. The points travel packed (:mod:`kimera_multi_py.comms.clouds`:
    ``num_points`` of them in ``cloud``; :meth:`points` unpacks them). ``found`` is False (with
    no points nor objects) for unknown keyframes.
    """

    robot: int = robot_id()
    request_id: int = count()
    keyframe: int = spec_field(Int())
    found: bool = spec_field(Bool())
    pose: np.ndarray = arr("float64", 4, 4)
    num_points: int = spec_field(Int(0, MAX_POINTS))
    cloud: np.ndarray = arr("uint8", "b")
    object_centroids: np.ndarray = arr("float32", "m", 3)
    object_classes: np.ndarray = arr("int32", "m", lo=0)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The ``(n, 3)`` points and ``(n,)`` labels; :class:`~kimera_multi_py.core.errors.MessageError`
        if the packed cloud is corrupt."""
        return unpack_cloud(self.cloud, self.num_points, "LoopClosureReply.cloud")


@message("LoopClosures", keys.LOOP_CLOSURES)
class LoopClosures(Message):
    """Verified inter-robot loop closures, sent until ``peer`` acknowledges ``batch``.

    The batch holds every closure the sender accepts with ``peer`` now: closure ``i`` joins
    ``keys_a[i]`` and ``keys_b[i]``. Its relative pose T(keys_a[i] -> keys_b[i]), diagonal noise
    (rotation rad x3, then translation m x3) and inlier support travel in ``poses``, ``sigmas``
    and ``inliers`` for the closures marked in ``fresh`` (1; empty: all of them), in order; the
    others are batch ``base``'s, which ``peer`` acknowledged (``base`` -1: none;
    :mod:`kimera_multi_py.comms.closure_stream` expands such a batch).
    """

    robot: int = robot_id()
    peer: int = robot_id()
    batch: int = count()
    keys_a: np.ndarray = arr("int64", "n")
    keys_b: np.ndarray = arr("int64", "n")
    poses: np.ndarray = arr("float64", "m", 4, 4)
    sigmas: np.ndarray = arr("float64", "m", 6, lo=0.0)
    inliers: np.ndarray = arr("int32", "m", lo=0)
    base: int = spec_field(Int(-1), default=-1)
    fresh: np.ndarray = spec_field(Array("uint8", ("f",), lo=0, hi=1), factory=lambda: np.zeros(0, np.uint8))


@message("LoopClosuresAck", keys.LOOP_CLOSURES_ACK)
class LoopClosuresAck(Message):
    """Acknowledges receipt of ``LoopClosures`` batch ``batch`` from ``peer``."""

    robot: int = robot_id()
    peer: int = robot_id()
    batch: int = count()


@message("KeyframeOdometry", keys.ODOMETRY)
class KeyframeOdometry(Message):
    """Centralised mode: a robot's keyframe odometry ``T_{k-1,k}`` streamed to the server."""

    robot: int = robot_id()
    keyframes: np.ndarray = arr("int64", "n", lo=0)
    odometry: np.ndarray = arr("float64", "n", 4, 4)
