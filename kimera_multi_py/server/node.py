"""Server: the centralised-mode runtime (docs/architecture.md). Same agents, different wiring.

Agents stream their keyframe odometry (``KeyframeOdometry``) and every loop closure their
front ends accept (``LoopClosures``, inter- and intra-robot) over the Bus. The server keeps the
joint graph, optimises it with gtsam GNC (:func:`solve_centralized`, robust) and publishes each
robot's corrected keyframe poses back as ``PublicPoses`` from its own id. It never sees a
robot's raw sensor data, and a robot that never connects simply keeps its odometry.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.alignment.server_frames import FrameScreen, MapRule, screen_frames
from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import Bus, Subscription
from kimera_multi_py.comms.closure_stream import ClosureInbox
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.closures import KeyframeOdometry, LoopClosures
from kimera_multi_py.comms.messages.pgo import PublicPoses
from kimera_multi_py.comms.messages.team import AgentState, PgoEpoch
from kimera_multi_py.core.errors import KimeraMultiError, MessageError
from kimera_multi_py.core.ids import SERVER_ID as SERVER_ID  # re-exported: the server's id
from kimera_multi_py.core.posegraph import PoseGraph, robot_key, split_key
from kimera_multi_py.core.robust import correlated_votes
from kimera_multi_py.mapping.submaps import SubmapMap
from kimera_multi_py.mapshare.agreement import source_states
from kimera_multi_py.mapshare.consensus import MAP_MESSAGES, MapConsensus, MapConsensusParams, get_map_consensus
from kimera_multi_py.mapshare.objects import OBJECT_MESSAGES, ObjectExchange
from kimera_multi_py.pgo.centralised import solve_centralized
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.team import ScheduleParams

log = logging.getLogger(__name__)



@dataclass
class ServerStats:
    solves: int = 0
    poses: int = 0
    edges: int = 0
    inter_edges: int = 0
    rejected_by_gnc: int = 0
    wall_s: float = 0.0
    refused: int = 0
    weights: dict[tuple[int, int, int, int], float] = field(default_factory=dict)


class Server:
    """Joint-graph GNC over what the agents stream (see the module docstring)."""

    def __init__(self, server_id: int, team: tuple[int, ...] | None, closure_sigmas: tuple[float, float],
                 odom_sigmas: tuple[float, float], closure_votes: bool = False, frame_screen: bool = True,
                 frame_params: PgoParams | None = None) -> None:
        self.id = server_id
        self.team = tuple(team) if team is not None else None  # None: whoever streams to it
        self.odometry: dict[int, list[np.ndarray]] = {r: [] for r in self.team or ()}
        self.closures: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.closure_info = np.diag(np.repeat(1.0 / np.square(closure_sigmas), 3))
        self.odom_info = np.diag(np.repeat(1.0 / np.square(odom_sigmas), 3))
        # correlated-closure votes (the agents' AgentParams.closure_votes) in the joint GNC: off.
        # Without the agents' frame hypotheses they make aliases cheaper: true closures that one
        # keyframe makes with many of the other robot's share a vote, an alias group spread over
        # many keyframes does not. Measured on office, 3 robots, seed 5 (the server's joint
        # graph): with votes GNC keeps 14 false closures (team ATE 2.81 m), and the alias's voted
        # TLS cost is below the truth's (267.5 against 280.6); without votes 0 false (0.077 m)
        self.closure_votes = closure_votes
        # the agents' frame decision before GNC (:mod:`~kimera_multi_py.alignment.server_frames`); off: all closures
        self.frame_screen = frame_screen
        self.frame_params = frame_params or PgoParams()  # the agents' frame rule (``align_*``, ``place_radius``)
        self.frames: FrameScreen | None = None  # the last solve's frame decisions
        self.map_rule: MapRule | None = None  # the frame screen faces the team map (ServerNode.fuse_maps)
        self.stats = ServerStats()
        self.round = 0

    # ---- messages in ----------------------------------------------------------------------
    def handle(self, msg: Message) -> None:
        if isinstance(msg, KeyframeOdometry):
            chain = self.odometry.setdefault(msg.robot, [])
            for k, T in zip(msg.keyframes.tolist(), msg.odometry, strict=True):
                if k != len(chain):
                    raise ValueError(f"robot {msg.robot}: odometry for keyframe {k}, expected {len(chain)}")
                chain.append(np.array(T))
        elif isinstance(msg, LoopClosures):
            self.closures[(msg.robot, msg.peer)] = (np.array(msg.keys_a), np.array(msg.keys_b), np.array(msg.poses))

    @property
    def root(self) -> int | None:
        """The root of the team frame: the lowest robot in the joint graph (None while it is empty)."""
        return min((r for r in (self.team or self.odometry) if self.odometry.get(r)), default=None)

    # ---- the joint graph ------------------------------------------------------------------
    def graph(self) -> tuple[PoseGraph, list[tuple[int, int, int, int]]]:
        robots = [r for r in (self.team or sorted(self.odometry)) if self.odometry.get(r)]
        offset, n = {}, 0
        for r in robots:
            offset[r] = n
            n += len(self.odometry[r])
        poses, robot, local, ei, ej, Z, info = [], [], [], [], [], [], []
        for r in robots:
            chain = self.odometry[r]
            T = np.eye(4)
            for k, odo in enumerate(chain):
                T = T @ odo if k else np.eye(4)
                poses.append(T)
                robot.append(r)
                local.append(k)
                if k:
                    ei.append(offset[r] + k - 1)
                    ej.append(offset[r] + k)
                    Z.append(odo)
                    info.append(self.odom_info)
        tags: list[tuple[int, int, int, int]] = []
        for _pair, (ka, kb, meas) in sorted(self.closures.items()):
            for x, y, T in zip(ka.tolist(), kb.tolist(), meas, strict=True):
                (ra, ia), (rb, ib) = split_key(x), split_key(y)
                if ra not in offset or rb not in offset or ia >= len(self.odometry[ra]) \
                        or ib >= len(self.odometry[rb]):
                    continue  # refers to keyframes we have not heard about yet
                ei.append(offset[ra] + ia)
                ej.append(offset[rb] + ib)
                Z.append(T)
                info.append(self.closure_info)
                tags.append((ra, ia, rb, ib))
        info_arr = np.array(info).reshape(-1, 6, 6)
        votes = self.votes(len(info_arr), tags)
        g = PoseGraph(
            poses=np.array(poses).reshape(-1, 4, 4), robot=np.array(robot, dtype=int), local=np.array(local, dtype=int),
            ids=np.array([robot_key(r, k) for r, k in zip(robot, local, strict=True)], dtype=np.int64),
            edge_i=np.array(ei, dtype=int), edge_j=np.array(ej, dtype=int),
            measurement=np.array(Z).reshape(-1, 4, 4), information=info_arr * votes[:, None, None],
            source="server",
        )
        return g, tags

    def votes(self, num_edges: int, tags: list[tuple[int, int, int, int]]) -> np.ndarray:
        """Each edge's robust vote: 1 for odometry, the closures' correlated votes after it
        (``tags`` are the closures, the last edges of the joint graph)."""
        votes = np.ones(num_edges)
        if self.closure_votes and tags:
            t = np.array(tags, dtype=int)
            votes[num_edges - len(tags):] = correlated_votes(t[:, 0], t[:, 1], t[:, 2], t[:, 3])
        return votes

    def optimise(self) -> list[Message]:
        """Solve the joint graph with GNC; return each robot's corrected poses."""
        g, tags = self.graph()
        if g.num_poses == 0:
            return []
        t0 = time.perf_counter()
        votes = self.votes(g.num_edges, tags)
        keep = np.ones(g.num_edges, dtype=bool)
        if self.frame_screen:
            p = self.frame_params
            self.frames = screen_frames(g, p.align_min_places, p.align_min_margin, p.place_radius,
                                        lone=p.align_lone_place, maps=self.map_rule,
                                        rival_places=p.align_tie_min_places)
            keep = self.frames.keep
            for r in self.frames.excluded():
                why = self.frames.report[r]["reason"]
                (log.warning if why == "no frame hypothesis leads" else log.info)(
                    "server: robot %d kept out of the team frame (%s)", r, why)
        solved = dataclasses.replace(g.subset_edges(keep), poses=self.frames.poses if self.frames else g.poses)
        res = solve_centralized(solved, robust=True, votes=votes[keep])
        self.stats.wall_s += time.perf_counter() - t0
        self.stats.solves += 1
        self.stats.poses, self.stats.edges, self.stats.inter_edges = g.num_poses, g.num_edges, len(tags)
        weights = np.zeros(g.num_edges)
        weights[keep] = 1.0 if res.weights is None else res.weights
        loop_w = weights[g.num_edges - len(tags):]
        self.stats.weights = {t: float(w) for t, w in zip(tags, loop_w, strict=True)}
        self.stats.rejected_by_gnc = int(np.sum(loop_w < 0.5))
        self.round += 1
        out: list[Message] = []
        # a robot kept out of the team frame gets its poses in its own frame, flagged not settled
        excluded = set(self.frames.excluded()) if self.frames else set()
        for r in sorted(set(g.robot.tolist())):
            idx = g.robot_indices(r)
            out.append(PublicPoses(robot=self.id, round=self.round,
                                   keys=np.array([robot_key(r, k) for k in range(len(idx))], dtype=np.int64),
                                   poses=res.poses[idx], settled=r not in excluded))
        return out


class ServerNode:
    """The Server on a Bus, on its own clock: it absorbs the team's topics, solves every
    ``period`` seconds of team time and once more (``final``) when every robot it knows has ended
    its stream; after the final solve it publishes a final :class:`PgoEpoch` so the agents know
    the run is over."""

    def __init__(self, server: Server, bus: Bus, schedule: ScheduleParams | None = None,
                 clock: Callable[[], float] | None = None) -> None:
        self.server = server
        self.bus = bus
        self.schedule = schedule or ScheduleParams()
        self.clock = clock or self._stream_time
        self.states: dict[int, AgentState] = {}
        self.complete = False
        self._sub: Subscription | None = None
        self._solved_at = 0.0
        self._absent_since: dict[int, float] = {}
        self._finished_since: float | None = None
        self._final_keyframes: dict[int, int] = {}
        self._final: PgoEpoch | None = None
        self.maps: MapConsensus | None = None  # the team map: every robot's evidence, fused here
        self.objects: ObjectExchange | None = None  # every robot's object table, relayed and fused here
        self.closures_in = ClosureInbox()  # the robots' closure batches, expanded

    def fuse_maps(self, local: SubmapMap, mode: str = "exact", params: MapConsensusParams | None = None,
                  keyframes_per_submap: int = 10) -> None:
        """Also fuse every robot's map evidence (a star: the agents' only map neighbour) and serve
        the team map back. ``local`` is an empty map with the agents' map parameters; ``params``
        the agents' map consensus knobs (default: the defaults); ``keyframes_per_submap`` the
        agents' mapping parameter: with exact fusion and the server's ``frame_params.map_check``
        (the agents' PGO parameters), its frame screen faces the robots' maps as the agents'
        frame decisions do."""
        self.maps = get_map_consensus(self.robot, local, mode, base=params)
        p = self.server.frame_params
        if self.maps.mode == "exact" and p.map_check:
            maps = self.maps
            self.server.map_rule = MapRule(
                lambda robot, poses: source_states(maps, robot, poses, keyframes_per_submap, p.map_occupancy),
                p.map_min_conflicts, p.map_conflict_ratio, p.map_coarse, p.align_rivals == "refuted")
        # the joint graph's frame: the lowest robot's (it follows the graph, see tick). Evidence is
        # applied only from robots whose pose tables are in it: a robot the frame screen keeps out
        # has its poses, and so its submaps and objects, in its own frame and stays out of the team map
        self.maps.set_frame(0)
        if self.maps.mode == "exact":
            maps = self.maps
            self.objects = ObjectExchange(self.robot, list,
                                          lambda src: maps.poses[src][0] if src in maps.poses else None,
                                          local.num_classes + 1)
            self.objects.set_frame(0)

    @property
    def robot(self) -> int:
        return self.server.id

    def _stream_time(self) -> float:
        return max((s.stamp for s in self.states.values()), default=0.0)

    async def start(self) -> None:
        await self.bus.announce()
        self._sub = self.bus.subscribe(keys.team_all(self.bus.team))

    async def drain(self) -> int:
        assert self._sub is not None, "start() first"
        n = 0
        while (msg := self._sub.try_recv()) is not None:
            n += 1
            if msg.robot == self.robot:
                continue
            if isinstance(msg, AgentState):
                self.states[msg.robot] = msg
                continue
            if isinstance(msg, MAP_MESSAGES + OBJECT_MESSAGES):
                sink = self.maps if isinstance(msg, MAP_MESSAGES) else self.objects
                if sink is not None:
                    try:
                        sink.handle(msg)
                    except (KimeraMultiError, ValueError, KeyError, IndexError) as exc:
                        self.server.stats.refused += 1
                        log.warning("server refused %s from robot %d: %s", type(msg).__name__, msg.robot, exc)
                continue
            try:
                self.server.handle(self.closures_in.expand(msg) if isinstance(msg, LoopClosures) else msg)
            except (ValueError, MessageError) as exc:
                self.server.stats.refused += 1
                log.warning("server refused %s from robot %d: %s", type(msg).__name__, msg.robot, exc)
        return n

    async def tick(self, wall: float | None = None, force: bool = False) -> int:
        """Solve on the period, and the final solve when every stream is over."""
        now = self.clock()
        wall = time.monotonic() if wall is None else wall
        sent = 0
        if self.maps is not None:
            root = self.server.root
            if root is not None:
                self.maps.set_frame(root)
                if self.objects is not None:
                    self.objects.set_frame(root)
            self.maps.set_neighbours({r for r in self.bus.peers() if r != self.robot})
            self.maps.set_team_size(max(1, len(self.states)))
            out = self.maps.step(wall)
            if self.objects is not None:
                self.objects.set_neighbours({r for r in self.bus.peers() if r != self.robot})
                out += self.objects.step(wall)
            for m in out:
                await self.bus.publish(self.bus.key(m.TOPIC), m)
                sent += 1
        if self._all_finished(wall):
            counts = {r: s.keyframes for r, s in self.states.items()}
            if counts == self._final_keyframes:
                return sent
            self._final_keyframes = counts
            await self.optimise()
            self._final = PgoEpoch(robot=self.robot, epoch=self.server.round,
                                   members=np.array(sorted(self.states), dtype=np.int64),
                                   pairs=np.zeros((0, 2), np.int64), final=True)
            await self.bus.publish(self.bus.key(PgoEpoch.TOPIC), self._final)
            self.complete = True
            return 1
        if now - self._solved_at >= self.schedule.period and self.server.odometry:
            self._solved_at = now
            await self.optimise()
            return sent + 1
        return sent

    def blocked(self) -> bool:
        return False

    def _all_finished(self, wall: float) -> bool:
        alive = {r for r in self.bus.peers() if r != self.robot}
        for r in self.states:
            if r in alive:
                self._absent_since.pop(r, None)
            else:
                self._absent_since.setdefault(r, wall)
        waiting = [r for r, st in self.states.items() if not st.finished
                   and (r in alive or wall - self._absent_since.get(r, wall) < self.schedule.absent_timeout)]
        waiting += [r for r in alive if r not in self.states]
        if waiting or not self.states:
            self._finished_since = None
            return False
        if self._finished_since is None:
            self._finished_since = wall
        return wall - self._finished_since >= self.schedule.final_grace

    async def optimise(self) -> None:
        await self.drain()
        for msg in self.server.optimise():
            await self.bus.publish(self.bus.key(msg.TOPIC), msg)

    async def run(self, tick_s: float = 0.005, linger: float = 30.0) -> None:
        """Serve until the final solve is published, then repeat its announcement until every
        agent reports it complete (at most ``linger`` s): a lost announcement must not strand one."""
        while not self.complete:
            await self.drain()
            await self.tick()
            await asyncio.sleep(tick_s)
        end = time.monotonic() + linger
        while time.monotonic() < end and not all(s.complete for s in self.states.values()):
            await self.drain()
            if self._final is not None:
                await self.bus.publish(self.bus.key(PgoEpoch.TOPIC), self._final)
            await asyncio.sleep(0.5)

    async def close(self) -> None:
        if self._sub is not None:
            self._sub.close()
