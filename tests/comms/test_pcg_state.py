"""The PcgState message of the distributed Gauss–Newton solve: codec round trip and validation."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.comms import codec
from kimera_multi_py.comms.messages import PcgState
from kimera_multi_py.errors import MessageError


def test_round_trip_keeps_scalars_and_vectors() -> None:
    msg = PcgState(robot=2, round=17, step=9, scalars=[1.5, -2.0], vectors=np.arange(18.0).reshape(3, 6))
    env = codec.decode(codec.encode(msg, team="t0", src=2, seq=1, stamp=0.0), team="t0",
                       robots={0, 2})
    assert type(env.msg) is PcgState and env.msg == msg
    assert env.msg.vectors.shape == (3, 6) and env.msg.scalars.tolist() == [1.5, -2.0]


def test_empty_vectors_are_allowed() -> None:
    msg = PcgState(robot=0, round=0, step=0, scalars=[3.0], vectors=np.zeros((0, 6)))
    assert msg.vectors.shape == (0, 6)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"vectors": np.zeros((2, 3))}, "PcgState.vectors"),
        ({"vectors": np.zeros(6)}, "PcgState.vectors"),
        ({"vectors": np.full((1, 6), np.nan)}, "PcgState.vectors"),
        ({"scalars": [np.inf]}, "PcgState.scalars"),
        ({"scalars": [[1.0]]}, "PcgState.scalars"),
        ({"step": -1}, "PcgState.step"),
        ({"robot": -1}, "PcgState.robot"),
    ],
)
def test_invalid_fields_are_named(kwargs: dict[str, object], field: str) -> None:
    base: dict[str, object] = {"robot": 0, "round": 0, "step": 0, "scalars": [1.0],
                               "vectors": np.zeros((1, 6))}
    base.update(kwargs)
    with pytest.raises(MessageError, match=field.replace(".", r"\.")):
        PcgState(**base)  # type: ignore[arg-type]
