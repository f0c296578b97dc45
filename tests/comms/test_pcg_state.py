"""The PcgState message of the distributed Gauss–Newton solve: codec round trip and validation."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from kimera_multi_py.comms import codec
from kimera_multi_py.comms.messages.pgo import PcgState
from kimera_multi_py.core.errors import MessageError


def _fields(**over: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "robot": 2, "round": 17, "step": 9, "scalars": [1.5, -2.0],
        "vectors": np.arange(18.0, dtype=np.float32).reshape(3, 6),
        "chunks": np.array([(2 << 32) | 0, (2 << 32) | 1]),
        "coarse": np.ones((2, 6), np.float32),
        "pairs": np.array([[(2 << 32) | 0, (2 << 32) | 1]]),
        "blocks": np.eye(6, dtype=np.float32)[None],
    }
    base.update(over)
    return base


def test_round_trip_keeps_every_field() -> None:
    msg = PcgState(**_fields())
    env = codec.decode(codec.encode(msg, team="t0", src=2, seq=1, stamp=0.0), team="t0",
                       robots={0, 2})
    assert type(env.msg) is PcgState and env.msg == msg
    assert env.msg.vectors.shape == (3, 6) and env.msg.vectors.dtype == np.float32
    assert env.msg.scalars.tolist() == [1.5, -2.0]
    assert env.msg.pairs.tolist() == msg.pairs.tolist()


def test_empty_parts_are_allowed() -> None:
    msg = PcgState(**_fields(vectors=np.zeros((0, 6), np.float32), chunks=np.zeros(0, np.int64),
                             coarse=np.zeros((0, 6), np.float32), pairs=np.zeros((0, 2), np.int64),
                             blocks=np.zeros((0, 6, 6), np.float32)))
    assert msg.vectors.shape == (0, 6) and msg.blocks.shape == (0, 6, 6)


@pytest.mark.parametrize(
    ("over", "field"),
    [
        ({"vectors": np.zeros((2, 3), np.float32)}, "PcgState.vectors"),
        ({"vectors": np.zeros(6, np.float32)}, "PcgState.vectors"),
        ({"vectors": np.full((1, 6), np.nan, np.float32)}, "PcgState.vectors"),
        ({"scalars": [np.inf]}, "PcgState.scalars"),
        ({"scalars": [[1.0]]}, "PcgState.scalars"),
        ({"step": -1}, "PcgState.step"),
        ({"robot": -1}, "PcgState.robot"),
        ({"coarse": np.ones((3, 6), np.float32)}, "PcgState"),  # 3 values for 2 chunks
        ({"chunks": np.array([-1, 0])}, "PcgState.chunks"),
        ({"blocks": np.ones((1, 6, 5), np.float32)}, "PcgState.blocks"),
        ({"pairs": np.array([[1, 2, 3]])}, "PcgState.pairs"),
    ],
)
def test_invalid_fields_are_named(over: dict[str, Any], field: str) -> None:
    with pytest.raises(MessageError, match=field.replace(".", r"\.")):
        PcgState(**_fields(**over))
