"""Ground-truth rooms of a simulated world: its spaces as boxes from floor to ceiling (world frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.world import World


@dataclass
class TrueRooms:
    """One axis-aligned box per space (rooms and corridors)."""

    names: list[str]
    kinds: list[str]
    lo: np.ndarray  # (r, 3)
    hi: np.ndarray  # (r, 3)

    def __len__(self) -> int:
        return len(self.names)

    def containing(self, points: np.ndarray) -> np.ndarray:
        """Index of the first box holding each point, -1 for none."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        inside = np.all((p[:, None] >= self.lo[None]) & (p[:, None] < self.hi[None]), axis=2)
        return np.where(inside.any(axis=1), np.argmax(inside, axis=1), -1)

    def to_dict(self) -> dict[str, object]:
        return {"names": self.names, "kinds": self.kinds, "lo": self.lo.tolist(), "hi": self.hi.tolist()}


def as_world(world_or_scenario: World | ScenarioConfig) -> World:
    return world_or_scenario if isinstance(world_or_scenario, World) else World(world_or_scenario)


def true_rooms(world_or_scenario: World | ScenarioConfig) -> TrueRooms:
    """The simulator's spaces as boxes ``[min, max] x [floor, ceiling]``."""
    cfg = world_or_scenario.cfg if isinstance(world_or_scenario, World) else world_or_scenario
    b = cfg.building
    lo = np.array([[s.min[0], s.min[1], b.floor_z] for s in cfg.spaces], dtype=np.float64)
    hi = np.array([[s.max[0], s.max[1], b.floor_z + b.height] for s in cfg.spaces], dtype=np.float64)
    return TrueRooms([s.name for s in cfg.spaces], [s.kind for s in cfg.spaces], lo, hi)
