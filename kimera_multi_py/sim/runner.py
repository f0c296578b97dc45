"""SimRunner: runs a team through a scenario in one process and evaluates it against truth.

``run()`` reads as its stages: spawn the per-robot estimators, stream every keyframe through
them, evaluate against ground truth, write the outputs. Modes:

* ``odometry`` -- dead reckoning: each robot chains its noisy keyframe odometry from identity.
  For the team figure each robot's odometry frame is anchored at its true start pose (the
  frames are otherwise unknown without inter-robot loop closures), then one SE(3) alignment
  over all robots is applied.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kimera_multi_py.errors import ConfigError
from kimera_multi_py.eval.metrics import ate_rmse
from kimera_multi_py.eval.results import Results, RobotResult
from kimera_multi_py.io.tum import write_tum
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.simulation import Keyframe, Simulation
from kimera_multi_py.viz.rerun_viz import NullViz, Viz

MODES = ("odometry",)
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


class SimRunner:
    """Runs one scenario for one seed and mode; returns :class:`Results`."""

    def __init__(self, cfg: ScenarioConfig, seed: int | None = None, mode: str = "odometry",
                 out_dir: str | Path | None = None, viz: Viz | None = None,
                 on_progress: Progress | None = None) -> None:
        if mode not in MODES:
            raise ConfigError("mode", f"unknown mode {mode!r} (available: {', '.join(MODES)})")
        self.cfg = cfg
        self.mode = mode
        self.sim = Simulation(cfg, seed)
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.viz: Viz = viz or NullViz()
        self.on_progress = on_progress
        self.tracks: list[_Track] = []
        self.rays = 0

    @property
    def total_keyframes(self) -> int:
        return self.sim.num_keyframes

    def run(self) -> Results:
        t0 = time.perf_counter()
        self._spawn_agents()
        self._run()
        results = self._evaluate(time.perf_counter() - t0)
        self._write_results(results)
        return results

    def _spawn_agents(self) -> None:
        self.tracks = [_Track() for _ in range(self.sim.num_robots)]
        self.viz.log_world(self.sim.world)

    def _run(self) -> None:
        total = self.total_keyframes
        for done, kf in enumerate(self.sim.stream(), 1):
            est = self.tracks[kf.robot].add(kf)
            self.rays += len(kf.scan)
            self.viz.log_keyframe(kf.robot, kf.stamp, est, kf.true_pose, kf.scan.points(), kf.scan.labels)
            if self.on_progress is not None:
                self.on_progress(done, total)
        self.viz.close()

    def _evaluate(self, wall_s: float) -> Results:
        robots, team_est, team_true = [], [], []
        for i, tr in enumerate(self.tracks):
            est, true = np.array(tr.est), np.array(tr.true)
            length = float(np.linalg.norm(np.diff(true[:, :3, 3], axis=0), axis=1).sum())
            robots.append(RobotResult(i, len(tr.est), length, ate_rmse(est[:, :3, 3], true[:, :3, 3])))
            anchored = true[0] @ est  # odometry frame placed at the true start pose
            team_est.append(anchored[:, :3, 3])
            team_true.append(true[:, :3, 3])
        team = {
            "ate_rmse_m": ate_rmse(np.concatenate(team_est), np.concatenate(team_true)),
            "keyframes": int(sum(r.keyframes for r in robots)),
            "trajectory_length_m": float(sum(r.trajectory_length_m for r in robots)),
            "frames": "each robot's odometry anchored at its true start pose",
        }
        return Results(
            scenario=self.cfg.name, mode=self.mode, seed=self.sim.seed, robots=robots, team=team,
            sim_seconds=self.sim.duration, wall_s=wall_s,
            extra={"rays": self.rays, "rays_per_s": self.rays / wall_s if wall_s > 0 else 0.0},
        )

    def _write_results(self, results: Results) -> None:
        if self.out_dir is None:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for i, tr in enumerate(self.tracks):
            write_tum(self.out_dir / f"robot{i}_est.tum", np.array(tr.stamps), np.array(tr.est))
            write_tum(self.out_dir / f"robot{i}_gt.tum", np.array(tr.stamps), np.array(tr.true))
        results.write_json(self.out_dir / "results.json")
