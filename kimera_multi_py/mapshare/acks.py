"""Map consensus: which sends a neighbour has been through (docs/algorithms/map_consensus.md, "Losses").

Every :class:`~kimera_multi_py.comms.messages.maps.SubmapEvidence` and
:class:`~kimera_multi_py.comms.messages.maps.SubmapPoses` a robot publishes carries ``seq``, one
counter per *stream* (evidence, poses) per publisher. A robot's version summary acknowledges, per
publisher it hears, the highest ``seq`` of each stream it has received (applied, ignored as a
duplicate or refused: received). A link carries a stream in its publication order (one priority
class of docs/deployment.md, "Link budget"), so a summary whose acknowledgement reaches a send's
``seq`` was made after that send arrived or was lost: if the summary still lacks what was sent,
it was lost. A summary below it says nothing about the send, which may still wait in a queue
(the old rule took every summary after a send for evidence, and a slow link re-sent a queued
submap once per summary period).

A send nothing follows (the last before the robots stop) is never acknowledged when it is
lost. So a send also counts as gone through when the neighbour's acknowledgement has not moved
for a while of its summaries since the send (a moving link acknowledges every message it
delivers): twice the time the neighbour's acknowledgements of our sends have been taking (the
largest lately, at least ``wait`` seconds), doubled with each send of the same version, a
back-off for a link that stalls longer than that. A robot that restarts numbers on from the highest acknowledgement of
it that it hears.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

EVIDENCE, POSES = 0, 1
STREAMS = (EVIDENCE, POSES)


@dataclass
class Send:
    """A robot's last send of one item (a submap's evidence or a source's pose table)."""

    version: int
    t: float  # local time of the send
    seq: int
    to: frozenset[int]  # the neighbours it went to
    count: int = 1  # sends of this version so far


class Acks:
    """A robot's acknowledgements: the sequence numbers it stamps, what it received, and what each
    neighbour's latest summary acknowledged (see the module docstring)."""

    def __init__(self, robot: int, wait: float) -> None:
        self.robot = int(robot)
        self.wait = float(wait)
        self._seq = [0, 0]  # per stream: the last seq stamped
        self._stamped: list[deque[tuple[int, float]]] = [deque(), deque()]  # per stream: (seq, time), recent
        self.flight: dict[int, float] = {}  # per neighbour: send to acknowledgement (s, decaying max)
        self._got: list[dict[int, int]] = [{}, {}]  # per stream: publisher -> highest seq received
        # per neighbour, per stream: publisher -> (acknowledged seq, local time it last moved)
        self._peer: dict[int, list[dict[int, tuple[int, float]]]] = {}

    def stamp(self, stream: int, now: float) -> int:
        """The ``seq`` of the next message of ``stream`` this robot publishes at ``now``."""
        self._seq[stream] += 1
        stamped = self._stamped[stream]
        stamped.append((self._seq[stream], float(now)))
        if len(stamped) > 4096:
            stamped.popleft()
        return self._seq[stream]

    def received(self, stream: int, publisher: int, seq: int) -> None:
        """A message of ``stream`` from ``publisher`` arrived (whatever became of it)."""
        got = self._got[stream]
        if seq > got.get(publisher, 0):
            got[publisher] = int(seq)

    def fields(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The summary's ``ack_robots``, ``ack_evidence`` and ``ack_poses``."""
        robots = sorted(set(self._got[EVIDENCE]) | set(self._got[POSES]))
        return (np.array(robots, np.int32),
                np.array([self._got[EVIDENCE].get(r, 0) for r in robots], np.int64),
                np.array([self._got[POSES].get(r, 0) for r in robots], np.int64))

    def on_summary(self, k: int, robots: np.ndarray, evidence: np.ndarray, poses: np.ndarray, now: float) -> None:
        """Neighbour ``k``'s summary, received at local time ``now``, acknowledged these."""
        old = self._peer.get(k, [{}, {}])
        new: list[dict[int, tuple[int, float]]] = [{}, {}]
        for stream, acks in ((EVIDENCE, evidence), (POSES, poses)):
            for r, a in zip(robots.tolist(), acks.tolist(), strict=True):
                if a <= 0:
                    continue
                prev = old[stream].get(r)
                new[stream][r] = prev if prev is not None and prev[0] == a else (a, now)
                if r == self.robot and (prev is None or prev[0] != a):
                    self._learn(k, stream, a, now)
                if r == self.robot and a > self._seq[stream]:  # numbered by an earlier run of ours
                    self._seq[stream] = a
        self._peer[k] = new

    def _learn(self, k: int, stream: int, ack: int, now: float) -> None:
        stamped = self._stamped[stream]
        i = ack - stamped[-1][0] + len(stamped) - 1 if stamped else -1  # consecutive since the last renumbering
        if not 0 <= i < len(stamped) or stamped[i][0] != ack:
            i = next((j for j, (seq, _) in enumerate(stamped) if seq == ack), -1)
        if i >= 0:
            took = now - stamped[i][1]
            self.flight[k] = max(took, 0.7 * self.flight.get(k, took) + 0.3 * took)

    def hears(self, k: int, stream: int, publisher: int) -> bool:
        """Whether ``k``'s latest summary acknowledges anything of ``publisher``'s ``stream``."""
        return publisher in self._peer.get(k, [{}, {}])[stream]

    def through(self, k: int, stream: int, publisher: int, seq: int, since: float, summary_t: float,
                sends: int = 1) -> bool:
        """Whether ``k``'s latest summary (received at ``summary_t``) was made after message
        ``seq`` of ``publisher``'s ``stream``, published or received here at ``since``, arrived
        or was lost: acknowledged, or the acknowledgement stood still after ``since`` for twice
        the flight time to ``k`` (at least ``wait``), times ``2 ** (sends - 1)``."""
        ack, moved = self._peer.get(k, [{}, {}])[stream].get(publisher, (0, -np.inf))
        if ack >= seq:
            return True
        wait = max(self.wait, 2.0 * self.flight.get(k, 0.0)) * 2.0 ** min(max(sends - 1, 0), 16)
        return summary_t - max(since, moved) > wait
