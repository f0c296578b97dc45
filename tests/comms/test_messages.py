"""Messages: a round trip of every type, coercion, and validation errors that name the field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kimera_multi_py.comms import codec
from kimera_multi_py.comms.messages import MESSAGE_TYPES
from kimera_multi_py.comms.messages.maps import MapDelta
from kimera_multi_py.comms.messages.pgo import GncWeights, PgoCommand, PgoStatus, PublicPoses
from kimera_multi_py.comms.messages.team import Heartbeat
from kimera_multi_py.core.errors import MessageError
from tests.support.samples import random_message


@pytest.mark.parametrize("type_name", sorted(MESSAGE_TYPES))
@pytest.mark.parametrize("max_len", [0, 5])
def test_round_trip_every_type(type_name: str, max_len: int) -> None:
    cls = MESSAGE_TYPES[type_name]
    msg = random_message(cls, np.random.default_rng(7), robot=3, max_len=max_len)
    data = codec.encode(msg, team="t0", src=3, seq=42, stamp=12.5)
    env = codec.decode(data, team="t0", robots={0, 3})
    assert (env.type, env.team, env.src, env.seq, env.stamp) == (type_name, "t0", 3, 42, 12.5)
    assert type(env.msg) is cls
    assert env.msg == msg
    for name, value in msg.to_wire().items():
        got = getattr(env.msg, name)
        if isinstance(value, np.ndarray):
            assert got.dtype == value.dtype and got.shape == value.shape
            assert not got.flags.writeable  # received messages are immutable values
    assert codec.encode(env.msg, team="t0", src=3, seq=42, stamp=12.5) == data


def test_construction_coerces_lists_and_numpy_scalars() -> None:
    msg = PublicPoses(robot=np.int64(1), round=0, keys=[5, 6], poses=[np.eye(4), np.eye(4)])
    assert msg.keys.dtype == np.int64 and msg.poses.dtype == np.float64
    assert isinstance(msg.robot, int)
    status = PgoStatus(robot=0, round=1, ready=np.bool_(True), cost=3, rel_change=np.float32(0.5))
    assert status.cost == 3.0 and isinstance(status.cost, float) and status.ready is True


def _poses(n: int) -> np.ndarray:
    return np.tile(np.eye(4), (n, 1, 1))


@pytest.mark.parametrize(
    ("build", "field"),
    [
        (lambda: PublicPoses(robot=0, round=0, keys=[1, 2], poses=_poses(3)), "PublicPoses.poses"),
        (lambda: PublicPoses(robot=0, round=0, keys=[1], poses=np.eye(4)), "PublicPoses.poses"),
        (lambda: PublicPoses(robot=0, round=0, keys=[1.5], poses=_poses(1)), "PublicPoses.keys"),
        (lambda: PublicPoses(robot=0, round=-1, keys=[1], poses=_poses(1)), "PublicPoses.round"),
        (lambda: PublicPoses(robot=True, round=0, keys=[1], poses=_poses(1)), "PublicPoses.robot"),
        (
            lambda: PublicPoses(robot=0, round=0, keys=[1], poses=_poses(1) * np.nan),
            "PublicPoses.poses",
        ),
        (
            lambda: PgoStatus(robot=0, round=0, ready=1, cost=0.0, rel_change=0.0),
            "PgoStatus.ready",
        ),
        (
            lambda: PgoStatus(robot=0, round=0, ready=True, cost=float("inf"), rel_change=0.0),
            "PgoStatus.cost",
        ),
        (lambda: PgoCommand(robot=0, round=0, command="dance", active=[]), "PgoCommand.command"),
        (
            lambda: GncWeights(robot=0, peer=1, round=0, keys_a=[1], keys_b=[2], weights=[1.5],
                               mu=1.0),
            "GncWeights.weights",
        ),
        (lambda: Heartbeat(robot=0, keyframes=0, status="x" * 65), "Heartbeat.status"),
        (
            lambda: MapDelta(robot=0, round=0, frame=0, resolution=0.1, depth=16, full=False,
                             keys=[1], logodds=np.zeros((1, 3), np.float32), scale=0.1),
            "MapDelta.logodds",
        ),
    ],
)
def test_invalid_messages_raise_naming_the_field(build, field: str) -> None:
    with pytest.raises(MessageError, match=field.replace(".", r"\.")):
        build()


def test_messages_compare_by_value_and_are_frozen() -> None:
    a = Heartbeat(robot=1, keyframes=2)
    assert a == Heartbeat(robot=1, keyframes=2)
    assert a != Heartbeat(robot=1, keyframes=3)
    with pytest.raises(AttributeError):
        a.keyframes = 5  # type: ignore[misc]


# ---------------------------------------------------------------------------- compiled checks
def _outcome(fn, *args):
    try:
        return fn(*args)
    except MessageError as exc:
        return ("error", str(exc))


@pytest.mark.parametrize("type_name", sorted(MESSAGE_TYPES))
def test_compiled_checks_agree_with_the_reference(type_name: str) -> None:
    """The compiled from_wire accepts, refuses (with the same message) and returns as the
    reference does, on valid bodies and on bodies with one field swapped for an odd value."""
    cls = MESSAGE_TYPES[type_name]
    rng = np.random.default_rng(7)
    odd = [None, True, 0, -1, 2**63, 1.5, math.nan, math.inf, "", "x" * 300, "start", b"",
           [], {}, np.int64(3), np.float32(1.0), np.zeros(0), np.zeros((2, 3)),
           np.zeros(3, np.int64), np.full(3, np.nan), np.ones((2, 4, 4)), np.ones(2, np.int32),
           np.zeros(4, np.uint8)[::2]]
    for _ in range(20):
        body = random_message(cls, rng, robot=1).to_wire()
        assert _outcome(cls.from_wire, body) == _outcome(cls._from_wire_slow, body)
        for name in body:
            for value in odd:
                mutated = {**body, name: value}
                fast, slow = _outcome(cls.from_wire, mutated), _outcome(cls._from_wire_slow, mutated)
                assert fast == slow, (name, value)
        assert _outcome(cls.from_wire, {**body, "extra": 1}) == _outcome(
            cls._from_wire_slow, {**body, "extra": 1})
        # construction: the compiled shortcut and the reference coercion give the same message
        built = cls(**body)
        ref = object.__new__(cls)
        ref.__dict__.update(body)
        ref._validate_slow()
        assert built == ref
