"""TeamPgo: one robot's share of the distributed PGO that the team runs itself (docs/deployment.md).

Pure logic, no I/O: :meth:`TeamPgo.handle` absorbs messages, :meth:`TeamPgo.tick` returns the
messages to publish. The node (:mod:`kimera_multi_py.agent.node`) moves them.

* **Epochs.** PGO runs in epochs. The *leader* — the lowest robot id alive — opens epoch ``e``
  with a :class:`PgoEpoch` naming its members (the robots alive now) and its robot graph, when
  ``period`` seconds of team time passed since the last epoch, when new inter-robot closures
  were accepted or its robot graph joined robots it did not know were joined (members' states
  carry their robot graphs: the closure messages may have been lost on the way to the leader),
  at most every ``closure_interval`` s, and once more (``final``) when every robot it knows has
  ended its stream (again if closures were accepted, or robots joined, after that epoch opened:
  they would never be optimised otherwise; and when a member's safety net took it out of the team
  frame after the final epoch, at most :data:`MAX_REOPEN` times per robot). Every member then
  builds a fresh :class:`PgoAgent` from its robot's current graph (warm-started from the
  current estimate, which is in the team frame once aligned) and runs rounds until the leader's
  ``stop``; the result is applied to the robot's poses. The robot's graph is the persistent
  state: it grows with every keyframe and closure between epochs.
* **Rounds.** A member runs round ``r`` once every robot it depends on (its neighbours; the
  epoch's leader waits for all members) reported round ``r − 1``, or when the wait times out:
  after ``round_timeout`` wall seconds in a process, or when the runtime says nothing more can
  arrive (:meth:`tick` with ``force``), which keeps the single-process simulation deterministic.
* **Epoch tags.** Every PGO message of epoch ``e`` travels with ``round = e·EPOCH_ROUNDS + r``;
  messages of other epochs never reach the epoch's solver (a late ``stop`` of epoch 3 must not
  end epoch 4).
* **Membership.** A robot that leaves is dropped from the epoch (nobody waits for it). Its last
  public poses stay fixed for its neighbours, so the edges to it keep constraining the others.
  A robot that joins is a member of the next epoch, where it aligns into the team frame.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from collections.abc import Callable, Collection
from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.alignment.map_check import MapAgreement
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.pgo import (
    EdgeVeto,
    FrameLandmarks,
    GncWeights,
    PgoCommand,
    PgoStatus,
    PoseDeltas,
    PublicPoses,
)
from kimera_multi_py.comms.messages.team import AgentState, PgoEpoch
from kimera_multi_py.pgo.agent import PgoAgent
from kimera_multi_py.pgo.local_graph import LocalGraph, component_root
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.pose_stream import PoseDecoder, PoseEncoder, PoseStreamParams

log = logging.getLogger(__name__)

EPOCH_ROUNDS = 1_000_000
EPOCH_RESEND = 25  # the leader repeats an epoch's opening every this many rounds
MAX_REOPEN = 2  # final epochs run again for one robot that left the team frame after the final one
_PGO_MESSAGES = (PublicPoses, PoseDeltas, PgoStatus, PgoCommand, GncWeights, EdgeVeto)


@dataclass
class ScheduleParams:
    """When the team optimises."""

    period: float = 60.0
    """Team-time seconds between PGO epochs (``--pgo-period``)."""
    closure_interval: float = 30.0
    """New accepted closures open an epoch at most this often (team-time s)."""
    round_timeout: float | None = 0.5
    """Wall seconds a round waits for its dependencies (null: only until forced; the simulator over
    loopback forces it once the network is quiet)."""
    absent_timeout: float = 30.0
    """Wall seconds an absent robot is waited for before the final epoch."""
    final_grace: float = 0.0
    """Wall seconds every stream must have been over before the final epoch."""


@dataclass
class Session:
    """One running epoch of this robot."""

    epoch: int
    members: tuple[int, ...]
    final: bool
    pgo: PgoAgent
    depends: set[int]
    keyframes: int  # the robot's keyframes when the epoch began
    rnd: int = 0
    seen: dict[int, int] = field(default_factory=dict)  # robot -> latest status round
    stopped: set[int] = field(default_factory=set)
    deadline: float | None = None
    began: float = 0.0  # team time


@dataclass
class TeamPgoStats:
    epochs: int = 0  # epochs this robot completed
    rounds: int = 0  # rounds it ran, over all epochs
    timeouts: int = 0  # rounds it ran without every dependency's status
    aborted: int = 0  # epochs replaced by a newer one before they finished
    opened: int = 0  # epochs it opened as the leader


class TeamPgo:
    """See the module docstring. ``build`` returns the robot's current :class:`LocalGraph`;
    ``apply`` adopts optimised poses of its first keyframes; ``landmarks`` (optional) returns
    the robot's object landmarks, MAP classes ``(n,)`` and centres ``(n, 3)`` in its current
    estimate's frame; ``map_view`` (optional) returns, for a team frame's root, how the robot's
    map agrees with the team's under a frame hypothesis (:mod:`kimera_multi_py.alignment.map_check`)."""

    def __init__(self, robot: int, params: PgoParams, schedule: ScheduleParams,
                 build: Callable[[], LocalGraph], apply: Callable[[np.ndarray], object],
                 robot_graph: Callable[[], Collection[tuple[int, int]]],
                 accepted_closures: Callable[[], int],
                 landmarks: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
                 map_view: Callable[[int], Callable[[np.ndarray], MapAgreement | None] | None] | None = None,
                 stream: PoseStreamParams | None = None) -> None:
        self.robot = robot
        # public poses out as a pose stream (block SOR; gn_pcg's lock-step wants them exact), and
        # whatever peers send decoded back to full PublicPoses
        self._encoder = PoseEncoder(stream) if stream is not None and params.method == "block_sor" else None
        self.decoder = PoseDecoder()
        self.params = params
        self.schedule = schedule
        self._build = build
        self._apply = apply
        self._robot_graph = robot_graph
        self._accepted = accepted_closures
        self._landmarks = landmarks
        self._map_view = map_view  # frame root -> how the robot's map agrees with the team's there
        # robot -> (root of its frame, classes, centres): settled peers' latest FrameLandmarks
        self.peer_landmarks: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        self._outbox: list[Message] = []  # messages not tied to a round (FrameLandmarks)
        self.epoch = 0  # the newest epoch heard of or opened
        self.completed = 0  # the newest epoch this robot completed
        self.final_done = False  # a final epoch completed (and no robot joined since)
        self.session: Session | None = None
        self.last_pgo: PgoAgent | None = None  # the solver of the last completed epoch
        self.stats = TeamPgoStats()
        self.states: dict[int, AgentState] = {}
        self.last_public: dict[int, np.ndarray] = {}  # pose key -> latest public pose heard
        self.last_settled: dict[int, bool] = {}  # robot -> its latest PublicPoses.settled
        self._future: list[Message] = []  # PGO messages (all carry a round) of an epoch not opened yet
        self._opened_at = 0.0  # team time of the last epoch's opening
        self._closures_at_open = 0
        self._pairs_at_open: frozenset[tuple[int, int]] = frozenset()  # the last epoch's robot graph
        self._finished_since: float | None = None
        self._absent_since: dict[int, float] = {}
        self._final_members: frozenset[int] = frozenset()
        self._reopened: Counter[int] = Counter()  # robot -> final epochs run again for it
        self._now = 0.0
        self._epoch_msg: PgoEpoch | None = None  # the last epoch this robot opened
        self.history: list[tuple[int, tuple[int, ...], bool, float]] = []  # completed: epoch, members, final, began

    # ------------------------------------------------------------------ messages in
    def handle(self, msg: Message, alive: Collection[int]) -> None:
        if isinstance(msg, AgentState):
            self.states[msg.robot] = msg
            if msg.epoch > self.epoch and self.session is None:
                self.epoch = msg.epoch  # a newer epoch ran elsewhere (partition, restart)
            if self.final_done and msg.robot not in self._final_members and msg.robot in alive:
                # a robot joined, or met us again (a partition that healed late), after the
                # final epoch: optimise again, with it
                self.final_done = False
            elif (self.final_done and msg.robot in self._final_members and msg.finished and not msg.complete
                  and msg.epoch >= self.completed and msg.robot in alive):
                # a member that completed the final epoch and is no longer complete: its safety
                # net took it out of the team frame (or it restarted): the team decides again
                self.reopen(msg.robot)
            return
        if isinstance(msg, PgoEpoch):
            if msg.epoch > self.epoch or (self.session is None and msg.epoch > self.completed
                                          and msg.epoch == self.epoch):
                self._begin(msg, alive)
            return
        if isinstance(msg, FrameLandmarks):
            if msg.robot != self.robot:
                self.peer_landmarks[msg.robot] = (msg.frame, np.asarray(msg.classes),
                                                  np.asarray(msg.centroids, dtype=float))
            return
        if not isinstance(msg, _PGO_MESSAGES) or msg.robot == self.robot:
            return
        if isinstance(msg, PublicPoses | PoseDeltas):
            decoded = self.decoder.decode(msg)
            if decoded is None:
                return
            msg = decoded
        if isinstance(msg, PublicPoses):
            for k, T in zip(msg.keys.tolist(), msg.poses, strict=True):
                self.last_public[int(k)] = np.array(T)
            self.last_settled[msg.robot] = bool(msg.settled)
        epoch, rnd = divmod(msg.round, EPOCH_ROUNDS)
        s = self.session
        if s is not None and epoch == s.epoch:
            self._absorb(s, dataclasses.replace(msg, round=rnd))
        elif epoch > self.epoch and len(self._future) < 10_000:
            self._future.append(msg)

    def reopen(self, robot: int) -> bool:
        """After the final epoch, run it again because of ``robot`` (its safety net took it out of
        the team frame, or it restarted), at most :data:`MAX_REOPEN` times per robot so that a
        robot the maps keep refuting cannot keep the team busy. Returns whether it was reopened."""
        if not self.final_done or self._reopened[robot] >= MAX_REOPEN:
            return False
        self._reopened[robot] += 1
        self.final_done = False
        log.info("robot %d: the final epoch runs again for robot %d", self.robot, robot, extra={"robot": self.robot})
        return True

    def _absorb(self, s: Session, msg: Message) -> None:
        if isinstance(msg, PgoStatus):
            s.seen[msg.robot] = max(s.seen.get(msg.robot, -1), msg.round)
        if isinstance(msg, PgoCommand) and msg.command == "stop":
            s.stopped.add(msg.robot)
        s.pgo.handle(msg)

    # ------------------------------------------------------------------ epochs
    def _begin(self, msg: PgoEpoch, alive: Collection[int]) -> None:
        members = tuple(sorted(int(r) for r in msg.members))
        if self.session is not None:
            self.stats.aborted += 1
        self.epoch = msg.epoch
        self.session = None
        if self.robot not in members:
            return
        pairs = [(int(a), int(b)) for a, b in msg.pairs.tolist()]
        local = self._build()
        keyframes = len(local.keys)
        local, seeded = self._restrict(local, members, pairs)
        last = self.last_pgo
        root = component_root(self.robot, members, local.robot_graph)
        # a frame an earlier epoch settled is kept against a tie or an early lead; an unsettled
        # one (adopted on one place) is decided afresh, and so is a frame with another root (the
        # robot was the root of its own, or of a team it is no longer joined to through the root)
        kept = last is not None and last.root_robot == root and (
            last.root or (last.frame.aligned and not last.frame.excluded and last.frame.settled))
        pgo = PgoAgent(local, self.params, neighbour_poses=seeded, peer_settled=self.last_settled,
                       in_team_frame=kept)
        if self._landmarks is not None:
            self._share_landmarks(pgo, last, members, local.robot_graph)
        if self._map_view is not None and root != self.robot:
            pgo.frame.set_map_view(self._map_view(root))
        leader = min(members)
        # the epoch's leader waits for everyone; the others for their neighbours and the leader
        # (which paces a robot without neighbours yet, instead of it racing to the round cap)
        depends = set(members if self.robot == leader else [*local.neighbours, leader]) & set(members)
        depends.discard(self.robot)
        self.session = Session(msg.epoch, members, bool(msg.final), pgo, depends, keyframes, began=self._now)
        if msg.final:  # a member that leads later re-runs the final epoch only for closures newer than this
            self._closures_at_open = max(self._closures_at_open, self._accepted())
        self._pairs_at_open = frozenset(pairs)
        future, self._future = self._future, []
        for m in future:
            epoch, rnd = divmod(m.round, EPOCH_ROUNDS)  # type: ignore[attr-defined]
            if epoch == msg.epoch:
                self._absorb(self.session, dataclasses.replace(m, round=rnd))
            elif epoch > msg.epoch:
                self._future.append(m)
        log.info("robot %d: PGO epoch %d with %s%s", self.robot, msg.epoch, list(members),
                 " (final)" if msg.final else "", extra={"robot": self.robot})

    def _restrict(self, local: LocalGraph, members: tuple[int, ...], pairs: list[tuple[int, int]]
                  ) -> tuple[LocalGraph, dict[int, np.ndarray]]:
        """The epoch's view of the graph: inter-robot edges to members, plus edges to absent
        robots whose last public pose is known (held fixed); the leader's robot graph."""
        member = np.isin(local.inter_peer, members)
        known = np.array([int(k) in self.last_public for k in local.inter_peer_key], dtype=bool)
        keep = member | known
        seeded = {int(k): self.last_public[int(k)] for k in local.inter_peer_key[~member & known]}
        sel = np.flatnonzero(keep)
        ms = set(members)
        local = dataclasses.replace(
            local,
            inter_own=local.inter_own[sel], inter_own_is_i=local.inter_own_is_i[sel],
            inter_peer=local.inter_peer[sel], inter_peer_key=local.inter_peer_key[sel],
            inter_meas=local.inter_meas[sel], inter_info=local.inter_info[sel],
            inter_vote=np.asarray(local.inter_vote)[sel], inter_edge=np.arange(len(sel)),
            robot_graph=sorted(p for p in pairs if p[0] in ms and p[1] in ms), team=members)
        return local, seeded

    def _share_landmarks(self, pgo: PgoAgent, last: PgoAgent | None, members: tuple[int, ...],
                         pairs: list[tuple[int, int]]) -> None:
        """Hand the solver the landmarks (own and settled peers'); publish ours when our poses
        are in this epoch's team frame on settled evidence (the last epoch's, rooted alike)."""
        assert self._landmarks is not None
        classes, centres = self._landmarks()
        pgo.frame.set_landmarks(classes, centres, self.peer_landmarks)
        root = component_root(self.robot, members, pairs)
        settled = pgo.frame.in_team_frame and last is not None and last.root_robot == root
        if len(classes) and (pgo.root or settled):
            self._outbox.append(FrameLandmarks(robot=self.robot, frame=root, classes=classes,
                                               centroids=np.asarray(centres, dtype=np.float32)))

    def _finish(self, s: Session) -> None:
        log.info("robot %d: PGO epoch %d ends after %d rounds (%s; %d timeouts so far, GNC step %d)", self.robot,
                 s.epoch, s.rnd, "stopped" if s.pgo.done else "round cap", self.stats.timeouts,
                 s.pgo.weights.gnc.steps,
                 extra={"robot": self.robot})
        self._apply(s.pgo.final_poses())
        self.last_pgo = s.pgo
        self.completed = s.epoch
        self.session = None
        self.stats.epochs += 1
        self.history.append((s.epoch, s.members, s.final, s.began))
        if s.final:
            self.final_done = True
            self._final_members = frozenset(s.members)

    # ------------------------------------------------------------------ the clock
    def tick(self, now: float, wall: float, alive: Collection[int], finished: bool,
             force: bool = False) -> list[Message]:
        """Advance: maybe open an epoch (leader), maybe run a round. ``now`` is team time
        (stream seconds), ``wall`` a monotonic wall clock, ``alive`` the robots present,
        ``finished`` whether this robot's stream ended; ``force`` ends a round's wait."""
        self._now = now
        out = self._lead(now, wall, set(alive), finished)
        out, self._outbox = out + self._outbox, []
        s = self.session
        if s is None:
            return out
        pgo = s.pgo
        gone = set(s.members) - set(alive) - {self.robot}
        if gone:  # robots that left are not waited for
            pgo.drop(gone)
            s.depends -= gone
        waiting = [r for r in s.depends if s.seen.get(r, -1) < s.rnd - 1 and r not in s.stopped]
        if waiting and not pgo.done and s.rnd > 0:
            timeout = self.schedule.round_timeout
            if not force and (timeout is None or s.deadline is None or wall < s.deadline):
                return out
            self.stats.timeouts += 1
        msgs: list[Message] = [] if pgo.done else pgo.step(s.rnd)
        if self._epoch_msg is not None and self._epoch_msg.epoch == s.epoch and s.rnd % EPOCH_RESEND == 0 \
                and s.rnd > 0:
            out.append(self._epoch_msg)  # the leader repeats the opening for a member that lost it
        self.stats.rounds += 0 if pgo.done else 1
        s.rnd += 1
        if self.schedule.round_timeout is not None:
            s.deadline = wall + self.schedule.round_timeout
        if pgo.done or s.rnd >= self.params.max_rounds:
            # echo the stop so a robot that lost the leader's copy still hears it
            msgs.append(PgoCommand(robot=self.robot, round=s.rnd, command="stop",
                                   active=np.zeros(0, np.int64)))
            self._finish(s)
        base = s.epoch * EPOCH_ROUNDS
        for m in msgs:
            sent: Message | None = dataclasses.replace(m, round=base + m.round)  # type: ignore[attr-defined]
            if self._encoder is not None and isinstance(sent, PublicPoses):
                sent = self._encoder.encode(sent)
            if sent is not None:
                out.append(sent)
        return out

    def blocked(self) -> bool:
        """A round is waiting for a status (what ``force`` would end)."""
        s = self.session
        return s is not None and any(s.seen.get(r, -1) < s.rnd - 1 and r not in s.stopped for r in s.depends)

    def _lead(self, now: float, wall: float, alive: set[int], finished: bool) -> list[Message]:
        """The leader opens epochs (see the module docstring)."""
        if self.robot != min(alive | {self.robot}) or self.session is not None:
            return []
        members = sorted(alive | {self.robot})
        final = self._all_finished(wall, alive, finished)
        closures = self._accepted()
        ms = set(members)
        pairs = sorted((a, b) for a, b in self._robot_graph() if a in ms and b in ms)
        # robots joined since the last epoch opened: closures we lost, or heard of only through a
        # member's state, count as new closures
        joined = not set(pairs) <= self._pairs_at_open
        due = now - self._opened_at >= self.schedule.period
        fresh = (closures > self._closures_at_open or joined) and \
            now - self._opened_at >= self.schedule.closure_interval
        if final:
            # closures accepted since the last final epoch opened (verified during it, or answered
            # late), or robots it did not know were joined, would never be optimised: the team
            # runs one more final epoch with them
            if self.final_done and closures <= self._closures_at_open and not joined:
                return []
        elif not (due or fresh) or self.final_done:
            return []
        self._opened_at, self._closures_at_open = now, closures
        msg = PgoEpoch(robot=self.robot, epoch=self.epoch + 1, members=np.array(members, dtype=np.int64),
                       pairs=np.array(pairs, dtype=np.int64).reshape(-1, 2), final=final)
        self.stats.opened += 1
        self._epoch_msg = msg
        self._begin(msg, alive)
        return [msg]

    def _all_finished(self, wall: float, alive: set[int], finished: bool) -> bool:
        """Every robot this one knows ended its stream (robots absent for ``absent_timeout``
        are no longer waited for), for ``final_grace`` seconds."""
        if not finished:
            self._finished_since = None
            return False
        for r in self.states:
            if r in alive:
                self._absent_since.pop(r, None)
            else:
                self._absent_since.setdefault(r, wall)
        waiting = [r for r, st in self.states.items() if not st.finished and r != self.robot
                   and (r in alive or wall - self._absent_since.get(r, wall) < self.schedule.absent_timeout)]
        waiting += [r for r in alive if r not in self.states]
        if waiting:
            self._finished_since = None
            return False
        if self._finished_since is None:
            self._finished_since = wall
        return wall - self._finished_since >= self.schedule.final_grace

    # ------------------------------------------------------------------ state
    @property
    def busy(self) -> bool:
        return self.session is not None
