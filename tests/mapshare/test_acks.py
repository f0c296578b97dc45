"""The acknowledgements that decide a map-consensus loss (docs/algorithms/map_consensus.md, "Losses")."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.mapshare.acks import EVIDENCE, POSES, Acks


def _summary(acks: Acks, k: int, evidence: dict[int, int], now: float) -> None:
    robots = sorted(evidence)
    acks.on_summary(k, np.array(robots, np.int32), np.array([evidence[r] for r in robots], np.int64),
                    np.zeros(len(robots), np.int64), now)


def test_a_send_is_through_once_acknowledged_or_once_the_acks_stand_still() -> None:
    a = Acks(0, wait=5.0)
    assert (a.stamp(EVIDENCE, 0.0), a.stamp(EVIDENCE, 1.0), a.stamp(POSES, 1.0)) == (1, 2, 1)
    _summary(a, 1, {0: 1}, 2.0)  # robot 1 has had our first evidence message, 2 s after it went
    assert a.through(1, EVIDENCE, 0, 1, 0.0, 2.0)
    assert not a.through(1, EVIDENCE, 0, 2, 1.0, 2.0)  # may still be queued
    assert not a.through(1, POSES, 0, 1, 1.0, 2.0)
    assert a.flight[1] == 2.0
    _summary(a, 1, {0: 1}, 6.0)
    assert not a.through(1, EVIDENCE, 0, 2, 1.0, 6.0)  # 4 s without a new acknowledgement
    _summary(a, 1, {0: 1}, 8.0)
    assert a.through(1, EVIDENCE, 0, 2, 1.0, 8.0)  # 6 s: taken for lost
    assert not a.through(1, EVIDENCE, 0, 2, 1.0, 8.0, sends=2)  # the second time it waits 10 s
    _summary(a, 1, {0: 2}, 9.0)
    assert a.through(1, EVIDENCE, 0, 2, 1.0, 9.0, sends=2)


def test_receipts_are_acknowledged_per_publisher_and_a_restart_numbers_on() -> None:
    a = Acks(0, wait=5.0)
    a.received(EVIDENCE, 2, 7)
    a.received(EVIDENCE, 2, 5)  # late or duplicated: the highest stands
    a.received(POSES, 1, 3)
    robots, evidence, poses = a.fields()
    assert robots.tolist() == [1, 2] and evidence.tolist() == [0, 7] and poses.tolist() == [3, 0]
    b = Acks(0, wait=5.0)  # robot 0 again, after a restart
    _summary(b, 2, {0: 40}, 1.0)
    assert b.stamp(EVIDENCE, 1.0) == 41
    assert b.hears(2, EVIDENCE, 0) and not b.hears(2, POSES, 0)
