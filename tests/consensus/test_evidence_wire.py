"""Map evidence on the wire: palette rows, the plain rows before them, corrupt payloads, and the
growing submap's hold (docs/algorithms/map_consensus.md)."""

from __future__ import annotations

import asyncio
import logging

import numpy as np
import pytest

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.comms.loopback import LoopbackNetwork
from kimera_multi_py.comms.messages.maps import SubmapEvidence
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.mapshare.exchange import MapExchange
from kimera_multi_py.mapshare.wire import PALETTE, PLAIN, pack_cells, unpack_cells

from ..mapping.helpers import K
from .test_map_consensus import add_scan, assert_exact, robot_map, run, team


def _submap_rows() -> tuple[np.ndarray, np.ndarray]:
    s = robot_map(0, 1).submaps[0]
    return s.codes, s.rows[:, 1:].astype(np.int16)


def test_palette_rows_round_trip_exactly_and_the_plain_rows_still_read() -> None:
    rng = np.random.default_rng(3)
    codes = np.unique(rng.integers(0, 1 << 48, 400))
    extreme = rng.choice(np.array([-32768, -1, 0, 1, 32767], np.int16), (len(codes), K))
    few = rng.integers(-3, 3, (len(codes), K)).astype(np.int16) * 410  # few distinct rows: uint8 indices
    for values in (extreme, few, rng.integers(-9000, 9000, (len(codes), K)).astype(np.int16)):
        for palette, head in ((True, PALETTE), (False, PLAIN)):
            payload = pack_cells(codes, values, palette)
            assert payload[0] & 0xF0 == head
            got_codes, got_values = unpack_cells(payload, len(codes), K, "w")
            assert np.array_equal(got_codes, codes) and np.array_equal(got_values, values)
            assert got_values.dtype == np.int16
    one = pack_cells(np.array([5], np.int64), np.array([[7]], np.int16))
    assert unpack_cells(one, 1, 1, "w")[1].tolist() == [[7]]
    empty = pack_cells(np.zeros(0, np.int64), np.zeros((0, K), np.int16))
    assert unpack_cells(empty, 0, K, "w")[0].size == 0


def test_palette_rows_are_smaller_on_map_evidence() -> None:
    codes, values = _submap_rows()
    plain, palette = len(pack_cells(codes, values, False)), len(pack_cells(codes, values, True))
    assert len(codes) > 1000 and palette < plain


def test_corrupt_evidence_payloads_raise_message_errors_only() -> None:
    codes, values = _submap_rows()
    good = pack_cells(codes, values)
    rng = np.random.default_rng(11)
    refused = 0
    for trial in range(300):
        bad = good.copy()
        kind = trial % 4
        if kind == 0:  # flipped bytes
            at = rng.integers(0, len(bad), 1 + trial % 5)
            bad[at] ^= rng.integers(1, 256, len(at)).astype(np.uint8)
        elif kind == 1:  # cut short
            bad = bad[: rng.integers(0, len(bad))]
        elif kind == 2:  # an unknown layout or compressor in the head byte
            bad[0] = rng.integers(0, 256)
        else:  # random bytes behind a valid head
            bad = np.concatenate([bad[:1], rng.integers(0, 256, rng.integers(0, 300)).astype(np.uint8)])
        try:
            got_codes, got_values = unpack_cells(bad, len(codes), K, "w")
        except MessageError:
            refused += 1
            continue
        # what is not refused is well formed: sorted unique codes and int16 rows of the right shape
        assert got_values.shape == (len(codes), K) and np.all(np.diff(got_codes) > 0)
    assert refused >= 250
    forged = pack_cells(codes, values, False)  # plain rows declared as a palette: sizes no longer match
    forged[0] = (forged[0] & 0x0F) | PALETTE
    with pytest.raises(MessageError, match="corrupt"):
        unpack_cells(forged, len(codes), K, "w")
    too_many = pack_cells(codes, values)  # a palette larger than the cells
    too_many[1:5] = np.frombuffer(np.array([len(codes) + 1], "<u4").tobytes(), np.uint8)
    with pytest.raises(MessageError, match="distinct rows"):
        unpack_cells(too_many, len(codes), K, "w")


def test_a_corrupt_evidence_message_is_refused_counted_and_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    codes, values = _submap_rows()
    payload = pack_cells(codes, values)
    payload[len(payload) // 2:] ^= 0x5A

    async def main() -> AgentNode:
        net = LoopbackNetwork(team="t0", seed=0, robots=[0, 1])
        node = AgentNode(Agent(1, (0, 1), AgentParams()), net.bus(1))
        assert node.maps is not None
        node.maps.set_neighbours({0})
        bad = SubmapEvidence(robot=0, source=0, submap=0, base=0, version=1, cells=len(codes), classes=K,
                             payload=payload)
        with caplog.at_level(logging.WARNING):
            await node._dispatch(bad)
        return node

    node = asyncio.run(main())
    assert node.errors["SubmapEvidence"] == 1
    assert node.maps is not None and not node.maps.held  # nothing half applied
    lines = [r for r in caplog.records if "refused SubmapEvidence" in r.getMessage()]
    assert len(lines) == 1


@pytest.mark.parametrize("hold", [0.0, 3.0, 10.0])
def test_exact_with_palette_rows_survives_shuffled_lost_and_duplicated_updates(hold: float) -> None:
    maps, nodes = team(3, hold=hold)
    net = MapExchange(nodes, drop=0.3, duplicate=0.3, reorder=True, seed=5)
    t = run(net, 0.0, 3)
    for k in range(6):  # the growing submaps change while messages are lost, doubled and shuffled
        for r in maps:
            add_scan(maps[r], 1, np.array([0.2 * k - 0.5, 0.1 * r, 1.0]), seed=100 + 10 * r + k)
        t = run(net, t, 1)
    net.drop = net.duplicate = 0.0
    run(net, t, 12)
    assert net.dropped > 0
    # duplicates did arrive (with a 10 s hold only 9 evidence messages go, none of them doubled)
    assert sum(n.ignored["evidence_duplicate"] + n.ignored["poses_duplicate"] for n in nodes.values()) > 0
    assert_exact(maps, nodes)


def test_holding_the_growing_submap_sends_fewer_bytes_for_the_same_team_map() -> None:
    sent = {}
    for hold in (0.0, 4.0):  # the growing submap 1 of robot 0 gets 8 scans, one per period
        maps, nodes = team(2, hold=hold)
        net = MapExchange(nodes)
        t = run(net, 0.0, 2)
        for k in range(8):
            add_scan(maps[0], 1, np.array([0.1 * k - 0.4, 0.2, 1.1]), seed=200 + k)
            t = run(net, t, 1)
        run(net, t, 8)
        assert_exact(maps, nodes)
        sent[hold] = net.bytes[0]["map/evidence"]
    assert sent[4.0] < sent[0.0]


def test_rows_that_share_a_hash_still_get_their_own_palette_entries(monkeypatch: pytest.MonkeyPatch) -> None:
    from kimera_multi_py.mapshare import wire

    codes, values = _submap_rows()
    monkeypatch.setattr(wire, "_MIX", np.zeros_like(wire._MIX))  # every row mixes to the same 64 bits
    got_codes, got_values = unpack_cells(pack_cells(codes, values), len(codes), K, "w")
    assert len(np.unique(values, axis=0)) > 1
    assert np.array_equal(got_codes, codes) and np.array_equal(got_values, values)
