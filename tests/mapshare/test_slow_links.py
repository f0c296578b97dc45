"""The exact map consensus over links that hold messages for several summary periods (a byte
budget per link, docs/deployment.md "Link budget"): a send waiting in a queue is not taken for
lost and sent again (docs/algorithms/map_consensus.md, "Losses"), a lost one still is, and the
team maps end equal to the centralised fusion."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms.link_budget import LinkBudget
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.maps import SubmapEvidence
from kimera_multi_py.mapshare.exchange import MapExchange

from ..consensus.test_map_consensus import add_scan, assert_exact, run, team

SUMMARY_PERIOD = 5.0  # MapConsensusParams: summary_every periods of 1 s


def _grow(maps: dict, net: MapExchange) -> float:
    """Three rounds, then new versions of submap 0 of each robot in turn."""
    t = run(net, 0.0, 3)
    for k in range(4):
        add_scan(maps[k % 3], 0, np.array([0.3 * k - 0.5, 0.1, 1.2]), seed=100 + k)
        t = run(net, t, 2)
    return t


def _evidence_sends(net: MapExchange) -> dict[tuple[int, int, int, int], int]:
    """(sender, source, submap, version) -> how many times it was published."""
    return {k[1:]: n for k, n in net.sent.items() if k[0] is SubmapEvidence}


def test_evidence_queued_for_several_summary_periods_is_sent_once() -> None:
    maps, nodes = team(3)
    net = MapExchange(nodes, budget=LinkBudget(kbps=1.0))
    run(net, _grow(maps, net), 100)
    assert max(q.stats.delay_max for q in net.queues.values()) > 3 * SUMMARY_PERIOD  # the links held it
    assert all(q.stats.dropped_messages == 0 for q in net.queues.values())
    sends = _evidence_sends(net)
    own = {k: n for k, n in sends.items() if k[0] == k[1]}
    assert len(own) >= 10 and max(own.values()) == 1  # each version of a robot's own submap went once
    assert max(sends.values()) == 1
    assert_exact(maps, nodes)


def test_lost_evidence_is_sent_again_over_a_slow_link() -> None:
    """A loss in the middle of the stream (acknowledged past by what follows) and one at its tail
    (nothing follows it) are both sent again."""
    maps, nodes = team(3)
    drops = {(0, 1, 1, 1)}  # (source, submap, version, receiver): the first send of each is lost
    lost: set[tuple[int, int, int, int]] = set()

    def lose(sender: int, receiver: int, msg: Message) -> bool:
        key = (msg.source, msg.submap, msg.version, receiver) if isinstance(msg, SubmapEvidence) else None
        if sender == getattr(msg, "source", -1) and key in drops and key not in lost:
            lost.add(key)
            return True
        return False

    net = MapExchange(nodes, budget=LinkBudget(kbps=1.0), lose=lose)
    t = run(net, _grow(maps, net), 60)
    add_scan(maps[1], 1, np.array([0.1, 0.5, 1.1]), seed=120)
    last = maps[1].submaps[1].num_scans  # robot 1's last version: its first send to both is lost
    drops |= {(1, 1, last, 0), (1, 1, last, 2)}
    run(net, t, 80)
    assert lost == drops
    sends = _evidence_sends(net)
    assert sends[(0, 0, 1, 1)] == 2  # lost in the middle of the stream: sent again
    assert sends[(1, 1, 1, last)] == 2  # lost at its tail: sent again once the acks stood still
    assert_exact(maps, nodes)


def test_a_relay_chain_over_slow_links_sends_each_version_once_per_hop() -> None:
    """Four robots in a line: evidence crosses two relays, each link holding it for several
    summary periods. Re-sends multiplied along the chain (the rule before sent a version up to
    16 times here, and the maps were not whole by the end)."""
    maps, nodes = team(4)
    line = {0: {1}, 1: {0, 2}, 2: {1, 3}, 3: {2}}
    net = MapExchange(nodes, links=line, budget=LinkBudget(kbps=1.0))
    run(net, _grow(maps, net), 100)
    assert max(q.stats.delay_max for q in net.queues.values()) > 3 * SUMMARY_PERIOD
    sends = _evidence_sends(net)
    assert max(sends.values()) == 1
    assert {k[1] for k in sends if k[0] != k[1]} >= {0, 1, 2, 3}  # relayed: every robot's evidence
    assert_exact(maps, nodes)
