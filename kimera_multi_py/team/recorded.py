"""Recorded data as a team: the sources of ``--source`` specs, their ground truth and the
simulated world they came from, if any (docs/bags.md).

``kimera-multi replay`` (one process) and ``kimera-multi launch --source`` (agent processes) open
a team's recorded sources through here, so a spec means the same team in both, and every error a
user can fix is raised before the run.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from kimera_multi_py.core.errors import ConfigError, DatasetError
from kimera_multi_py.io.bag.config import config_for
from kimera_multi_py.io.bag.reader import BagSource, bag_robots
from kimera_multi_py.io.bag.tf import PoseSeries
from kimera_multi_py.io.sources import KeyframeSource, RecordedSource, read_ground_truth, read_manifest
from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.sim.scenario import ScenarioConfig, load_scenario
from kimera_multi_py.sim.source import recorded_scenario
from kimera_multi_py.team.build import bag_spec


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


def source_stamps(source: KeyframeSource) -> np.ndarray:
    """A bag's keyframe stamps (ROS time; the team's first becomes 0 s); a recorded folder's start at 0 s."""
    return source.stamps if isinstance(source, BagSource) else np.zeros(1)


def source_truth(sources: Sequence[KeyframeSource], truth_files: Sequence[str | Path]) -> list[np.ndarray | None]:
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


def recorded_world(sources: Sequence[KeyframeSource]) -> tuple[ScenarioConfig | None, int]:
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


__all__ = ["open_sources", "recorded_world", "source_stamps", "source_truth"]
