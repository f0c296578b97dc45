"""Key expressions: builders, parser, and the wildcard matcher checked against Zenoh's."""

from __future__ import annotations

import numpy as np
import pytest
import zenoh

from kimera_multi_py.comms import keys
from kimera_multi_py.core.errors import MessageError


def test_builders_follow_the_design_layout() -> None:
    assert keys.topic_key("t0", 2, keys.PUBLIC_POSES) == "kmp/t0/r2/pgo/public_poses"
    assert keys.topic_key("t0", 2, keys.MAP_DELTA) == "kmp/t0/r2/map/delta"
    assert keys.alive_key("t0", 2) == "kmp/t0/alive/r2"
    assert keys.keyframe_key("t0", 1, 17) == "kmp/t0/r1/keyframe/17"
    assert keys.topic_all("t0", keys.HEARTBEAT) == "kmp/t0/*/heartbeat"


@pytest.mark.parametrize(
    "bad",
    [lambda: keys.topic_key("t 0", 0, "x"), lambda: keys.topic_key("t0", -1, "x"),
     lambda: keys.topic_key("t0", 0, "a//b"), lambda: keys.topic_key("t0", True, "x"),
     lambda: keys.keyframe_key("t0", 0, 1.5)],
)
def test_builders_reject_bad_parts(bad) -> None:
    with pytest.raises(MessageError):
        bad()


def test_parse_key_and_labels() -> None:
    p = keys.parse_key("kmp/t0/r12/pgo/status")
    assert (p.team, p.robot, p.topic, p.alive) == ("t0", 12, "pgo/status", False)
    a = keys.parse_key("kmp/t0/alive/r3")
    assert a.alive and a.robot == 3
    for bad in ["kmp/t0/x3/pgo", "other/t0/r1/x", "kmp/t0/r1", "kmp/t0/r01/x", "kmp/t0/alive/r1/x"]:
        with pytest.raises(MessageError):
            keys.parse_key(bad)
    assert keys.topic_label("kmp/t0/r1/keyframe/17") == "keyframe"
    assert keys.topic_label("kmp/t0/r1/map/delta") == "map/delta"
    assert keys.topic_label("garbage") == "garbage"


def test_team_wildcards_do_not_match_presence_or_other_teams() -> None:
    assert keys.intersects(keys.team_all("t0"), "kmp/t0/r1/pgo/status")
    assert not keys.intersects(keys.topic_all("t0", keys.HEARTBEAT), "kmp/t1/r1/heartbeat")
    assert not keys.intersects(keys.topic_all("t0", keys.HEARTBEAT), keys.alive_key("t0", 1))
    assert keys.intersects(keys.alive_all("t0"), keys.alive_key("t0", 4))


def test_intersects_agrees_with_zenoh() -> None:
    rng = np.random.default_rng(0)
    chunks = ["a", "b", "c", "*", "**"]
    for _ in range(3000):
        a = "/".join(rng.choice(chunks, rng.integers(1, 5)))
        b = "/".join(rng.choice(chunks, rng.integers(1, 5)))
        try:
            ka, kb = zenoh.KeyExpr(a), zenoh.KeyExpr(b)
        except zenoh.ZError:
            continue  # not canonical (e.g. "**/**"); zenoh refuses it
        assert keys.intersects(a, b) == ka.intersects(kb), (a, b)
