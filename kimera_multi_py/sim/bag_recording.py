"""The simulator's streams written as a ROS bag (docs/bags.md): what ``kimera-multi record --format``
writes, so tests run on real bag files and users see what a working bag looks like."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.io.bag.depth import camera_model
from kimera_multi_py.io.bag.writer import BagWriter, Format
from kimera_multi_py.sim.scenario import ScenarioConfig, with_team_size
from kimera_multi_py.sim.simulation import Simulation
from kimera_multi_py.sim.source import keyframe_input


def write_bag(out: str | Path, cfg: ScenarioConfig, fmt: Format = "ros2", robots: int | None = None,
              seed: int | None = None, camera: bool = False, label_encoding: str = "mono16",
              extrinsic: np.ndarray | None = None, scenario_path: str | Path | None = None,
              float64: bool = False) -> Path:
    """Simulate a team for ``seed`` and write it into one bag (robot r under ``/robot{r}``); return
    the bag's config file. ``camera``: depth + semantic images (a pinhole sensor's rays are its pixels)."""
    if robots is not None and robots != len(cfg.robots):
        cfg = with_team_size(cfg, robots)
    s = cfg.sensor
    if camera and s.model != "pinhole":
        raise ConfigError("camera", f"depth images need a pinhole sensor; the scenario's is {s.model!r}")
    cam = (camera_model(s.rows, s.cols, s.h_fov_deg, s.v_fov_deg), s.rows, s.cols) if camera else None
    sim = Simulation(cfg, seed)
    writer = BagWriter(out, fmt, camera=cam, label_encoding=label_encoding, extrinsic=extrinsic, float64=float64)
    odom: dict[int, np.ndarray] = {}
    try:
        for kf in sim.stream():
            odom[kf.robot] = kf.odometry.copy() if kf.index == 0 else odom[kf.robot] @ kf.odometry
            writer.add(kf.robot, keyframe_input(kf), odom[kf.robot], kf.true_pose)
    except BaseException:
        writer.abort()
        raise
    noise = {"rot_sigma_deg": cfg.odometry.rot_sigma_deg, "trans_sigma": cfg.odometry.trans_sigma,
             "keyframe_distance": cfg.keyframes.distance}
    origin = {"scenario": None if scenario_path is None else str(Path(scenario_path).resolve()), "seed": sim.seed,
              "robots": sim.num_robots}
    return writer.close(noise=noise, origin=origin)
