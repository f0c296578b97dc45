"""SimRunner: feeds a team of robot nodes from the simulator and evaluates them against truth.

``run()`` reads as its stages: spawn the robots, stream every keyframe to them, evaluate against
ground truth, write the outputs. The runner is only a sensor feed, a clock and an evaluator:
every robot is an :class:`AgentNode` that runs its own loop closures, distributed PGO (opened
and closed by the team's leader) and outputs, exactly as in ``kimera-multi agent``. Modes:

* ``odometry`` -- dead reckoning: each robot chains its noisy keyframe odometry from identity.
  For the team figure each robot's odometry frame is anchored at its true start pose (the
  frames are otherwise unknown without inter-robot loop closures), then one SE(3) alignment
  over all robots is applied.
* ``distributed`` -- one node per robot, each on its own bus (in-process loopback, or one Zenoh
  session per robot). Estimates end in the team frame (robot 0's), which one SE(3) alignment
  places in the world for evaluation.
* ``centralized`` -- the same nodes plus a :class:`ServerNode` on its own bus: agents stream
  keyframe odometry and their accepted loop closures; the server runs gtsam GNC on the joint
  graph on its own schedule and publishes corrected poses back.

The clock is simulated: keyframes arrive in stamp order, and after each one the nodes run until
the network is quiet. Over loopback no wait is on the wall clock (a round's or a query's ends when
nothing more can arrive; delays run on :mod:`~kimera_multi_py.comms.deliveries`' event time), so a
seed always gives the same results, whatever the machine's load and however lossy the links.

Parameters come from a :class:`~kimera_multi_py.team.config.KimeraConfig`; the run folder gets
``config.yaml``, all the run ran with (docs/outputs.md): ``sim --config`` with it repeats the run.
"""

from __future__ import annotations

import asyncio
import dataclasses
import heapq
import math
import time
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.agent.outputs import RobotOutcome, outcome_of
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.comms.bus import Bus
from kimera_multi_py.comms.comm_range import neighbours_within
from kimera_multi_py.comms.faults import check_robots, cut_links
from kimera_multi_py.comms.link_budget import budget_of
from kimera_multi_py.comms.loopback import Faults, LoopbackBus, LoopbackNetwork
from kimera_multi_py.comms.team import TRANSPORTS, open_buses
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.core.ids import SERVER_ID
from kimera_multi_py.eval.accuracy import TeamMaps, accuracy_results, start_team_maps
from kimera_multi_py.eval.map_metrics import TeamMapReport
from kimera_multi_py.eval.people import people_results
from kimera_multi_py.eval.phi_records import PhiRecords
from kimera_multi_py.eval.results import Results
from kimera_multi_py.eval.team import (
    excluded_robots,
    scene_graph_results,
    team_frame_robots,
    team_results,
    trajectory_results,
)
from kimera_multi_py.mapping.config import get_submap_map
from kimera_multi_py.mapshare.fusion import centralised_team_map
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.server.node import Server, ServerNode
from kimera_multi_py.sim.scenario import ScenarioConfig, load_scenario
from kimera_multi_py.sim.simulation import Keyframe, Simulation
from kimera_multi_py.sim.source import keyframe_input
from kimera_multi_py.team.build import agent_params
from kimera_multi_py.team.config import DEFAULT_SCENARIO, KimeraConfig
from kimera_multi_py.viz.rerun_viz import NullViz, Viz
from kimera_multi_py.workflow.sim_links import DRAIN_S, SimLinks
from kimera_multi_py.workflow.sim_results import map_consensus_results, write_run
from kimera_multi_py.workflow.sim_track import Track
from kimera_multi_py.workflow.sim_viz import log_team

MODES = ("odometry", "distributed", "centralized")
MAP_SETTLE_S = 15.0  # sim seconds the team keeps exchanging maps after its final optimisation
PHI_EVERY_S = 10.0  # sim seconds between two records of the team maps' disagreement
Progress = Callable[[int, int], None]


class _SimClock:
    """The simulated clock the nodes read (seconds of scenario time)."""

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t


class SimRunner:
    """Runs one scenario for one seed and mode; returns :class:`Results`.

    ``config`` gives every parameter (default: the defaults; its ``run`` section is read by
    :meth:`from_config` only); ``pgo_period`` and ``map_consensus``, when given, override its
    ``schedule.period`` and ``node.map_consensus``; ``params`` and ``pgo_params`` replace what it builds.
    """

    def __init__(self, cfg: ScenarioConfig, seed: int | None = None, mode: str = "odometry",
                 out_dir: str | Path | None = None, viz: Viz | None = None,
                 on_progress: Progress | None = None, transport: str = "loopback",
                 pgo_period: float | None = None, params: AgentParams | None = None,
                 pgo_params: PgoParams | None = None, join: dict[int, float] | None = None,
                 leave: dict[int, float] | None = None, map_consensus: str | None = None,
                 comm_range: float | None = None, drop: float = 0.0, faults: Faults | None = None,
                 quality: bool = True, config: KimeraConfig | None = None,
                 simulation: Simulation | None = None) -> None:
        if mode not in MODES:
            raise ConfigError("mode", f"unknown mode {mode!r} (available: {', '.join(MODES)})")
        if transport not in TRANSPORTS:
            raise ConfigError("transport", f"unknown transport {transport!r} (available: {', '.join(TRANSPORTS)})")
        self.cfg = cfg
        self.mode = mode
        self.transport = transport
        self.sim = simulation or Simulation(cfg, seed)  # replay passes recorded streams (workflow/replay.py)
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.viz: Viz = viz or NullViz()
        self.on_progress = on_progress
        explicit = {name: values for name, values in (("schedule", {"period": pgo_period}),
                                                      ("node", {"map_consensus": map_consensus}))
                    if None not in values.values()}
        self.config = (config or KimeraConfig.defaults()).updated(explicit)
        self.params = params or agent_params(cfg, self.config)
        self.pgo_params = pgo_params or self.config.to_pgo_params()
        # over Zenoh a round waits on the wall clock; over loopback until the network is quiet
        self.schedule = self.config.to_schedule(round_timeout=0.5 if transport == "zenoh" else None)
        self.node_params = self.config.to_node_params()
        # a byte budget per link, on the simulated clock (docs/deployment.md, "Link budget")
        self.links = SimLinks(budget_of(self.node_params.link_budget, self.node_params.link_policy))
        if self.links.budget is not None and transport != "loopback":
            raise ConfigError("link_budget", "the simulation runs a link budget on its clock over the loopback "
                                             "transport (Zenoh processes: agent, launch)")
        self.map_params = self.config.to_map_params()
        self.scene_graph_params = self.config.to_scene_graph_params()
        self.clock = _SimClock()
        self.map_mode = self.node_params.map_consensus
        # score the maps and the scene graph against truth (off: team ATE, closures, map agreement only)
        self.quality = quality
        # loopback link faults (``faults`` wins over ``drop``); partitions run on the simulated clock
        self.faults = faults if faults is not None else Faults(drop=drop)
        check_robots(self.faults.partitions, range(self.sim.num_robots))
        if transport != "loopback" and self.faults != Faults(drop=self.faults.drop):
            raise ConfigError("transport", "delay, jitter, duplicates and partitions need the loopback transport")
        self.drop = self.faults.drop
        self._cut: frozenset[tuple[int, int]] = frozenset()
        self.comm_range = comm_range
        self.map_report: TeamMapReport | None = None
        self._next_phi = 0.0
        self._phi_s = 0.0  # wall time spent recording φ (evaluation, not part of wall_s)
        self.phi_background = True  # φ of each record computed in a worker thread (False: at once)
        self._phi: PhiRecords | None = None
        # worker processes for the accuracy figures' team maps (None: one per spare core for big maps)
        self.eval_workers: int | None = None
        self._team_maps: TeamMaps | None = None
        self._reference: Any = None
        # robot -> seconds after the others that it joins (its whole stream is shifted by that)
        self.join = {int(r): float(t) for r, t in (join or {}).items()}
        # robot -> time at which it leaves for good (its node closes; the rest of its stream is dropped)
        self.leave = {int(r): float(t) for r, t in (leave or {}).items()}
        for what, table in (("join", self.join), ("leave", self.leave)):
            for r, t in table.items():
                if not 0 <= r < self.sim.num_robots or not (math.isfinite(t) and t >= 0):
                    raise ConfigError(what, f"robot {r} at {t} s: needs a robot of the team and a time >= 0")
        self.tracks: list[Track] = []
        self.nodes: list[AgentNode] = []
        self.server: ServerNode | None = None
        self.outcomes: list[RobotOutcome] = []
        self.rays = 0

    @classmethod
    def from_config(cls, config: KimeraConfig, out_dir: str | Path | None = None, viz: Viz | None = None,
                    on_progress: Progress | None = None) -> SimRunner:
        """The run ``config`` describes, its ``run`` section included (``kimera-multi sim``)."""
        if config.run.scenario is None:
            config = config.updated({"run": {"scenario": DEFAULT_SCENARIO}})
        run = config.run
        assert run.scenario is not None
        chosen: dict[str, Any] = {"mode": run.mode, "transport": run.transport}  # null: SimRunner's own default
        return cls(load_scenario(run.scenario, robots=run.robots), seed=run.seed, out_dir=out_dir, viz=viz,
                   on_progress=on_progress, join=run.join, leave=run.leave, comm_range=run.comm_range,
                   faults=run.faults.build(), config=config, **{k: v for k, v in chosen.items() if v is not None})

    def resolved_config(self) -> KimeraConfig:
        """Everything this run runs with, its choices included: the run folder's ``config.yaml``."""
        run = {"scenario": self.config.run.scenario, "seed": self.sim.seed, "robots": self.sim.num_robots,
               "mode": self.mode, "transport": self.transport, "comm_range": self.comm_range, "join": self.join,
               "leave": self.leave, "faults": dataclasses.asdict(self.faults)}
        return KimeraConfig.resolved(run, self.params, self.pgo_params, self.node_params, self.schedule,
                                     self.map_params, self.scene_graph_params)

    @property
    def agents(self) -> list[Agent]:
        return [n.agent for n in self.nodes]

    @property
    def total_keyframes(self) -> int:
        return self.sim.num_keyframes

    def run(self) -> Results:
        t0 = time.perf_counter()
        self._spawn_agents()
        if self.mode == "odometry":
            self._run_odometry()
        else:
            asyncio.run(self._run_team())
        # the system's time: the evaluation's records of φ during the run are not the team's work
        results = self._evaluate(time.perf_counter() - t0 - self._phi_s)
        self._write_results(results)
        return results

    def _spawn_agents(self) -> None:
        self.tracks = [Track() for _ in range(self.sim.num_robots)]
        self.viz.log_world(self.sim.world)

    def _step(self, done: int, kf: Keyframe, est: np.ndarray) -> None:
        self.rays += len(kf.scan)
        self.viz.log_keyframe(kf.robot, kf.stamp, est, kf.true_pose, kf.scan.points(), kf.scan.labels)
        if self.on_progress is not None:
            self.on_progress(done, self.total_keyframes)

    def _run_odometry(self) -> None:
        for done, kf in enumerate(self.sim.stream(), 1):
            self._step(done, kf, self.tracks[kf.robot].add(kf))
        self.viz.close()

    async def _run_team(self) -> None:
        robots = list(range(self.sim.num_robots))
        central = self.mode == "centralized"
        ids = robots + ([SERVER_ID] if central else [])
        params = replace(self.params, server=SERVER_ID) if central else self.params
        async with self._buses(ids) as buses:
            node_params = dataclasses.replace(self.node_params, server=params.server)
            self.nodes = [AgentNode(Agent(r, None, params), buses[r], self.pgo_params, self.schedule, node_params,
                                    clock=self.clock.now, map_params=self.map_params) for r in robots]
            if self.comm_range is not None:
                for agent_node in self.nodes:
                    agent_node.map_neighbours = lambda r=agent_node.robot: self._in_range(r)
            self.map_report = TeamMapReport(self.map_mode, 0) if self.map_mode != "off" else None
            self._phi = PhiRecords(self.phi_background) if self.map_report is not None else None
            nodes: list[AgentNode | ServerNode] = list(self.nodes)
            if central:
                server = Server(SERVER_ID, None, self.params.closure_sigmas, self.params.odom_sigmas,
                                frame_params=self.pgo_params)
                self.server = ServerNode(server, buses[-1], self.schedule, clock=self.clock.now)
                if self.map_mode != "off":
                    self.server.fuse_maps(get_submap_map(params.mapping), self.map_mode, self.map_params,
                                          params.mapping.keyframes_per_submap)
                nodes.append(self.server)
            for node in nodes:
                if node.robot not in self.join:
                    await node.start()
            epochs = 0
            for done, kf in enumerate(self._stream(), 1):
                await self._links_until(kf.stamp, nodes, buses)
                self.clock.t = max(self.clock.t, kf.stamp)
                self._show_partitions(buses)
                for r, t in self.leave.items():
                    if kf.stamp >= t and self.nodes[r] in nodes:
                        nodes.remove(self.nodes[r])
                        await self.nodes[r].close()
                        await buses[r].close()
                if self.nodes[kf.robot] not in nodes:
                    continue
                node = self.nodes[kf.robot]
                if kf.index == 0 and kf.robot in self.join:
                    await node.start()
                await node.process_keyframe(keyframe_input(kf))
                await self._settle(nodes, buses)
                self.tracks[kf.robot].add(kf)
                self._step(done, kf, node.agent.poses[-1])
                self._record_phi()
                if self._epochs() > epochs:
                    epochs = self._epochs()
                    self._log_team(kf.stamp)
            self._start_team_maps()
            for node in self.nodes:
                if node in nodes:
                    await node.finish_stream()
            end = self.links.streams_end = self.clock.t
            waiting_from = end
            while True:
                await self._until_complete(nodes, buses, waiting_from, end)
                settle_end = self.clock.t + MAP_SETTLE_S
                # map consensus relays what is still missing (under a budget: until the links
                # drain); a safety net that takes a robot out of the frame the final epoch left it
                # in sends the team into another final epoch, and the wait begins again
                while all(n.complete for n in nodes) and (
                        self.clock.t < settle_end or any(not n.settled for n in nodes if isinstance(n, AgentNode))
                        or (self.links.active and self.clock.t - end < DRAIN_S
                            and not self.links.note_complete(self.clock.t, nodes))):
                    await self._links_until(self.clock.t + 1.0, nodes, buses)
                    self.clock.t += 1.0
                    self._show_partitions(buses)
                    await self._settle(nodes, buses)
                    self.links.note_complete(self.clock.t, nodes)
                if all(n.complete for n in nodes):
                    break
                waiting_from = self.clock.t
            self._record_phi(force=True)
            self._add_phi(finish=True)
            self._log_team()
            weights = self.server.server.stats.weights if self.server is not None else None
            self.outcomes = [outcome_of(n, weights) for n in self.nodes]
            for node in nodes:
                await node.close()
        self.viz.close()

    async def _until_complete(self, nodes: list[AgentNode | ServerNode], buses: list[Bus], since: float,
                              end: float) -> None:
        """Run the team on the simulated clock until every node's final optimisation is done."""
        while not all(n.complete for n in nodes):
            if not await self._settle(nodes, buses):
                # quiet but not done: time passes (a robot that left is waited for a while)
                if self.clock.t - since > 10 * self.schedule.absent_timeout + (
                        DRAIN_S if self.links.active and since == end else 0.0):
                    raise RuntimeError("the team stopped before its final optimisation")  # a bug
                await self._links_until(self.clock.t + 1.0, nodes, buses)
                self.clock.t += 1.0
                self._show_partitions(buses)
            self.links.note_complete(self.clock.t, nodes)

    @asynccontextmanager
    async def _buses(self, ids: list[int]) -> AsyncIterator[list[Bus]]:
        """One bus per robot (and server): over loopback with this run's link faults, whose
        partitions follow the simulated clock."""
        if self.transport != "loopback":
            async with open_buses(ids, self.transport, drop=self.drop, team="sim", seed=self.sim.seed) as zbuses:
                yield zbuses
            return
        self._cut = frozenset()
        net = LoopbackNetwork(team="sim", seed=self.sim.seed, faults=self.faults, robots=ids, clock=self.clock.now,
                              budget=self.links.budget)
        self.links.net = net
        buses: list[Bus] = [net.bus(r) for r in ids]
        try:
            yield buses
        finally:
            for b in buses:
                await b.close()

    def _show_partitions(self, buses: list[Bus]) -> None:
        """Show partition changes as presence changes, as Zenoh would: a robot cut off from this
        one leaves, and appears again when the link heals (so catch-up traffic follows)."""
        if not self.faults.partitions:
            return
        net = getattr(buses[0], "network", None)
        if not isinstance(net, LoopbackNetwork):
            return
        by_robot = {b.robot: b for b in buses}
        cut = cut_links(self.faults.partitions, sorted(by_robot), self.clock.t)
        for a, b in sorted(cut ^ self._cut):
            alive = (a, b) not in cut
            for me, other in ((a, b), (b, a)):
                bus = by_robot[me]
                if isinstance(bus, LoopbackBus) and not bus.closed and (not alive or (net.team, other) in net._alive):
                    bus._set_alive(other, alive)
        self._cut = cut

    def _stream(self) -> Iterator[Keyframe]:
        """Every robot's keyframes in time order, a late joiner's shifted by its delay."""
        if not self.join:
            return self.sim.stream()

        def shifted(r: int) -> Iterator[Keyframe]:
            dt = self.join.get(r, 0.0)
            for kf in self.sim.keyframes(r):
                yield replace(kf, stamp=kf.stamp + dt)

        return heapq.merge(*(shifted(r) for r in range(self.sim.num_robots)), key=lambda kf: (kf.stamp, kf.robot))

    def _in_range(self, robot: int) -> set[int]:
        """The robots within radio range of ``robot`` now (by their true positions)."""
        pos = {n.robot: self.tracks[n.robot].true[-1] for n in self.nodes
               if self.tracks[n.robot].true and n._sub is not None}
        if robot not in pos:
            return set()
        return neighbours_within(pos, self.comm_range)[robot]

    def _start_team_maps(self) -> None:
        """The keyframes are in: the team maps at the poses known now start building off the robots'
        path (in worker processes where cores allow), for the accuracy figures."""
        if self.quality:
            self._team_maps = start_team_maps(self.sim.world, self.params.mapping,
                                              [np.array(tr.true) for tr in self.tracks],
                                              [tr.scans for tr in self.tracks], self.agents, self.eval_workers)

    def _record_phi(self, force: bool = False) -> None:
        """φ between neighbouring robots' team maps, every ``PHI_EVERY_S`` of sim time: a snapshot of
        their cells here, φ computed off the robots' path (:class:`~kimera_multi_py.eval.phi_records.PhiRecords`)."""
        if self.map_report is None or self._phi is None or (
                not force and (self.clock.t < self._next_phi or not self.quality)):
            return  # (without quality scores only the end's φ)
        self._next_phi = self.clock.t + PHI_EVERY_S
        t0 = time.perf_counter()
        live = [n for n in self.nodes if n.maps is not None and n._sub is not None]
        cells = {n.robot: n.maps.team_cells() for n in live if n.maps is not None}
        pairs = [(a.robot, b.robot) for i, a in enumerate(live) for b in live[i + 1:]]
        self._phi.record(self.clock.t, cells, pairs, self.nodes[0].agent.map.template.model.prior_row)
        self._phi_s += time.perf_counter() - t0
        self._add_phi()
        if force and not isinstance(self.viz, NullViz):  # the end: each team map, placed like the team
            T = self.tracks[0].true[0] if self.tracks[0].true else np.eye(4)
            for n in live:
                assert n.maps is not None
                tm = n.maps.team_map
                lv, occ = tm.leaves(), tm.occupied_leaves()
                self.viz.log_voxels(f"team_map/r{n.robot}", self.clock.t, transform_points(T, lv.centers[occ]),
                                    np.argmax(lv.logodds[occ], axis=1))

    def _add_phi(self, finish: bool = False) -> None:
        """The φ records computed so far into the report (``finish``: all, waiting for the rest)."""
        if self._phi is None or self.map_report is None:
            return
        t0 = time.perf_counter()
        for t, value in self._phi.finish() if finish else self._phi.done():
            self.map_report.record_phi(value)
            self.map_report.rounds += 1
            self.viz.log_scalar("map_consensus/phi", t, value["phi"])
        self._phi_s += time.perf_counter() - t0

    def _epochs(self) -> int:
        if self.server is not None:
            return self.server.server.stats.solves
        return max((n.pgo.stats.epochs for n in self.nodes if n.pgo is not None), default=0)

    async def _links_until(self, t: float, nodes: list[AgentNode | ServerNode], buses: list[Bus]) -> None:
        """Under a link budget: let the simulated clock run to ``t`` through every transfer that ends
        before it, the team answering each delivery at its time (a no-op without a budget)."""
        while (nxt := self.links.next_delivery()) is not None and nxt <= t:
            self.clock.t = max(self.clock.t, nxt)
            self._show_partitions(buses)
            await self._settle(nodes, buses)

    async def _settle(self, nodes: list[AgentNode | ServerNode], buses: list[Bus]) -> bool:
        """Run the nodes until the team is quiet: no message queued or in flight, no timer due.

        Over loopback a PGO round still waiting then can never get its status, so its wait
        ends (the deterministic equivalent of a timeout). Returns whether anything happened.
        """
        net = getattr(buses[0], "network", None)
        wall = self.clock.now if net is not None else time.monotonic
        progressed = False
        while True:
            handled = self.links.pump()
            for node in nodes:
                handled += await node.drain()
            for node in nodes:
                handled += await node.tick(wall())
            if handled:
                progressed = True
                continue
            await asyncio.sleep(0)
            if net is not None and net.in_flight:
                net.step()  # the next delayed deliveries, on the network's event time (no wall time)
                continue
            if any(n._sub is not None and n._sub.pending() for n in nodes):
                continue
            blocked = [n for n in nodes if n.blocked()]
            if not blocked:
                self.links.end_wait()
                return progressed
            if net is None:  # Zenoh: wait for messages or the round timeout
                await asyncio.sleep(0.001)
                continue
            if self.links.round_waits(self.clock.t, blocked):
                return progressed  # its messages are on the links: time passes, the streams go on
            self.links.end_wait()
            for node in blocked:
                await node.tick(wall(), force=True)
            progressed = True

    def _log_team(self, stamp: float | None = None) -> None:
        if not isinstance(self.viz, NullViz):
            log_team(self.viz, self.agents, self.tracks[0].true[0] if self.tracks[0].true else np.eye(4),
                     stamp if stamp is not None else self.sim.duration)

    def _evaluate(self, wall_s: float) -> Results:
        truth = [np.array(tr.true) for tr in self.tracks]
        team_mode = bool(self.outcomes)
        est = [o.poses for o in self.outcomes] if team_mode else [np.array(tr.est) for tr in self.tracks]
        robots, team, T_world_team = trajectory_results(truth, est, anchored=not team_mode,
                                                        own_frame=excluded_robots(self.outcomes))
        extra: dict[str, object] = {"rays": self.rays, "rays_per_s": self.rays / wall_s if wall_s > 0 else 0.0,
                                    "phi_records_s": self._phi_s}
        if team_mode:
            extra.update(team_results(self.sim.world, truth, self.outcomes, T_world_team,
                                      self.params.team_object_sightings))
            extra["pgo_runs"] = self._epochs()
            extra["memory"] = {str(n.robot): n.memory() for n in self.nodes}
            if self.server is not None and self.server.server.frames is not None:
                # the server's last frame screen: per robot, what its frame rests on and the evidence
                extra["server_frames"] = {str(r): rep for r, rep in self.server.server.frames.report.items()}
            if self.quality:
                extra.update(accuracy_results(self.sim.world, self.params.mapping, truth,
                                              [tr.scans for tr in self.tracks], self.agents, self.outcomes,
                                              T_world_team, excluded_robots(self.outcomes), self._team_maps))
            extra["transport"] = self.transport
            extra["link_budget"] = self.links.results()
            team_maps = None
            if self.map_report is not None:
                extra["map_consensus"], team_maps = self._map_results(T_world_team)
            if self.quality:
                graphs: dict[str, Any] = {}
                extra["scene_graph"] = scene_graph_results(self.sim.world, self.outcomes, T_world_team, self.out_dir,
                                                           team_maps, self._reference_map(), self.scene_graph_params,
                                                           graphs)
                if getattr(self.sim, "humans", None) is not None:  # recorded data holds no people's truth
                    extra["people"] = people_results(self.sim, truth, self.outcomes, T_world_team,
                                                     team_frame_robots(self.outcomes), graphs.get("team"),
                                                     graphs.get("room_match"))
        if self._team_maps is not None:
            self._team_maps.close()
        return Results(scenario=self.cfg.name, mode=self.mode, seed=self.sim.seed, robots=robots, team=team,
                       sim_seconds=max(self.sim.duration, self.clock.t), wall_s=wall_s, extra=extra)

    def _reference_map(self) -> Any:
        """The reference team map: the centralised fusion of the evidence of every robot in the
        team frame (:func:`~kimera_multi_py.eval.team.team_frame_robots`; a robot kept out of it
        has its poses in its own frame: its evidence has no place in the team's map)."""
        if not self.nodes:
            return None
        if self._reference is None:
            robots = team_frame_robots(self.outcomes) if self.outcomes else [n.robot for n in self.nodes]
            self._reference = centralised_team_map({n.robot: n.agent.map for n in self.nodes}, robots)
        return self._reference

    def _map_results(self, T_world_team: np.ndarray) -> tuple[dict[str, Any], dict[int, Any]]:
        """``results.json["map_consensus"]`` and each robot's team map (:func:`.sim_results.map_consensus_results`)."""
        assert self.map_report is not None
        return map_consensus_results(self.nodes, self._reference_map(), self.map_mode, self.map_report, T_world_team,
                                     self.sim.world if self.quality else None, self.comm_range, self.out_dir)

    def _write_results(self, results: Results) -> None:
        if self.out_dir is None:
            return
        write_run(self.out_dir, self.tracks, self.outcomes, self.nodes, self.agents, results)
        self.resolved_config().write(self.out_dir)
