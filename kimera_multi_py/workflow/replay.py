"""Replay: a team on recorded data (bags or recorded folders) in one process (docs/bags.md).

:func:`replay` runs exactly the nodes ``kimera-multi sim`` runs (:class:`SimRunner`'s loop,
over loopback, on the recorded stamps as the clock) and writes the same run folder. The
sources stand in for the simulator through :class:`RecordedTeam`. Ground truth is optional:
a bag's ground-truth topic, a recorded folder's ``ground_truth/``, or TUM files; with it the run
is scored by the simulator's evaluator. When the data were simulated (a bag written by
``kimera-multi record`` names its scenario), maps and objects are scored against that world too.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.eval.results import Results
from kimera_multi_py.io.bag.outputs import RobotOutput, write_outputs_bag
from kimera_multi_py.io.bag.reader import BagSource
from kimera_multi_py.io.sources import KeyframeSource
from kimera_multi_py.sim.scenario import ScenarioConfig, SpaceConfig
from kimera_multi_py.sim.sensors import Scan
from kimera_multi_py.sim.simulation import Keyframe, Simulation
from kimera_multi_py.team.build import params_for
from kimera_multi_py.team.config import KimeraConfig
from kimera_multi_py.team.evaluate import recorded_scores
from kimera_multi_py.team.recorded import open_sources, recorded_world, source_stamps, source_truth
from kimera_multi_py.workflow.simulate import SimRunner

MODES = ("distributed", "centralized", "odometry")


@dataclass
class _RecordedScan(Scan):
    """A recorded scan: its end points exactly as the source gave them."""

    stored: np.ndarray | None = None

    def points(self) -> np.ndarray:
        assert self.stored is not None
        return self.stored


def _scan(kf: KeyframeInput) -> _RecordedScan:
    pts = np.asarray(kf.points, dtype=np.float64)
    rng = np.linalg.norm(pts, axis=1)
    directions = np.divide(pts, rng[:, None], out=np.tile([1.0, 0.0, 0.0], (len(pts), 1)), where=rng[:, None] > 0)
    return _RecordedScan(directions, np.where(kf.hit, rng, np.inf), np.asarray(kf.labels), float(kf.max_range), pts)


class RecordedTeam:
    """The team's recorded keyframes in the simulator's shape (what :class:`SimRunner` consumes).

    Stamps are shifted so the team's first keyframe is at 0 s. ``truth[r]`` is robot r's true
    T_world_keyframe per keyframe (None: unknown; identity then stands in and nothing is scored).
    """

    def __init__(self, sources: Sequence[KeyframeSource], stamps: Sequence[np.ndarray],
                 truth: Sequence[np.ndarray | None], seed: int = 0, world: Any = None) -> None:
        self.sources, self.truth, self.seed, self.world = list(sources), list(truth), seed, world
        self.origin = min((float(s[0]) for s in stamps if len(s)), default=0.0)
        self._end = 0.0  # the last stamp streamed

    @property
    def num_robots(self) -> int:
        return len(self.sources)

    @property
    def num_keyframes(self) -> int:
        return sum(s.num_keyframes for s in self.sources)

    @property
    def duration(self) -> float:
        return self._end

    @property
    def has_truth(self) -> bool:
        return all(t is not None for t in self.truth)

    def keyframes(self, robot: int) -> Iterator[Keyframe]:
        truth = self.truth[robot]
        for kf in self.sources[robot]:
            scan = _scan(kf)
            pose = truth[kf.index] if truth is not None else np.eye(4)
            self._end = max(self._end, kf.stamp - self.origin)
            yield Keyframe(robot, kf.index, kf.stamp - self.origin, kf.odometry, scan, pose, scan)

    def stream(self) -> Iterator[Keyframe]:
        return heapq.merge(*(self.keyframes(r) for r in range(self.num_robots)), key=lambda k: (k.stamp, k.robot))


class ReplayRunner(SimRunner):
    """:class:`SimRunner` over recorded sources; scoring what the ground truth allows."""

    def __init__(self, team: RecordedTeam, cfg: ScenarioConfig, name: str, **options: Any) -> None:
        quality = team.world is not None and team.has_truth
        super().__init__(cfg, seed=team.seed, simulation=team, quality=quality,  # type: ignore[arg-type]
                         **options)  # (a RecordedTeam has the Simulation's shape SimRunner reads)
        self.team, self.name = team, name

    def _evaluate(self, wall_s: float) -> Results:
        results = super()._evaluate(wall_s) if self.team.world is not None and self.team.has_truth \
            else self._scored(wall_s)
        dropped = {str(r): dict(s.dropped) for r, s in enumerate(self.team.sources) if isinstance(s, BagSource)}
        if dropped:
            results.extra["dropped_points"] = dropped
        return results

    def _scored(self, wall_s: float) -> Results:
        """What the ground truth allows without the world (:func:`recorded_scores`)."""
        truth = [np.array(tr.true) for tr in self.tracks] if self.team.has_truth else None
        est = [o.poses for o in self.outcomes] if self.outcomes else [np.array(tr.est) for tr in self.tracks]
        robots, team, T, scored = recorded_scores(truth, est, self.outcomes)
        extra: dict[str, Any] = {"rays": self.rays, **scored}
        if self.outcomes:
            extra.update(pgo_runs=self._epochs(), transport=self.transport)
            if self.map_report is not None:
                extra["map_consensus"], _ = self._map_results(T)
        return Results(scenario=self.name, mode=self.mode, seed=self.team.seed, robots=robots, team=team,
                       sim_seconds=max(self.team.duration, self.clock.t), wall_s=wall_s, extra=extra)

    def _write_results(self, results: Results) -> None:
        super()._write_results(results)
        if self.out_dir is not None and not self.team.has_truth:
            for i in range(self.team.num_robots):
                (self.out_dir / f"robot{i}_gt.tum").unlink(missing_ok=True)


def replay(specs: Sequence[str], mode: str = "distributed", out_dir: str | Path | None = None,
           truth: Sequence[str | Path] = (), bag_config: str | Path | None = None,
           config: KimeraConfig | None = None, out_bag: str | Path | None = None) -> Results:
    """Run a team on recorded sources (see the module docstring); write ``out_dir`` like ``sim``
    and, with ``out_bag``, the robots' trajectories, team maps and objects as a ROS 2 bag."""
    if out_bag is not None and Path(out_bag).exists():
        raise ConfigError("out-bag", f"{out_bag} exists already")
    if mode not in MODES:
        raise ConfigError("mode", f"unknown mode {mode!r} (available: {', '.join(MODES)})")
    sources = open_sources(specs, bag_config)
    truths = source_truth(sources, truth)
    scenario, seed = recorded_world(sources)
    world = Simulation(scenario, seed).world if scenario is not None else None
    team = RecordedTeam(sources, [source_stamps(s) for s in sources], truths, seed, world)
    name = scenario.name if scenario is not None else Path(specs[0].removeprefix("bag:")).name
    cfg = scenario or ScenarioConfig(name=name, spaces=[SpaceConfig(name="unknown", min=(0.0, 0.0), max=(1.0, 1.0))])
    config = config or KimeraConfig.defaults()
    runner = ReplayRunner(team, cfg, name, mode=mode, out_dir=out_dir, params=params_for(sources[0], config),
                          config=config)
    results = runner.run()
    if out_bag is not None:
        write_outputs_bag(out_bag, robot_outputs(runner))
    return results


def robot_outputs(runner: SimRunner) -> list[RobotOutput]:
    """Each robot's estimate, team map (its own map without map consensus) and objects after a run."""
    out = []
    for i, tr in enumerate(runner.tracks):
        outcome = runner.outcomes[i] if runner.outcomes else None
        node = runner.nodes[i] if runner.nodes else None
        tree = node.maps.team_map if node is not None and node.maps is not None else \
            outcome.octree if outcome is not None else None
        cells, classes, size = np.zeros((0, 3)), np.zeros(0, dtype=int), 0.0
        if tree is not None:
            leaves, occ = tree.leaves(), tree.occupied_leaves()
            cells, classes, size = leaves.centers[occ], np.argmax(leaves.logodds[occ], axis=1), tree.resolution
        objects = [] if outcome is None else outcome.team_objects if outcome.team_objects is not None \
            else outcome.objects
        poses = outcome.poses if outcome is not None else np.array(tr.est).reshape(-1, 4, 4)
        out.append(RobotOutput(i, np.array(tr.stamps), poses, cells, classes, float(size), list(objects)))
    return out


__all__ = ["RecordedTeam", "ReplayRunner", "open_sources", "replay"]
