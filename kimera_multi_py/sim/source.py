"""The simulator as a keyframe source: a robot's stream regenerated from a scenario and seed.

The simulator draws each robot's noise from its own generator seeded by ``(seed, robot)``, so
the stream does not depend on the team size. Starting at ``k`` replays keyframes ``0..k-1``
(their ray casts decide how much noise each draws) unless a :meth:`SimSource.state` saved
earlier is passed as ``resume``: then no skipped keyframe is simulated. :func:`write_recording`
records a simulated team into the folder format of :mod:`kimera_multi_py.io.recording`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from kimera_multi_py.core.config import validate
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.io.recording import MANIFEST, GroundTruth, RecordingWriter
from kimera_multi_py.sim.scenario import ScenarioConfig, with_team_size
from kimera_multi_py.sim.simulation import Keyframe, Simulation


def keyframe_input(kf: Keyframe) -> KeyframeInput:
    """What the agent may see of a simulated keyframe (no ground truth)."""
    return KeyframeInput(kf.index, kf.stamp, kf.odometry, kf.scan.points(), kf.scan.labels, kf.scan.hit,
                         kf.scan.max_range)


class SimSource:
    """Robot ``robot``'s simulated keyframes from ``start`` on (an iterator).

    ``resume`` is a :meth:`state` taken when ``start`` was the next keyframe; with it the
    source continues at once (the generator state is restored instead of replaying the
    skipped keyframes' ray casts).
    """

    def __init__(self, cfg: ScenarioConfig, seed: int | None, robot: int, start: int = 0,
                 resume: dict[str, Any] | None = None, simulation: Simulation | None = None) -> None:
        if not 0 <= robot < len(cfg.robots):
            raise ConfigError("robot", f"robot {robot} is not in the scenario's team of {len(cfg.robots)}")
        self.sim = simulation or Simulation(cfg, seed)
        self.robot = int(robot)
        self.start = int(start)
        if not 0 <= self.start <= self.num_keyframes:
            raise ConfigError("start", f"keyframe {start} is outside robot {robot}'s 0..{self.num_keyframes}")
        self._rng = self.sim.rng(self.robot)
        self._next = 0
        if resume is not None:
            self._resume(resume)
        while self._next < self.start:  # replay: the noise drawn depends on each scan's hits
            self._simulate(self._next)

    @property
    def num_keyframes(self) -> int:
        return len(self.sim.plans[self.robot].stamps)

    @property
    def next_index(self) -> int:
        return self._next

    def state(self) -> dict[str, Any]:
        """Plain data to resume from the next keyframe (store it in a checkpoint's ``extra``)."""
        return {"robot": self.robot, "seed": self.sim.seed, "next": self._next,
                "rng": self._rng.bit_generator.state}

    def _resume(self, resume: dict[str, Any]) -> None:
        if not isinstance(resume, dict) or {"robot", "seed", "next", "rng"} - resume.keys():
            raise ConfigError("resume", "not a SimSource state")
        if (resume["robot"], resume["seed"], resume["next"]) != (self.robot, self.sim.seed, self.start):
            got = f"robot {resume['robot']}, seed {resume['seed']} at keyframe {resume['next']}"
            raise ConfigError("resume", f"state of {got}, not robot {self.robot}, seed {self.sim.seed} at {self.start}")
        try:
            self._rng.bit_generator.state = resume["rng"]
        except (TypeError, ValueError, KeyError) as exc:
            raise ConfigError("resume", f"bad generator state: {exc}") from None
        self._next = self.start

    def _simulate(self, k: int) -> Keyframe:
        kf = self.sim.keyframe(self.robot, k, self._rng)
        self._next = k + 1
        return kf

    def keyframes(self) -> Iterator[Keyframe]:
        """The simulator's keyframes (with ground truth) from the next one on; for evaluators."""
        while self._next < self.num_keyframes:
            yield self._simulate(self._next)

    def __iter__(self) -> Iterator[KeyframeInput]:
        return self

    def __next__(self) -> KeyframeInput:
        if self._next >= self.num_keyframes:
            raise StopIteration
        return keyframe_input(self._simulate(self._next))


def write_recording(out_dir: str | Path, cfg: ScenarioConfig, robots: int | None = None, seed: int | None = None,
                    scenario_path: str | Path | None = None, chunk_size: int = 32) -> Path:
    """Simulate a team of ``robots`` (default: the scenario's) for ``seed`` and record it; return the manifest.

    Each robot's stream is the same as :class:`SimSource`'s (it does not depend on the team size).
    """
    if robots is not None and robots != len(cfg.robots):
        cfg = with_team_size(cfg, robots)
    sim = Simulation(cfg, seed)
    info = {"scenario_name": cfg.name, "scenario_path": None if scenario_path is None else str(scenario_path),
            "seed": sim.seed, "robots": sim.num_robots, "scenario": cfg.model_dump(mode="json", by_alias=True)}
    sensor = {**cfg.sensor.model_dump(mode="json"), "odometry": cfg.odometry.model_dump(mode="json"),
              "keyframe_distance": cfg.keyframes.distance}  # the agents' noise model
    with RecordingWriter(out_dir, sensor=sensor, truth_info=info,
                         chunk_size=chunk_size) as writer:
        for r in range(sim.num_robots):
            for kf in sim.keyframes(r):
                i = keyframe_input(kf)
                writer.add_keyframe(r, i.index, i.stamp, i.odometry, i.points, i.labels, i.hit, i.max_range,
                                    true_pose=kf.true_pose)
    return Path(out_dir) / MANIFEST


def recorded_scenario(truth: GroundTruth) -> ScenarioConfig | None:
    """The scenario a recording's ground truth holds, if the simulator wrote it."""
    data = truth.info.get("scenario")
    return None if data is None else validate(ScenarioConfig, data, source="ground_truth scenario")
