"""Frame decisions over a row of identical rooms (:func:`.alignment.decide`).

A robot meets its peers in a row of four identical rooms, 6 m apart, and (sometimes) at one place
that looks like no other. Every room it shares with a peer also yields aliased closures to the
peer's keyframes one room further on: the frame shifted by one room. That alias rests on almost
as many places as the truth, so a lead in places alone is never twice its support; what tells
them apart is where only one of them has closures.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.alignment.frames import FrameHypothesis, decide, frame_hypotheses, settled_decision
from kimera_multi_py.core.geometry import inverse, make_pose, se3_exp

ROOM = 6.0
T_TRUE = make_pose(np.eye(3), np.array([-12.0, 2.5, 0.0]))  # team <- own frame


def _closures(rooms: list[int], aliased: list[int], unique: bool, peers: tuple[int, ...] = (1, 2), seed: int = 0
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closures of the robot (own frame) with ``peers`` (team frame): 3 per peer in each room of
    ``rooms``, 3 aliased ones (to the peer one room further on) in each room of ``aliased``, and 3
    at the unique place 10 m off the row when ``unique``. Returns own, neighbour, Z, own_is_i,
    peer, alias."""
    rng = np.random.default_rng(seed)
    own, nb, Z, peer, alias = [], [], [], [], []
    spots = [(ROOM * k, False) for k in rooms] + [(ROOM * k, True) for k in aliased]
    spots += [(30.0, False)] if unique else []
    for x, is_alias in spots:
        for p in peers:
            for _ in range(3):
                o = make_pose(np.eye(3), np.array([x, 0.0, 0.0]) + rng.normal(scale=0.4, size=3) * [1, 1, 0])
                seen = T_TRUE @ o @ se3_exp(rng.normal(scale=[0.05, 0.05, 0.3, 0.3, 0.3, 0.0]))  # peer keyframe
                rel = inverse(T_TRUE @ o) @ seen @ se3_exp(rng.normal(scale=0.01, size=6))
                shift = make_pose(np.eye(3), np.array([ROOM, 0.0, 0.0])) if is_alias else np.eye(4)
                own.append(o)
                nb.append(shift @ seen)  # an aliased closure's peer keyframe is one room further on
                Z.append(rel)
                peer.append(p)
                alias.append(is_alias)
    n = len(own)
    return np.array(own), np.array(nb), np.array(Z), np.ones(n, dtype=bool), np.array(peer), np.array(alias)


def _hypotheses(rooms: list[int], aliased: list[int], unique: bool) -> tuple[list[FrameHypothesis], np.ndarray]:
    own, nb, Z, own_is_i, peer, alias = _closures(rooms, aliased, unique)
    return frame_hypotheses(own, nb, Z, own_is_i, peer), alias


def _is_true(h: FrameHypothesis) -> bool:
    return bool(np.linalg.norm(h.T[:3, 3] - T_TRUE[:3, 3]) < 1.0)


def test_places_only_the_truth_explains_decide_a_row_of_twin_rooms() -> None:
    # every room but the last aliases to the next: truth 4 rooms + the unique place per peer,
    # the shift 3 rooms per peer (10 against 6 places: less than twice)
    hyps, alias = _hypotheses([0, 1, 2, 3], [0, 1, 2], unique=True)
    assert _is_true(hyps[0]) and not alias[hyps[0].edges].any()
    assert hyps[1].places > hyps[0].places / 2  # a lead in places alone would not decide
    best, margin = decide(hyps)
    assert best is hyps[0] and margin >= 2


def test_a_row_of_twin_rooms_alone_stays_undecided() -> None:
    # the robot met its peers only in rooms 0-2; the shift by one room (rooms 1-3 of the peers)
    # explains exactly as many places, none that the truth does not: nothing to decide on
    hyps, _ = _hypotheses([0, 1, 2], [0, 1, 2], unique=False)
    assert decide(hyps)[0] is None


def test_peers_agreeing_on_one_frame_through_disjoint_closures_do_not_contest() -> None:
    own, nb, Z, own_is_i, peer, _ = _closures([0, 1, 2, 3], [], unique=True)
    every = frame_hypotheses(own, nb, Z, own_is_i, peer)
    per_peer = []
    for p in (1, 2):
        idx = np.flatnonzero(peer == p)
        hyps = frame_hypotheses(own[idx], nb[idx], Z[idx], own_is_i[idx], peer[idx])
        for h in hyps:
            h.edges = idx[h.edges]
        per_peer.append(hyps)
    best, _, verdict = settled_decision(None, every, per_peer)
    assert verdict == "settled" and best is not None and _is_true(best)
    # the same two peers' leads, each compared with the other when every edge decides nothing
    best, _, verdict = settled_decision(None, [], per_peer)
    assert verdict != "contested"
