"""SimRunner: runs a team through a scenario in one process and evaluates it against truth.

``run()`` reads as its stages: spawn the per-robot estimators, stream every keyframe through
them, evaluate against ground truth, write the outputs. Modes:

* ``odometry`` -- dead reckoning: each robot chains its noisy keyframe odometry from identity.
  For the team figure each robot's odometry frame is anchored at its true start pose (the
  frames are otherwise unknown without inter-robot loop closures), then one SE(3) alignment
  over all robots is applied.
* ``distributed`` -- one :class:`Agent` per robot, each wrapped in an :class:`AgentNode` on its
  own bus (in-process loopback, or one Zenoh session per robot): maps, objects, inter-robot
  loop closures (descriptors, queries, verification, PCM) and distributed PGO every
  ``pgo_period`` seconds of simulated time and at the end. Estimates end in the team frame
  (robot 0's), which one SE(3) alignment places in the world for evaluation.
* ``centralized`` -- the same agents and nodes plus a :class:`ServerNode` (id N) on its own
  bus: agents stream keyframe odometry and their accepted loop closures; the server runs gtsam
  GNC on the joint graph on the same schedule and publishes corrected poses back.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kimera_multi_py.agent.agent import Agent, AgentParams, KeyframeInput
from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.agent.team_graph import joint_graph
from kimera_multi_py.comms.bus import Bus
from kimera_multi_py.consensus.pgo import PgoAgent, PgoParams
from kimera_multi_py.consensus.runner import run_team
from kimera_multi_py.consensus.server_node import Server, ServerNode
from kimera_multi_py.consensus.workflow import open_buses
from kimera_multi_py.errors import ConfigError
from kimera_multi_py.eval.metrics import align_se3, ate_rmse
from kimera_multi_py.eval.results import Results, RobotResult
from kimera_multi_py.eval.slam import map_quality, merge_objects, object_quality, score_closures, world_boxes
from kimera_multi_py.geometry import transform_points
from kimera_multi_py.io.g2o import write_g2o
from kimera_multi_py.io.pose_graph import split_key
from kimera_multi_py.io.tum import write_tum
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.simulation import Keyframe, Simulation
from kimera_multi_py.viz.rerun_viz import NullViz, Viz

MODES = ("odometry", "distributed", "centralized")
TRANSPORTS = ("loopback", "zenoh")
Progress = Callable[[int, int], None]


@dataclass
class _Track:
    """One robot's estimated (own odometry frame) and true (world) keyframe poses."""

    stamps: list[float] = field(default_factory=list)
    est: list[np.ndarray] = field(default_factory=list)
    true: list[np.ndarray] = field(default_factory=list)

    def add(self, kf: Keyframe) -> np.ndarray:
        pose = kf.odometry.copy() if not self.est else self.est[-1] @ kf.odometry
        self.stamps.append(kf.stamp)
        self.est.append(pose)
        self.true.append(kf.true_pose)
        return pose


def keyframe_input(kf: Keyframe) -> KeyframeInput:
    """What the agent may see of a simulated keyframe (no ground truth)."""
    return KeyframeInput(kf.index, kf.stamp, kf.odometry, kf.scan.points(), kf.scan.labels, kf.scan.hit,
                         kf.scan.max_range)


class SimRunner:
    """Runs one scenario for one seed and mode; returns :class:`Results`."""

    def __init__(self, cfg: ScenarioConfig, seed: int | None = None, mode: str = "odometry",
                 out_dir: str | Path | None = None, viz: Viz | None = None,
                 on_progress: Progress | None = None, transport: str = "loopback",
                 pgo_period: float = 60.0, params: AgentParams | None = None,
                 pgo_params: PgoParams | None = None) -> None:
        if mode not in MODES:
            raise ConfigError("mode", f"unknown mode {mode!r} (available: {', '.join(MODES)})")
        if transport not in TRANSPORTS:
            raise ConfigError("transport", f"unknown transport {transport!r} (available: {', '.join(TRANSPORTS)})")
        self.cfg = cfg
        self.mode = mode
        self.transport = transport
        self.pgo_period = pgo_period
        self.sim = Simulation(cfg, seed)
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.viz: Viz = viz or NullViz()
        self.on_progress = on_progress
        o = cfg.odometry
        odom_sigmas = (max(np.deg2rad(o.rot_sigma_deg), 1e-4), max(o.trans_sigma, 1e-3))
        self.params = params or AgentParams(odom_sigmas=odom_sigmas, keyframe_distance=cfg.keyframes.distance)
        self.pgo_params = pgo_params or PgoParams(robust=True, max_rounds=300)
        self.tracks: list[_Track] = []
        self.agents: list[Agent] = []
        self.bytes: dict[str, object] = {}
        self.refused: dict[int, dict[str, int]] = {}
        self.pgo_runs = 0
        self.rays = 0

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
        results = self._evaluate(time.perf_counter() - t0)
        self._write_results(results)
        return results

    def _spawn_agents(self) -> None:
        self.tracks = [_Track() for _ in range(self.sim.num_robots)]
        team = tuple(range(self.sim.num_robots))
        if self.mode == "centralized":
            from dataclasses import replace

            self.params = replace(self.params, server=len(team))
        if self.mode != "odometry":
            self.agents = [Agent(r, team, self.params) for r in team]
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
        ids = robots + ([len(robots)] if self.mode == "centralized" else [])
        async with open_buses(ids, self.transport, team="sim", seed=self.sim.seed) as buses:
            agent_nodes = [AgentNode(a, b) for a, b in zip(self.agents, buses, strict=False)]
            nodes: list[AgentNode | ServerNode] = list(agent_nodes)
            if self.mode == "centralized":
                self.server = ServerNode(Server(len(robots), tuple(robots), self.params.closure_sigmas,
                                                self.params.odom_sigmas), buses[-1])
                nodes.append(self.server)
            for node in nodes:
                await node.start()
            next_pgo = self.pgo_period
            for done, kf in enumerate(self.sim.stream(), 1):
                node = agent_nodes[kf.robot]
                await node.process_keyframe(keyframe_input(kf))
                await _drain(nodes)
                self.tracks[kf.robot].add(kf)
                self._step(done, kf, node.agent.poses[-1])
                if kf.stamp >= next_pgo:
                    await self._optimise(buses, nodes)
                    self._log_team(kf.stamp)
                    next_pgo += self.pgo_period
            await _drain(nodes)
            await self._optimise(buses, nodes)
            self._log_team()
            per_robot: dict[str, int] = {}
            per_topic: dict[str, int] = {}
            for b in buses:
                snap = b.counters.snapshot()["sent"]
                per_robot[str(b.robot)] = int(sum(v["bytes"] for v in snap.values()))
                for topic, v in snap.items():
                    per_topic[topic] = per_topic.get(topic, 0) + int(v["bytes"])
            self.bytes = {"per_robot": per_robot, "per_topic": per_topic, "total": sum(per_robot.values())}
            self.refused = {n.robot: dict(n.errors) for n in nodes if isinstance(n, AgentNode)}
            for node in nodes:
                await node.close()
        self.viz.close()

    async def _optimise(self, buses: list[Bus], nodes: list[AgentNode | ServerNode]) -> None:
        """Distributed PGO over the agents' graphs, or the server's GNC; the agents adopt the result."""
        if self.mode == "centralized":
            await self.server.optimise()
            await _drain(nodes)
        else:
            pgo = [PgoAgent(a.local_graph(), self.pgo_params) for a in self.agents]
            await run_team(pgo, buses, self.pgo_params.max_rounds)
            for agent, p in zip(self.agents, pgo, strict=True):
                agent.apply_poses(p.final_poses())
            self.pgo = pgo
        self.pgo_runs += 1

    def _log_team(self, stamp: float | None = None) -> None:
        """Send the team's current estimate to the visualiser, placed in the world by the true start
        of robot 0 (the team frame is robot 0's odometry frame)."""
        if isinstance(self.viz, NullViz):
            return
        T = self.tracks[0].true[0] if self.tracks[0].true else np.eye(4)
        trajs = [transform_points(T, np.array(a.poses)[:, :3, 3]) if a.poses else np.zeros((0, 3))
                 for a in self.agents]
        closures = []
        for a in self.agents:
            for peer, group in a.closures.items():
                for c in group:
                    if c.own_kf < len(a.poses) and c.peer_kf < len(self.agents[peer].poses):
                        closures.append((transform_points(T, a.poses[c.own_kf][None, :3, 3])[0],
                                         transform_points(T, self.agents[peer].poses[c.peer_kf][None, :3, 3])[0],
                                         c.accepted))
        voxels = []
        for a in self.agents:
            lv, occ = a.map.octree.leaves(), a.map.octree.occupied_leaves()
            voxels.append((transform_points(T, lv.centers[occ]), np.argmax(lv.logodds[occ], axis=1)))
        lms = [lm for a in self.agents for lm in a.objects.confirmed()]
        objects = (transform_points(T, np.array([lm.position for lm in lms]).reshape(-1, 3)),
                   np.array([lm.box()[1] for lm in lms]).reshape(-1, 3), np.array([lm.label for lm in lms], dtype=int))
        self.viz.log_team(stamp if stamp is not None else self.sim.duration, trajs, closures, voxels, objects)

    def _evaluate(self, wall_s: float) -> Results:
        robots, team_est, team_true = [], [], []
        for i, tr in enumerate(self.tracks):
            true = np.array(tr.true)
            est = np.array(self.agents[i].poses) if self.agents else np.array(tr.est)
            length = float(np.linalg.norm(np.diff(true[:, :3, 3], axis=0), axis=1).sum())
            robots.append(RobotResult(i, len(true), length, ate_rmse(est[:, :3, 3], true[:, :3, 3])))
            # odometry: each robot's own frame anchored at its true start; otherwise the team frame
            team_est.append((true[0] @ est if not self.agents else est)[:, :3, 3])
            team_true.append(true[:, :3, 3])
        est_all, true_all = np.concatenate(team_est), np.concatenate(team_true)
        team = {
            "ate_rmse_m": ate_rmse(est_all, true_all),
            "keyframes": int(sum(r.keyframes for r in robots)),
            "trajectory_length_m": float(sum(r.trajectory_length_m for r in robots)),
            "frames": ("each robot's odometry anchored at its true start pose" if not self.agents
                       else "the team frame (robot 0's), one SE(3) alignment to the world"),
        }
        extra: dict[str, object] = {"rays": self.rays, "rays_per_s": self.rays / wall_s if wall_s > 0 else 0.0}
        if self.agents:
            extra.update(self._evaluate_team(align_se3(est_all, true_all)))
        return Results(scenario=self.cfg.name, mode=self.mode, seed=self.sim.seed, robots=robots, team=team,
                       sim_seconds=self.sim.duration, wall_s=wall_s, extra=extra)

    def _evaluate_team(self, T_world_team: np.ndarray) -> dict[str, object]:
        """Maps, objects, loop closures and traffic of a team run (agents' estimates in the team frame)."""
        world = self.sim.world
        for a in self.agents:
            a.objects.merge_fragments(a.map.octree)
        grid = world.gt_voxel_grid(self.agents[0].map.resolution)
        centers, gt = grid.centers().reshape(-1, 3), grid.labels.reshape(-1)
        maps = {str(a.robot): map_quality(a.map.octree, T_world_team, centers, gt) for a in self.agents}
        lms = [lm for a in self.agents for lm in a.objects.confirmed()
               if lm.num_observations >= self.params.team_object_sightings]
        boxes = [lm.aabb() for lm in lms]
        lo, hi = world_boxes(T_world_team, np.array([b[0] for b in boxes]).reshape(-1, 3),
                             np.array([b[1] for b in boxes]).reshape(-1, 3))
        cls, lo, hi = merge_objects(np.array([lm.label for lm in lms], dtype=int), lo, hi)
        objects = object_quality(cls, (lo + hi) / 2, np.array([o.label for o in world.objects]),
                                 np.array([o.centroid for o in world.objects]))
        objects["landmarks"] = len(lms)
        closures = self._closure_stats()
        return {"map": maps, "objects": objects, "loop_closures": closures, "bytes_sent": self.bytes,
                "pgo_runs": self.pgo_runs, "refused_messages": self.refused,
                "transport": self.transport}

    def _backend_weights(self) -> dict[tuple[int, int, int, int], float]:
        """Final back-end (GNC) weight of each inter-robot edge, keyed ``(a, kf_a, b, kf_b)``."""
        if self.mode == "centralized":
            return dict(self.server.server.stats.weights)
        out: dict[tuple[int, int, int, int], float] = {}
        for a, p in zip(self.agents, getattr(self, "pgo", []), strict=False):
            lg = p.local
            for e in range(len(lg.inter_own)):
                peer_kf = split_key(lg.inter_peer_key[e])[1]
                out[(a.robot, int(lg.inter_own[e]), int(lg.inter_peer[e]), peer_kf)] = float(p.inter_weights[e])
            for e_ in np.flatnonzero(~lg.intra_odometry).tolist():
                out[(a.robot, int(lg.intra_i[e_]), a.robot, int(lg.intra_j[e_]))] = float(p.intra_weights[e_])
        return out

    def _closure_stats(self) -> dict[str, int]:
        """Loop closures through the pipeline, scored against the true poses.

        ``candidates`` were fetched and verified; ``verified`` passed geometry; PCM then kept a
        consistent set and the back end's GNC weights decided the rest (weight < 0.5 = rejected).
        """
        truth = [np.array(tr.true) for tr in self.tracks]
        weights = self._backend_weights()
        rows = []  # (inter, pcm accepted, gnc accepted, true)
        for a in self.agents:
            for peer, group in a.closures.items():
                if not group:
                    continue
                ok = score_closures(np.stack([c.Z for c in group]), truth[a.robot][[c.own_kf for c in group]],
                                    truth[peer][[c.peer_kf for c in group]])
                for c, true in zip(group, ok, strict=True):
                    w = weights.get((a.robot, c.own_kf, peer, c.peer_kf), 0.0)
                    rows.append((peer != a.robot, c.accepted, c.accepted and w >= 0.5, bool(true)))
        r = np.array(rows, dtype=bool).reshape(-1, 4)
        inter, pcm_ok, final, true = r.T
        stats = [a.stats for a in self.agents]
        return {
            "candidates": sum(s.candidates for s in stats),
            "verified": sum(s.verified for s in stats),
            "rejected_verification": sum(s.rejected_verification for s in stats),
            "verified_true_inter": int((inter & true).sum()),
            "verified_false_inter": int((inter & ~true).sum()),
            "rejected_pcm_true_inter": int((inter & ~pcm_ok & true).sum()),
            "rejected_pcm_false_inter": int((inter & ~pcm_ok & ~true).sum()),
            "rejected_gnc_true_inter": int((inter & pcm_ok & ~final & true).sum()),
            "rejected_gnc_false_inter": int((inter & pcm_ok & ~final & ~true).sum()),
            "accepted_inter": int((inter & final).sum()),
            "true_accepted_inter": int((inter & final & true).sum()),
            "false_accepted_inter": int((inter & final & ~true).sum()),
            "accepted_intra": int((~inter & final).sum()),
            "false_accepted_intra": int((~inter & final & ~true).sum()),
        }

    def _write_results(self, results: Results) -> None:
        if self.out_dir is None:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for i, tr in enumerate(self.tracks):
            est = np.array(self.agents[i].poses) if self.agents else np.array(tr.est)
            write_tum(self.out_dir / f"robot{i}_est.tum", np.array(tr.stamps), est)
            write_tum(self.out_dir / f"robot{i}_gt.tum", np.array(tr.stamps), np.array(tr.true))
        if self.agents:  # the team's joint graph, for `kimera-multi pgo` and offline study
            graph, inter = joint_graph(self.agents)
            write_g2o(self.out_dir / "team_graph.g2o", graph)
            truth = [np.array(tr.true) for tr in self.tracks]
            Z = np.array([self.agents[a].inter_edges[(ka, b, kb)][0] for a, ka, b, kb in inter]).reshape(-1, 4, 4)
            ok = score_closures(Z, np.array([truth[a][ka] for a, ka, _, _ in inter]).reshape(-1, 4, 4),
                                np.array([truth[b][kb] for _, _, b, kb in inter]).reshape(-1, 4, 4))
            (self.out_dir / "team_graph_truth.json").write_text(json.dumps(
                {"inter_robot_edges": [list(e) for e in inter], "true": ok.tolist(),
                 "note": "inter-robot edges follow the odometry and intra-robot edges in team_graph.g2o"}))
        results.write_json(self.out_dir / "results.json")


async def _drain(nodes: list[AgentNode | ServerNode]) -> None:
    """Let every node handle its queued messages until the team is quiet."""
    while True:
        handled = 0
        for node in nodes:
            handled += await node.drain()
        if not handled:
            await asyncio.sleep(0)
            if not any(n._sub is not None and n._sub.pending() for n in nodes):
                return
