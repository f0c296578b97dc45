"""Team membership and progress (docs/architecture.md): liveness, latency probes, the PGO leader's
epochs and each node's progress report.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.messages.base import Message, message
from kimera_multi_py.comms.messages.fields import (
    INT64_MAX,
    MAX_ROBOT_ID,
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

# PGO epochs tag rounds as epoch * 1e6 + round (:data:`kimera_multi_py.pgo.team.EPOCH_ROUNDS`), and a leader opens the
# newest epoch it heard of + 1: epochs on the wire stay below what keeps that tag an int64
MAX_EPOCH = INT64_MAX // 1_000_000 - 2


@message("Heartbeat", keys.HEARTBEAT)
class Heartbeat(Message):
    """Periodic liveness and progress: keyframes processed and a short status word."""

    robot: int = robot_id()
    keyframes: int = count()
    status: str = spec_field(Str(max_len=64), default="ok")


@message("Ping", keys.PING)
class Ping(Message):
    """Diagnostics: an opaque payload with a send time (``time.monotonic_ns``) for latency."""

    robot: int = robot_id()
    nonce: int = count()
    sent_ns: int = count()
    echo: bool = spec_field(Bool(), default=False)
    payload: np.ndarray = spec_field(
        Array("uint8", ("n",)), factory=lambda: np.zeros(0, np.uint8)
    )


@message("PgoEpoch", keys.PGO_EPOCH)
class PgoEpoch(Message):
    """The PGO leader opens optimisation epoch ``epoch`` for ``members`` (the robots alive now).

    ``pairs`` is the leader's robot graph (robot pairs joined by accepted inter-robot closures),
    so every member colours the same graph; ``final`` marks the epoch after every stream ended.
    The rounds of an epoch's PGO messages are ``epoch * EPOCH_ROUNDS + round``.
    """

    robot: int = robot_id()
    epoch: int = spec_field(Int(0, MAX_EPOCH))  # epoch * EPOCH_ROUNDS + round must fit a round (int64)
    members: np.ndarray = arr("int64", "m", lo=0, hi=MAX_ROBOT_ID)
    pairs: np.ndarray = arr("int64", "p", 2, lo=0, hi=MAX_ROBOT_ID)
    final: bool = spec_field(Bool())


@message("AgentState", keys.AGENT_STATE)
class AgentState(Message):
    """A node's progress, published on a period: keyframes, latest stamp, whether its stream
    ended, the last PGO epoch it completed, and the verifications it still waits on."""

    robot: int = robot_id()
    keyframes: int = count()
    stamp: float = spec_field(Float())
    finished: bool = spec_field(Bool())
    epoch: int = spec_field(Int(0, MAX_EPOCH))
    complete: bool = spec_field(Bool())
    closures: int = count()  # inter-robot closures this robot verified that PCM accepts (its newest batches)
    rounds: int = count()  # PGO rounds it ran
    bytes_sent: int = count()
    # its robot graph (robot pairs joined by accepted inter-robot closures), repeated with every
    # state so that the leader learns pairs whose closure messages it lost
    pairs: np.ndarray = spec_field(Array("int64", ("p", 2), lo=0, hi=MAX_ROBOT_ID),
                                   factory=lambda: np.zeros((0, 2), np.int64))
    # its queries for peers' keyframes still unanswered that it will ask again: closures may still
    # come of them, and a leader re-runs the final epoch for a late one (docs/deployment.md)
    verifying: int = spec_field(Int(0, INT64_MAX), default=0)
