"""Scenario files (``sims/*.toml``): the validated description of a simulated world and team.

A scenario holds the building (rectangular spaces joined by doors), furniture layouts that
rooms instantiate (two rooms with the same layout are perceptually identical), robots with
routes or waypoints, optional walking humans, and the sensor / odometry / keyframe models.
Every structural problem raises :class:`ConfigError` naming the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from kimera_multi_py.core.config import StrictModel, apply_env_overrides, load_toml, validate
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.semantics import CLASS_IDS, CLASS_NAMES, DYNAMIC_CLASSES, STRUCTURE_CLASSES

PosFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


class BuildingConfig(StrictModel):
    height: PosFloat = 2.5
    """Floor-to-ceiling height (m)."""
    wall_thickness: PosFloat = 0.1
    slab_thickness: PosFloat = 0.1
    floor_z: float = 0.05
    """z of the floor surface. 0.05 puts floor and ceiling mid-voxel on 0.1 m grids."""


class SpaceConfig(StrictModel):
    name: str
    min: Vec2
    max: Vec2
    kind: Literal["room", "corridor"] = "room"
    layout: str | None = None
    """Name of a furniture layout, placed relative to ``min``."""
    via: Vec2 | None = None
    """Point routes pass through when the layout has no tour (default: the centre)."""

    @model_validator(mode="after")
    def _check_extent(self) -> SpaceConfig:
        if not (self.max[0] > self.min[0] and self.max[1] > self.min[1]):
            raise ValueError(f"max {self.max} must exceed min {self.min} on both axes")
        return self


class DoorConfig(StrictModel):
    at: Vec2
    """Centre of the opening, on the wall line shared by two spaces."""
    width: PosFloat = 1.0
    leaf: bool = True
    """Add an open door leaf (class ``door``) against the wall beside the opening."""


class ObjectConfig(StrictModel):
    cls: str = Field(alias="class")
    shape: Literal["box", "ellipsoid"] = "box"
    xy: Vec2
    size: tuple[PosFloat, PosFloat, PosFloat]
    yaw_deg: float = 0.0
    elevation: NonNegFloat = 0.0
    """Height of the object's bottom above the floor (e.g. a monitor on a table)."""

    @field_validator("cls")
    @classmethod
    def _known_class(cls, v: str) -> str:
        if v not in CLASS_IDS or v == "free":
            raise ValueError(f"unknown class {v!r} (known: {', '.join(CLASS_NAMES[1:])})")
        if v in STRUCTURE_CLASSES or v in DYNAMIC_CLASSES:
            raise ValueError(f"class {v!r} cannot be furniture")
        return v


class LayoutConfig(StrictModel):
    objects: list[ObjectConfig] = []
    tour: list[Vec2] = []
    """Waypoints (relative to the room's min corner) a route follows inside the room."""


class RobotConfig(StrictModel):
    route: list[str] | None = None
    """Names of spaces to visit in order; the path between them is planned through doors."""
    waypoints: list[Vec2] | None = None
    speed: PosFloat = 0.5
    turn_rate_deg: PosFloat = 45.0

    @model_validator(mode="after")
    def _one_path(self) -> RobotConfig:
        if (self.route is None) == (self.waypoints is None):
            raise ValueError("give exactly one of 'route' or 'waypoints'")
        if self.waypoints is not None and len(self.waypoints) < 2:
            raise ValueError("waypoints need at least two points")
        if self.route is not None and len(self.route) < 1:
            raise ValueError("route needs at least one space")
        return self


class HumanConfig(StrictModel):
    """A walking person (class ``human``): along ``waypoints``, or from room to room along ``route``
    (space names; the path is planned through doors and follows each room's tour, as a robot's)."""

    waypoints: list[Vec2] | None = None
    route: list[str] | None = None
    speed: PosFloat = 0.8
    radius: PosFloat = 0.25
    height: PosFloat = 1.75
    pause: NonNegFloat = 0.0
    """Seconds the person stands still at each waypoint (a route's door passages excepted)."""
    start: NonNegFloat = 0.0
    """Seconds the person stands at the first waypoint before setting off."""
    loop: bool = False
    """Walk back to the first waypoint and round again; false: back and forth along the path."""

    @model_validator(mode="after")
    def _one_path(self) -> HumanConfig:
        if (self.route is None) == (self.waypoints is None):
            raise ValueError("give exactly one of 'route' or 'waypoints'")
        if self.waypoints is not None and len(self.waypoints) < 2:
            raise ValueError("waypoints need at least two points")
        if self.route is not None and len(self.route) < 1:
            raise ValueError("route needs at least one space")
        return self


class SensorConfig(StrictModel):
    model: Literal["pinhole", "spherical"] = "pinhole"
    h_fov_deg: Annotated[float, Field(gt=0, le=360)] = 90.0
    v_fov_deg: Annotated[float, Field(gt=0, lt=180)] = 60.0
    rows: Annotated[int, Field(gt=0)] = 48
    cols: Annotated[int, Field(gt=0)] = 64
    max_range: PosFloat = 8.0
    height: NonNegFloat = 1.0
    """Mounting height above the floor (m)."""
    range_sigma: NonNegFloat = 0.02
    label_flip: Annotated[float, Field(ge=0, le=1)] = 0.1
    """Probability that a hit's label flips to a uniformly random other class."""
    confusion: list[list[float]] | None = None
    """Optional K x K row-stochastic confusion matrix over classes 1..K; overrides label_flip."""

    @model_validator(mode="after")
    def _check_fov(self) -> SensorConfig:
        if self.model == "pinhole" and self.h_fov_deg >= 180:
            raise ValueError("pinhole h_fov_deg must be below 180")
        return self


class OdometryConfig(StrictModel):
    rot_sigma_deg: NonNegFloat = 0.5
    """Per-keyframe rotation noise, per axis (deg)."""
    trans_sigma: NonNegFloat = 0.02
    """Per-keyframe translation noise, per axis (m)."""


class KeyframeConfig(StrictModel):
    distance: PosFloat = 0.5
    angle_deg: PosFloat = 20.0


class GroundTruthConfig(StrictModel):
    resolution: PosFloat = 0.1


class ScenarioConfig(StrictModel):
    """Root model of a scenario file."""

    name: str = "scenario"
    seed: int = 0
    building: BuildingConfig = BuildingConfig()
    spaces: list[SpaceConfig]
    doors: list[DoorConfig] = []
    layouts: dict[str, LayoutConfig] = {}
    robots: list[RobotConfig] = []
    humans: list[HumanConfig] = []
    sensor: SensorConfig = SensorConfig()
    odometry: OdometryConfig = OdometryConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    ground_truth: GroundTruthConfig = GroundTruthConfig()

    @model_validator(mode="after")
    def _cross_refs(self) -> ScenarioConfig:
        names = [s.name for s in self.spaces]
        if not names:
            raise ValueError("a scenario needs at least one space")
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"duplicate space names: {sorted(dup)}")
        return self


def check_references(cfg: ScenarioConfig) -> None:
    """Cross-field checks pydantic cannot name precisely: layouts, routes, confusion matrix."""
    names = {s.name for s in cfg.spaces}
    for i, space in enumerate(cfg.spaces):
        if space.layout is not None and space.layout not in cfg.layouts:
            raise ConfigError(f"spaces[{i}].layout", f"unknown layout {space.layout!r}")
    routes = [("robots", i, r.route) for i, r in enumerate(cfg.robots)]
    routes += [("humans", i, h.route) for i, h in enumerate(cfg.humans)]
    for group, i, route in routes:
        for j, name in enumerate(route or []):
            if name not in names:
                raise ConfigError(f"{group}[{i}].route[{j}]", f"unknown space {name!r}")
    if cfg.sensor.confusion is not None:
        import numpy as np

        C = np.asarray(cfg.sensor.confusion, dtype=float)
        K = len(CLASS_NAMES) - 1
        if C.shape != (K, K):
            raise ConfigError("sensor.confusion", f"must be {K}x{K} (classes 1..{K}), got {C.shape}")
        if np.any(C < 0) or not np.allclose(C.sum(1), 1.0, atol=1e-6):
            raise ConfigError("sensor.confusion", "rows must be non-negative and sum to 1")


def load_scenario(path: str | Path, robots: int | None = None, env: bool = True) -> ScenarioConfig:
    """Load and validate a scenario; ``robots`` (from the CLI) overrides the team size.

    Geometric checks (doors on walls, paths through walls) happen when the world is built.
    """
    data = load_toml(path)
    if env:
        data = apply_env_overrides(data, names=ScenarioConfig.model_fields)
    cfg = validate(ScenarioConfig, data, source=str(path))
    check_references(cfg)
    if robots is not None:
        cfg = with_team_size(cfg, robots)
    if not cfg.robots:
        raise ConfigError("robots", "the scenario has no robots; add [[robots]] or pass --robots N")
    return cfg


def with_team_size(cfg: ScenarioConfig, n: int) -> ScenarioConfig:
    """Keep the first ``n`` robots, or add generated ones that tour the rooms in a fixed order.

    Generated routes depend only on the robot's index, so a team of N is the same for every seed.
    """
    import numpy as np

    if n < 1:
        raise ConfigError("robots", f"must be at least 1, got {n}")
    robots = list(cfg.robots[:n])
    rooms = [s.name for s in cfg.spaces if s.kind == "room"] or [s.name for s in cfg.spaces]
    for k in range(len(robots), n):
        order = np.random.default_rng(1000 + k).permutation(len(rooms))
        route = [rooms[j] for j in order[: max(2, min(4, len(rooms)))]]
        robots.append(RobotConfig(route=route))
    return cfg.model_copy(update={"robots": robots})
