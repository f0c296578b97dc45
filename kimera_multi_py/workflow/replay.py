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
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.core.errors import ConfigError, DatasetError
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.eval.results import Results, RobotResult
from kimera_multi_py.eval.team import alignment_report, closure_stats, traffic_totals, trajectory_results
from kimera_multi_py.io.bag.config import config_for
from kimera_multi_py.io.bag.outputs import RobotOutput, write_outputs_bag
from kimera_multi_py.io.bag.reader import BagSource, bag_robots
from kimera_multi_py.io.bag.tf import PoseSeries
from kimera_multi_py.io.sources import KeyframeSource, RecordedSource, read_ground_truth, read_manifest
from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.sim.scenario import ScenarioConfig, SpaceConfig, load_scenario
from kimera_multi_py.sim.sensors import Scan
from kimera_multi_py.sim.simulation import Keyframe, Simulation
from kimera_multi_py.sim.source import recorded_scenario
from kimera_multi_py.team.build import bag_spec, params_for
from kimera_multi_py.team.config import KimeraConfig
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


def open_sources(specs: Sequence[str], bag_config: str | Path | None = None) -> list[KeyframeSource]:
    """One source per robot: each spec is a robot, unless a single spec names a team (a bag with
    ``/robot{r}`` namespaces, or a recorded folder of several robots)."""
    if not specs:
        raise ConfigError("--source", "give at least one --source")
    sources: list[KeyframeSource] = []
    for spec in specs:
        if spec.startswith("bag:"):
            path, config = bag_spec(spec)
            cfg, _ = config_for(path, config or bag_config)
            robots = bag_robots(path) if len(specs) == 1 and cfg.namespace is None else [None]
            for r in robots:
                # robot r of a team's bag; else this spec's robot (its namespace found by BagSource)
                sources.append(BagSource(path, len(sources) if r is None else r, config=cfg))
        elif Path(spec).is_dir():
            ids = [e["robot"] for e in read_manifest(spec)["robots"]]
            for r in ids if len(specs) == 1 else ids[:1]:
                sources.append(RecordedSource(spec, r))
        else:
            raise ConfigError("--source", f"{spec!r}: expected bag:PATH[:CONFIG] or a recorded folder")
    for i, s in enumerate(sources):  # the team's ids are 0..n-1, in this order
        if s.num_keyframes == 0:
            raise DatasetError(f"{specs[min(i, len(specs) - 1)]}: robot {i} yields no keyframe")
    return sources


def _stamps(source: KeyframeSource) -> np.ndarray:
    """A bag's keyframe stamps (ROS time; the team's first becomes 0 s); a recorded folder's start at 0 s."""
    return source.stamps if isinstance(source, BagSource) else np.zeros(1)


def _truth(sources: Sequence[KeyframeSource], truth_files: Sequence[str | Path]) -> list[np.ndarray | None]:
    """Per robot: the TUM file given for it (interpolated at its keyframes), else what its source holds."""
    if truth_files and len(truth_files) != len(sources):
        raise ConfigError("--truth", f"give one TUM file per robot ({len(sources)}), got {len(truth_files)}")
    out: list[np.ndarray | None] = []
    for i, src in enumerate(sources):
        if truth_files:
            stamps, poses = read_tum(truth_files[i])
            if not isinstance(src, BagSource):
                raise ConfigError("--truth", "TUM ground truth goes with bag sources")
            try:
                out.append(PoseSeries(stamps, poses).at(src.stamps, src.cfg.sync_tolerance) @ src.T_base_keyframe)
            except ValueError as exc:
                raise DatasetError(f"{truth_files[i]}: {exc}") from None
        elif isinstance(src, BagSource):
            out.append(src.ground_truth())
        elif isinstance(src, RecordedSource) and (src.dir / "ground_truth").is_dir():
            out.append(read_ground_truth(src.dir).poses.get(src.robot))
        else:
            out.append(None)
    return out


def _world(sources: Sequence[KeyframeSource]) -> tuple[ScenarioConfig | None, int]:
    """The simulated scenario and seed the data came from, if the first source says so."""
    src = sources[0]
    if isinstance(src, BagSource) and src.cfg.origin and "scenario" in src.cfg.origin:
        path = Path(str(src.cfg.origin["scenario"]))
        if path.is_file():
            return load_scenario(path, robots=len(sources)), int(src.cfg.origin.get("seed", 0))
    if isinstance(src, RecordedSource) and (src.dir / "ground_truth").is_dir():
        gt = read_ground_truth(src.dir)
        cfg = recorded_scenario(gt)
        return cfg, int(gt.info.get("seed", 0))
    return None, 0


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
        """What the ground truth allows without the world: trajectories and closures, or nothing."""
        truth = [np.array(tr.true) for tr in self.tracks]
        est = [o.poses for o in self.outcomes] if self.outcomes else [np.array(tr.est) for tr in self.tracks]
        extra: dict[str, Any] = {"rays": self.rays, "ground_truth": self.team.has_truth}
        if self.team.has_truth:
            robots, team, T = trajectory_results(truth, est, anchored=not self.outcomes)
        else:
            robots = [RobotResult(i, len(e), float(np.linalg.norm(np.diff(e[:, :3, 3], axis=0), axis=1).sum()),
                                  math.nan) for i, e in enumerate(est)]
            team = {"ate_rmse_m": math.nan, "keyframes": sum(r.keyframes for r in robots),
                    "trajectory_length_m": sum(r.trajectory_length_m for r in robots), "frames": "no ground truth"}
            T = np.eye(4)
        if self.outcomes:
            extra["loop_closures"] = (closure_stats(truth, self.outcomes) if self.team.has_truth
                                      else {"accepted_inter": sum(c.accepted and c.peer != o.robot
                                                                  for o in self.outcomes for c in o.closures)})
            extra.update(alignment=alignment_report(self.outcomes), bytes_sent=traffic_totals(self.outcomes),
                         pgo_runs=self._epochs(), transport=self.transport)
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
    truths = _truth(sources, truth)
    scenario, seed = _world(sources)
    world = Simulation(scenario, seed).world if scenario is not None else None
    team = RecordedTeam(sources, [_stamps(s) for s in sources], truths, seed, world)
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
