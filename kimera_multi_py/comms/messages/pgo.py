"""The distributed-PGO protocol (docs/algorithms/pgo.md): public poses, progress, the leader's
commands, robust weights, the Gauss–Newton lock-step, and the landmarks a frame decision may use.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.messages.base import Message, message
from kimera_multi_py.comms.messages.fields import (
    MAX_ROBOT_ID,
    Bool,
    Float,
    Str,
    arr,
    count,
    robot_id,
    spec_field,
)

PGO_COMMANDS = ("start", "round", "update_weights", "stop")


@message("PublicPoses", keys.PUBLIC_POSES)
class PublicPoses(Message):
    """A robot's public poses (those touching inter-robot edges) after a PGO round.

    ``settled``: the sender's frame is the team frame's root, or rests on a frame hypothesis of
    at least two places decided on settled peers' poses. A frame adopted on one place (or on a
    consensus of a few edges) is not settled: an alias looks exactly like it, and its receivers
    do not align through it while settled evidence exists.
    """

    robot: int = robot_id()
    round: int = count()
    keys: np.ndarray = arr("int64", "n")
    poses: np.ndarray = arr("float64", "n", 4, 4)
    settled: bool = spec_field(Bool(), default=True)


@message("PoseDeltas", keys.POSE_DELTAS)
class PoseDeltas(Message):
    """A robot's public poses that moved, as float32 deltas against its full
    :class:`PublicPoses` of round ``base`` (:mod:`kimera_multi_py.pgo.pose_stream`).

    Entry ``i``: the pose of ``base``'s key ``index[i]`` is ``T_base · [exp(deltas[i, :3]),
    deltas[i, 3:]]`` (rotation vector in rad, translation in m). ``settled`` as in the base.
    """

    robot: int = robot_id()
    round: int = count()
    base: int = count()
    index: np.ndarray = arr("int32", "n", lo=0)
    deltas: np.ndarray = arr("float32", "n", 6)
    settled: bool = spec_field(Bool(), default=True)


@message("FrameLandmarks", keys.FRAME_LANDMARKS)
class FrameLandmarks(Message):
    """A settled robot's confirmed object landmarks, in its frame (rooted at robot ``frame``),
    sent when a PGO epoch opens: MAP class and box centre per object. A robot whose frame
    hypotheses closures cannot tell apart checks them against these
    (:mod:`kimera_multi_py.alignment.landmark_check`)."""

    robot: int = robot_id()
    frame: int = robot_id()
    classes: np.ndarray = arr("int32", "n", lo=0)
    centroids: np.ndarray = arr("float32", "n", 3)


@message("EdgeVeto", keys.EDGE_VETO)
class EdgeVeto(Message):
    """Inter-robot edges between ``robot`` (pose keys ``keys_a``) and ``peer`` (``keys_b``) that
    ``robot``'s frame decision found in a frame hypothesis the maps refute: both ends hold them
    at weight 0 until the epoch ends, whatever GNC would make of them (the maps already decided)."""

    robot: int = robot_id()
    peer: int = robot_id()
    round: int = count()
    keys_a: np.ndarray = arr("int64", "m")
    keys_b: np.ndarray = arr("int64", "m")


@message("PgoStatus", keys.PGO_STATUS)
class PgoStatus(Message):
    """A robot's PGO progress: ``ready`` once the relative pose change is below tolerance."""

    robot: int = robot_id()
    round: int = count()
    ready: bool = spec_field(Bool())
    cost: float = spec_field(Float(lo=0.0))
    rel_change: float = spec_field(Float(lo=0.0))


@message("PcgState", keys.PCG_STATE)
class PcgState(Message):
    """One lock-step of the distributed Gauss–Newton solve (:mod:`kimera_multi_py.pgo.gn`).

    ``scalars`` are the robot's shares of the team-wide sums of this step (costs, CG inner
    products); ``vectors`` a tangent vector at its public poses, in the order of its
    :class:`PublicPoses` keys (a CG direction or the Gauss–Newton step), or empty.
    ``chunks`` are the ids of its coarse unknowns (rigid pose chunks) and ``coarse`` a vector's
    restriction to them; ``pairs`` / ``blocks`` its rows of the coarse matrix (6x6 blocks
    joining two chunk ids). Any of these may be empty. Vectors and blocks travel as float32
    (the sender rounds its own copy the same way, so every robot applies the same operator).
    """

    robot: int = robot_id()
    round: int = count()
    step: int = count()
    scalars: np.ndarray = arr("float64", "s")
    vectors: np.ndarray = arr("float32", "n", 6)
    chunks: np.ndarray = arr("int64", "c", lo=0)
    coarse: np.ndarray = arr("float32", "c", 6)
    pairs: np.ndarray = arr("int64", "b", 2, lo=0)
    blocks: np.ndarray = arr("float32", "b", 6, 6)


@message("PgoCommand", keys.PGO_COMMAND)
class PgoCommand(Message):
    """A schedule decision: which robots update in ``round`` (one colour of the robot graph)."""

    robot: int = robot_id()
    round: int = count()
    command: str = spec_field(Str(choices=PGO_COMMANDS))
    active: np.ndarray = arr("int64", "m", lo=0, hi=MAX_ROBOT_ID)


@message("GncWeights", keys.GNC_WEIGHTS)
class GncWeights(Message):
    """GNC-TLS weights of the inter-robot edges between ``robot`` and ``peer``.

    Edge ``i`` joins pose keys ``keys_a[i]`` (owned by ``robot``) and ``keys_b[i]`` (``peer``).
    """

    robot: int = robot_id()
    peer: int = robot_id()
    round: int = count()
    keys_a: np.ndarray = arr("int64", "m")
    keys_b: np.ndarray = arr("int64", "m")
    weights: np.ndarray = arr("float64", "m", lo=0.0, hi=1.0)
    mu: float = spec_field(Float(lo=0.0))
