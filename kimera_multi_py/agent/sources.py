"""Keyframe sources: what feeds a robot's :class:`~kimera_multi_py.agent.agent.Agent` (DESIGN §4.7).

A source yields :class:`KeyframeInput` in index order and can start at any keyframe index:

* :class:`SimSource` regenerates robot ``i``'s stream from a scenario and seed. The simulator
  draws each robot's noise from its own generator seeded by ``(seed, robot)``, so the stream
  does not depend on the team size. Starting at ``k`` replays keyframes ``0..k-1`` (their
  ray casts decide how much noise each draws) unless a :meth:`SimSource.state` saved earlier
  is passed as ``resume``: then no skipped keyframe is simulated.
* :class:`RecordedSource` reads a recording folder (:mod:`.recording`), written by
  :func:`write_recording` from a scenario or by :class:`RecordingWriter` from plain arrays.

The folder format is described in :mod:`kimera_multi_py.agent.recording`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from kimera_multi_py.agent.agent import KeyframeInput
from kimera_multi_py.agent.recording import (
    MANIFEST,
    GroundTruth,
    RecordingWriter,
    read_chunk,
    read_ground_truth,
    read_manifest,
)
from kimera_multi_py.errors import ConfigError, DatasetError
from kimera_multi_py.sim.scenario import ScenarioConfig, load_scenario, with_team_size
from kimera_multi_py.sim.simulation import Keyframe, Simulation

__all__ = ["GroundTruth", "KeyframeSource", "RecordedSource", "RecordingWriter", "SimSource", "keyframe_input",
           "read_ground_truth", "read_manifest", "source_from_spec", "write_recording"]


class KeyframeSource(Protocol):
    """A robot's keyframes from ``start`` on, in index order.

    ``state()`` is plain data to pass back as ``resume`` (with ``start`` = its ``next``) to
    continue exactly where this source is now; a node keeps it in its checkpoint's ``extra``.
    """

    robot: int
    start: int

    def __iter__(self) -> Iterator[KeyframeInput]: ...

    def __next__(self) -> KeyframeInput: ...

    @property
    def num_keyframes(self) -> int:
        """Keyframes in the whole stream (from index 0)."""
        ...

    @property
    def next_index(self) -> int:
        """The index of the keyframe ``next()`` returns."""
        ...

    def state(self) -> dict[str, Any]: ...


def keyframe_input(kf: Keyframe) -> KeyframeInput:
    """What the agent may see of a simulated keyframe (no ground truth)."""
    return KeyframeInput(kf.index, kf.stamp, kf.odometry, kf.scan.points(), kf.scan.labels, kf.scan.hit,
                         kf.scan.max_range)


# ---- simulator ----------------------------------------------------------------------------
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


class RecordedSource:
    """Robot ``robot``'s keyframes from a recording folder, from ``start`` on (an iterator).

    A restart reads only the chunk holding ``start``; ``resume`` (a :meth:`state`) is only checked.
    """

    def __init__(self, folder: str | Path, robot: int, start: int = 0, resume: dict[str, Any] | None = None) -> None:
        self.dir = Path(folder)
        self.manifest = read_manifest(self.dir)
        entry = next((e for e in self.manifest["robots"] if e["robot"] == robot), None)
        if entry is None:
            have = ", ".join(str(e["robot"]) for e in self.manifest["robots"])
            raise DatasetError(f"{self.dir / MANIFEST}: no robot {robot} (robots: {have})")
        self.robot = int(robot)
        self.start = int(start)
        self._chunks: list[dict[str, Any]] = entry["chunks"]
        self._n = int(entry["keyframes"])
        if not 0 <= self.start <= self._n:
            raise DatasetError(f"{self.dir}: robot {robot} has keyframes 0..{self._n - 1}, cannot start at {start}")
        if resume is not None and (not isinstance(resume, dict) or resume.get("robot") != self.robot
                                   or resume.get("next") != self.start):
            raise ConfigError("resume", f"not the state of robot {self.robot}'s recording at keyframe {self.start}")
        self._next = self.start
        self._buffer: list[KeyframeInput] = []
        self._last_stamp = -np.inf

    def state(self) -> dict[str, Any]:
        """Plain data to resume from the next keyframe."""
        return {"robot": self.robot, "next": self._next}

    @property
    def num_keyframes(self) -> int:
        return self._n

    @property
    def next_index(self) -> int:
        return self._next

    def __iter__(self) -> Iterator[KeyframeInput]:
        return self

    def __next__(self) -> KeyframeInput:
        if self._next >= self._n:
            raise StopIteration
        if not self._buffer:
            chunk = next(c for c in self._chunks if c["first"] <= self._next < c["first"] + c["count"])
            previous = self._last_stamp if chunk["first"] == self._next else -np.inf
            kfs = read_chunk(self.dir, chunk, previous)
            self._last_stamp = kfs[-1].stamp
            self._buffer = [kf for kf in kfs if kf.index >= self._next]
        kf = self._buffer.pop(0)
        self._next += 1
        return kf


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


def source_from_spec(spec: str, robot: int, start: int = 0, resume: dict[str, Any] | None = None) -> KeyframeSource:
    """``sim:SCENARIO[:SEED]`` (the scenario's seed by default) or a recording folder.

    ``resume`` is a source's :meth:`~KeyframeSource.state` saved when ``start`` was next.
    """
    if spec.startswith("sim:"):
        rest = spec[4:]
        path, _, tail = rest.rpartition(":")
        if not path or not tail.lstrip("-").isdigit():
            path, tail = rest, ""
        if not path:
            raise ConfigError("--source", f"{spec!r}: expected sim:SCENARIO[:SEED]")
        cfg = load_scenario(path)
        if robot >= len(cfg.robots):  # generated robots depend only on their index
            cfg = with_team_size(cfg, robot + 1)
        return SimSource(cfg, int(tail) if tail else None, robot, start, resume)
    if Path(spec).is_dir():
        return RecordedSource(spec, robot, start, resume)
    raise ConfigError("--source", f"{spec!r} is neither sim:SCENARIO[:SEED] nor a recording folder")
