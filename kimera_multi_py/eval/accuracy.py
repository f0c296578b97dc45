"""Metric accuracy of a team run, separated by cause.

* :func:`team_map_quality`: every keyframe of every robot integrated into one semantic octree at
  given world poses, scored against the world's voxel grid. At the final estimated poses it is
  the map the team can have; at the true poses (same scans, same sensor model) the ceiling.
* :func:`closure_errors`: how far accepted loop closures are from the truth (median
  translation and rotation), inter- and intra-robot separately.
* :func:`accuracy_results`: the figures above plus the ATE of dead reckoning, of the
  registration-refined odometry and of the full system, and the front end's cost per keyframe.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.outputs import RobotOutcome
from kimera_multi_py.core.geometry import relative, so3_log, transform_points
from kimera_multi_py.eval.metrics import align_se3, occupancy_f1, semantic_miou
from kimera_multi_py.eval.team import team_frame_estimates
from kimera_multi_py.mapping.config import MappingConfig, get_octree

_SCAN_COUNTS = ("registered", "degenerate", "gated", "failed")
_FLOOR_COUNTS = ("corrected", "missing", "gated")  # of the floor and of the heading reference
PARALLEL_MIN_RAYS = 500_000  # rays per team map below which worker processes cost more than they save
WORKER_NICENESS = 5  # added to the run's niceness for the processes that build the team maps


@dataclass
class ScanRecord:
    """One keyframe's scan as the agent saw it (sensor frame; misses at ``max_range``)."""

    points: np.ndarray  # (n, 3)
    labels: np.ndarray  # (n,)
    max_range: float


def team_map_quality(mapping: MappingConfig, scans: Sequence[Sequence[ScanRecord]],
                     poses: Sequence[np.ndarray], centers: np.ndarray, gt_labels: np.ndarray) -> dict[str, float]:
    """Occupancy F1 and semantic mIoU of all robots' scans fused at world ``poses`` (per robot
    ``(n, 4, 4)``), with the agents' octree parameters, on the ground-truth grid
    ``centers``/``gt_labels``."""
    octree = get_octree(mapping.octree)
    for robot_scans, robot_poses in zip(scans, poses, strict=True):
        if len(robot_scans) != len(robot_poses):
            raise ValueError(f"team map: {len(robot_scans)} scans for {len(robot_poses)} poses")
        for s, T in zip(robot_scans, robot_poses, strict=True):
            octree.insert_scan(T[:3, 3], transform_points(T, s.points), s.labels, s.max_range)
    pred = octree.class_at(centers)
    return {"occupancy_f1": occupancy_f1(pred, gt_labels), "semantic_miou": semantic_miou(pred, gt_labels)}


class TeamMaps:
    """The team maps the accuracy figures score (:func:`team_map_quality`), each started as soon as
    its poses are known. ``workers`` processes build them (default: one per core this process may
    use beyond its own, when the maps are big enough to pay for starting processes; 0: none), so
    they stay off the core of the caller; the others are built in :meth:`result`. The figures are
    the same wherever a map is built."""

    def __init__(self, mapping: MappingConfig, scans: Sequence[Sequence[ScanRecord]], centers: np.ndarray,
                 gt_labels: np.ndarray, workers: int | None = None) -> None:
        self.mapping, self.centers, self.gt_labels = mapping, centers, gt_labels
        self.scans = [list(s) for s in scans]  # a worker reads them later: the caller's lists may grow
        if workers is None:
            rays = sum(len(s.points) for robot in scans for s in robot)
            workers = len(os.sched_getaffinity(0)) - 1 if rays >= PARALLEL_MIN_RAYS else 0
        # the workers yield to the robots (a lower priority), whatever else the machine runs
        self._pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=os.nice,
                                         initargs=(WORKER_NICENESS,)) if workers > 0 else None
        self._jobs: dict[str, Future[dict[str, float]] | list[np.ndarray]] = {}

    def start(self, name: str, poses: Sequence[np.ndarray], here: bool = False) -> None:
        """The map of all scans at world ``poses`` (per robot ``(n, 4, 4)``): in a worker if there is
        one and not ``here``, else in :meth:`result`."""
        poses = [np.array(p) for p in poses]
        self._jobs[name] = poses if self._pool is None or here else self._pool.submit(
            team_map_quality, self.mapping, self.scans, poses, self.centers, self.gt_labels)

    def result(self) -> dict[str, dict[str, float]]:
        """Every started map's figures, by name in the order started (waits for the workers)."""
        out = {name: team_map_quality(self.mapping, self.scans, job, self.centers, self.gt_labels)
               for name, job in self._jobs.items() if not isinstance(job, Future)}
        out.update({name: job.result() for name, job in self._jobs.items() if isinstance(job, Future)})
        self.close()
        return {name: out[name] for name in self._jobs}

    def close(self) -> None:
        """Stop the workers (a map not finished yet is dropped)."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


def truth_grid(world: Any, mapping: MappingConfig) -> tuple[np.ndarray, np.ndarray]:
    """The world's ground-truth voxel grid at the agents' resolution: cell centres and labels."""
    grid = world.gt_voxel_grid(mapping.octree.resolution)
    return grid.centers().reshape(-1, 3), grid.labels.reshape(-1)


def odometry_estimates(agents: Sequence[Agent]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each robot's dead reckoning and registration-refined odometry (dead reckoning without it)."""
    dr = [np.array(a.dead_reckoning) for a in agents]
    reg = [np.array(a.scan_odometry.poses) if a.scan_odometry is not None else np.array(a.dead_reckoning)
           for a in agents]
    return dr, reg


def start_team_maps(world: Any, mapping: MappingConfig, truth: Sequence[np.ndarray],
                    scans: Sequence[Sequence[ScanRecord]], agents: Sequence[Agent],
                    workers: int | None = None) -> TeamMaps:
    """The team maps whose poses are known once the keyframes are in (true poses, dead reckoning,
    registration odometry), started (:class:`TeamMaps`); :func:`accuracy_results` adds the estimate's."""
    maps = TeamMaps(mapping, scans, *truth_grid(world, mapping), workers=workers)
    dr, reg = odometry_estimates(agents)
    maps.start("true_poses", list(truth))
    maps.start("dead_reckoning", _world(truth, dr, anchored=True)[0])
    maps.start("registration_odometry", _world(truth, reg, anchored=True)[0])
    return maps


def closure_errors(truth: Sequence[np.ndarray], outcomes: Sequence[RobotOutcome]) -> dict[str, dict[str, float]]:
    """Median error of the closures the back end kept (PCM-accepted, weight >= 0.5), against
    the true relative poses: ``{"inter"|"intra": {count, median_trans_m, median_rot_deg}}``."""
    rows: dict[str, list[tuple[float, float]]] = {"inter": [], "intra": []}
    for o in outcomes:
        for c in o.closures:
            if not c.accepted or (c.weight if c.weight is not None else 0.0) < 0.5:
                continue
            E = relative(c.Z, relative(truth[o.robot][c.own_kf], truth[c.peer][c.peer_kf]))
            rows["intra" if c.peer == o.robot else "inter"].append(
                (float(np.linalg.norm(E[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(E[:3, :3]))))))
    out = {}
    for kind, r in rows.items():
        a = np.array(r).reshape(-1, 2)
        out[kind] = {"count": len(a), "median_trans_m": float(np.median(a[:, 0])) if len(a) else float("nan"),
                     "median_rot_deg": float(np.median(a[:, 1])) if len(a) else float("nan")}
    return out


def _world(truth: Sequence[np.ndarray], est: Sequence[np.ndarray], anchored: bool) -> tuple[list[np.ndarray], float]:
    """Estimates placed in the world (anchored at each robot's true start if ``anchored``, then
    one SE(3) alignment over the team) and the team ATE."""
    placed = [t[0] @ e if anchored else e for t, e in zip(truth, est, strict=True)]
    e_all = np.concatenate([p[:, :3, 3] for p in placed])
    t_all = np.concatenate([t[:, :3, 3] for t in truth])
    T = align_se3(e_all, t_all)
    world = [T @ p for p in placed]
    err = np.concatenate([w[:, :3, 3] for w in world]) - t_all
    return world, float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _drift(truth: Sequence[np.ndarray], est: Sequence[np.ndarray]) -> float:
    """Mean over robots of the final position error of an anchored chain / distance travelled."""
    out = []
    for t, e in zip(truth, est, strict=True):
        length = float(np.linalg.norm(np.diff(t[:, :3, 3], axis=0), axis=1).sum())
        end = (t[0] @ e[-1])[:3, 3] - t[-1, :3, 3]
        out.append(float(np.linalg.norm(end)) / length if length > 0 else 0.0)
    return float(np.mean(out))


def accuracy_results(world: Any, mapping: MappingConfig, truth: Sequence[np.ndarray],
                     scans: Sequence[Sequence[ScanRecord]], agents: Sequence[Agent],
                     outcomes: Sequence[RobotOutcome], T_world_team: np.ndarray,
                     own_frame: Collection[int] = (), maps: TeamMaps | None = None) -> dict[str, Any]:
    """``team_map``, ``ate_rmse_m`` per estimate, ``drift``, ``closure_error``, ``scan_odometry``
    and ``front_end_ms_per_keyframe`` (a machine timing) of a team run. Robots in ``own_frame``
    (kept out of the team frame) are placed like dead reckoning (:func:`.team.team_frame_estimates`).
    ``maps``: the team maps :func:`start_team_maps` started for this run (default: started now)."""
    dr, reg = odometry_estimates(agents)
    _, dr_ate = _world(truth, dr, anchored=True)
    _, reg_ate = _world(truth, reg, anchored=True)
    team = team_frame_estimates(truth, [o.poses for o in outcomes], own_frame)
    est_world, est_ate = _world(truth, [T_world_team @ p for p in team], anchored=False)
    if maps is None:
        maps = start_team_maps(world, mapping, truth, scans, agents)
    maps.start("full_system", est_world, here=True)
    quality = maps.result()
    team_map: dict[str, Any] = {**quality.pop("full_system"), **quality}
    stats = [a.scan_odometry.stats for a in agents if a.scan_odometry is not None]
    floors = [f for f in (a.scan_odometry.floor for a in agents if a.scan_odometry is not None) if f is not None]
    headings = [h for h in (a.scan_odometry.heading for a in agents if a.scan_odometry is not None) if h is not None]
    keyframes = max(sum(a.num_keyframes for a in agents), 1)
    return {
        "team_map": team_map,
        "ate_rmse_m": {"dead_reckoning": dr_ate, "registration_odometry": reg_ate, "full_system": est_ate},
        "drift_per_distance": {"dead_reckoning": _drift(truth, dr), "registration_odometry": _drift(truth, reg)},
        "closure_error": closure_errors(truth, outcomes),
        "scan_odometry": {**{k: sum(getattr(s, k) for s in stats) for k in _SCAN_COUNTS},
                          **{f"floor_{k}": sum(getattr(f.stats, k) for f in floors) for k in _FLOOR_COUNTS},
                          **{f"heading_{k}": sum(getattr(h.stats, k) for h in headings) for k in _FLOOR_COUNTS}},
        "front_end_ms_per_keyframe": {
            "total": 1000 * sum(a.front_end_seconds for a in agents) / keyframes,
            "registration": 1000 * sum(s.seconds for s in stats) / keyframes},
    }
