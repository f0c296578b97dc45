"""Where a robot's parts are chosen: its keyframe source and its agent parameters (docs/architecture.md).

Every runner (the single-process simulation, the agent process, replay) builds through here,
so a source spec or a noise model means the same thing everywhere. The noise model is the
source's: the scenario's sensor, a recording's manifest, or their defaults; a configuration
(:class:`~kimera_multi_py.team.config.KimeraConfig`) that sets ``agent.odom_sigmas`` or
``agent.keyframe_distance`` explicitly overrides it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.io.bag.reader import BagSource
from kimera_multi_py.io.sources import KeyframeSource, RecordedSource
from kimera_multi_py.sim.scenario import KeyframeConfig, OdometryConfig, ScenarioConfig, load_scenario, with_team_size
from kimera_multi_py.sim.source import SimSource
from kimera_multi_py.team.config import KimeraConfig

# the server process has no keyframe source: about the simulator's default noise (0.5 deg, 0.03 m)
SERVER_ODOM_SIGMAS = (0.0087, 0.03)


def noise_model(rot_sigma_deg: float, trans_sigma: float, keyframe_distance: float) -> dict[str, Any]:
    """The agents' noise fields for an odometry noise model (floored so no edge is infinitely certain)."""
    odom_sigmas = (max(float(np.deg2rad(rot_sigma_deg)), 1e-4), max(trans_sigma, 1e-3))
    return {"odom_sigmas": odom_sigmas, "keyframe_distance": keyframe_distance}


def noise_params(rot_sigma_deg: float, trans_sigma: float, keyframe_distance: float,
                 config: KimeraConfig | None = None) -> AgentParams:
    """The agents' parameters (``config``'s, else the defaults) for an odometry noise model."""
    return (config or KimeraConfig.defaults()).to_agent_params(
        **noise_model(rot_sigma_deg, trans_sigma, keyframe_distance))


def agent_params(cfg: ScenarioConfig, config: KimeraConfig | None = None) -> AgentParams:
    """The agents' parameters for a scenario (the odometry noise model comes from its sensor)."""
    return noise_params(cfg.odometry.rot_sigma_deg, cfg.odometry.trans_sigma, cfg.keyframes.distance, config)


def params_for(source: KeyframeSource, config: KimeraConfig | None = None) -> AgentParams:
    """The agent's parameters with the source's noise model: the scenario's for the simulator, the
    recording's sensor info (``odometry.rot_sigma_deg``, ``odometry.trans_sigma``,
    ``keyframe_distance``) otherwise; what a recording leaves out takes the simulator's defaults."""
    if isinstance(source, SimSource):
        return agent_params(source.sim.cfg, config)
    sensor = getattr(source, "manifest", {}).get("sensor", {})
    odo = sensor.get("odometry") or {}
    odo_default, kf_default = OdometryConfig(), KeyframeConfig()
    try:
        rot = float(odo.get("rot_sigma_deg", odo_default.rot_sigma_deg))
        trans = float(odo.get("trans_sigma", odo_default.trans_sigma))
        dist = float(sensor.get("keyframe_distance", kf_default.distance))
    except (TypeError, ValueError) as exc:
        raise ConfigError("manifest.sensor", f"bad odometry noise model: {exc}") from None
    return noise_params(rot, trans, dist, config)


def source_from_spec(spec: str, robot: int, start: int = 0, resume: dict[str, Any] | None = None) -> KeyframeSource:
    """``sim:SCENARIO[:SEED]`` (the scenario's seed by default), ``bag:PATH[:CONFIG]`` (a ROS 1 or
    ROS 2 bag; its config: CONFIG, else the bag's own ``PATH.toml``; docs/bags.md) or a recording folder.

    ``resume`` is a source's :meth:`~KeyframeSource.state` saved when ``start`` was next.
    """
    if spec.startswith("bag:"):
        bag, config = bag_spec(spec)
        return BagSource(bag, robot, start, resume, config)
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
    raise ConfigError("--source", f"{spec!r} is neither sim:SCENARIO[:SEED], bag:PATH nor a recording folder")


def bag_spec(spec: str) -> tuple[Path, Path | None]:
    """``bag:PATH[:CONFIG]`` as ``(PATH, CONFIG)``; CONFIG ends in .toml, .yaml or .yml."""
    rest = spec[4:]
    head, _, tail = rest.rpartition(":")
    if not head or Path(tail).suffix.lower() not in (".toml", ".yaml", ".yml"):
        head, tail = rest, ""
    if not head:
        raise ConfigError("--source", f"{spec!r}: expected bag:PATH[:CONFIG]")
    if not Path(head).exists():
        raise ConfigError("--source", f"{spec!r}: no bag at {head}")
    return Path(head), Path(tail) if tail else None
