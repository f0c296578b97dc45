"""An agent's wait after its final epoch (``team.process.until_whole``, docs/deployment.md): it
stays while a robot it hears is still streaming or waits on a verification (a closure of it re-runs
the final epoch), and its ``--linger-max`` counts from when none streams.
Unit test with a stand-in node (the loop only reads the node's maps, states and presence)."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

from kimera_multi_py.team.process import until_whole


class StreamingPeer:
    """Robot 0, done, hearing robot 1, which still streams for ``ticks`` ticks; until then robot
    1's newest submap is always missing here (a gap in the team map)."""

    def __init__(self, ticks: int) -> None:
        self.ticks = ticks
        self.ticked = 0
        self.robot = 0
        self.settled = True
        self.own_verifying = 0
        state = SimpleNamespace(finished=False, verifying=0)
        self.pgo = SimpleNamespace(states={1: state}, busy=False)
        self.maps = SimpleNamespace(mode="exact", gaps=self._gaps, heard=lambda: {0, 1})

    def _gaps(self, team: set[int]) -> dict[int, list[str]]:
        return {1: ["submaps_ahead"]} if not self.pgo.states[1].finished else {}

    def alive(self) -> frozenset[int]:
        return frozenset({1})

    def verifying(self) -> int:
        return self.own_verifying

    async def drain(self) -> int:
        return 0

    async def tick(self) -> int:
        self.ticked += 1
        if self.ticked >= self.ticks:
            self.pgo.states[1].finished = True
        return 0


def test_a_robot_waits_for_a_peer_still_streaming_beyond_its_linger_cap() -> None:
    node = StreamingPeer(ticks=500)
    out = asyncio.run(until_whole(node, None, cap=0.05, poll=0.001, settle=0.01))  # type: ignore[arg-type]
    assert node.ticked >= 500  # it did not give up while robot 1 streamed
    assert out["whole"] and out["missing"] == {}


def test_without_a_streaming_peer_the_cap_ends_the_wait() -> None:
    node = StreamingPeer(ticks=10**9)
    node.pgo.states[1].finished = True
    node.maps.gaps = lambda team: {1: ["submaps_ahead"]}  # a gap that never closes
    out = asyncio.run(until_whole(node, None, cap=0.05, poll=0.001, settle=0.01))  # type: ignore[arg-type]
    assert not out["whole"] and out["missing"] == {"1": ["submaps_ahead"]}


class VerifyingPeer(StreamingPeer):
    """Every stream over and the team map whole, but robot 1 (or robot 0 itself) still waits on
    a keyframe it asked for, for ``ticks`` ticks."""

    def __init__(self, ticks: int, own: bool) -> None:
        super().__init__(ticks)
        self.pgo.states[1].finished = True
        self.own = own
        if own:
            self.own_verifying = 1
        else:
            self.pgo.states[1].verifying = 1

    async def tick(self) -> int:
        self.ticked += 1
        if self.ticked >= self.ticks:
            self.own_verifying = 0
            self.pgo.states[1].verifying = 0
        return 0


def test_a_robot_stays_while_a_peer_or_itself_still_waits_on_a_verification() -> None:
    for own in (False, True):
        node = VerifyingPeer(ticks=200, own=own)
        out = asyncio.run(until_whole(node, None, cap=10.0, poll=0.001, settle=0.01))  # type: ignore[arg-type]
        assert node.ticked >= 200, own  # whole and quiet from the start, but a closure may still come
        assert out["whole"]


def test_an_absent_peer_s_verifications_do_not_hold_a_robot() -> None:
    node = VerifyingPeer(ticks=10**9, own=False)
    node.alive = lambda: frozenset()  # type: ignore[method-assign]
    out = asyncio.run(until_whole(node, None, cap=10.0, poll=0.001, settle=0.01))  # type: ignore[arg-type]
    assert out["whole"] and node.ticked < 200  # left after the settle window, not at the cap (10 s of 1 ms polls)


class GonePeer(StreamingPeer):
    """Every map gap closed, but robot 1 went out of reach before its stream ended; it comes back
    (its stream then over) after ``ticks`` ticks, or never."""

    def __init__(self, ticks: int) -> None:
        super().__init__(ticks)
        self.maps.gaps = lambda team: {}

    def alive(self) -> frozenset[int]:
        return frozenset({1}) if self.ticked >= self.ticks else frozenset()


def test_a_peer_gone_mid_stream_holds_a_robot_until_it_returns() -> None:
    node = GonePeer(ticks=200)
    out = asyncio.run(until_whole(node, None, cap=10.0, poll=0.001, settle=0.01))  # type: ignore[arg-type]
    assert node.ticked >= 200  # it did not leave in the settle window while robot 1 could come back
    assert out["whole"] and out["out_of_reach"] == []


def test_a_peer_gone_mid_stream_for_good_ends_the_wait_at_the_cap_and_is_reported() -> None:
    node = GonePeer(ticks=10**9)
    out = asyncio.run(until_whole(node, None, cap=0.3, poll=0.001, settle=0.01))  # type: ignore[arg-type]
    assert not out["whole"] and out["out_of_reach"] == [1] and out["missing"] == {}
