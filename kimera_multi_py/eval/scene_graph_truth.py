"""Ground-truth rooms of a simulated world: its spaces as boxes from floor to ceiling (world frame).

A room is one space, or several spaces joined by an opening as wide as the wall they share
(a "door" that removes the whole wall, as in an L-shaped room built from two rectangles).
A room may therefore hold several boxes, as Hydra's room ground truth does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from kimera_multi_py.core.semantics import NUM_CLASSES
from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.observation import SCALE
from kimera_multi_py.mapping.semantic_octree import SemanticOctree
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.world import World


@dataclass
class TrueRooms:
    """Rooms as unions of axis-aligned boxes."""

    names: list[str]  # per room ("a+b" for joined spaces)
    kinds: list[str]  # per room: "room" or "corridor"
    lo: np.ndarray  # (boxes, 3)
    hi: np.ndarray  # (boxes, 3)
    box_room: np.ndarray  # (boxes,) room index of each box

    def __len__(self) -> int:
        return len(self.names)

    def containing(self, points: np.ndarray) -> np.ndarray:
        """Room index of the first box holding each point, -1 for none."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        inside = np.all((p[:, None] >= self.lo[None]) & (p[:, None] < self.hi[None]), axis=2)
        return np.where(inside.any(axis=1), self.box_room[np.argmax(inside, axis=1)], -1)

    def to_dict(self) -> dict[str, object]:
        return {"names": self.names, "kinds": self.kinds, "lo": self.lo.tolist(), "hi": self.hi.tolist(),
                "box_room": self.box_room.tolist()}


def as_world(world_or_scenario: World | ScenarioConfig) -> World:
    return world_or_scenario if isinstance(world_or_scenario, World) else World(world_or_scenario)


def _shared_wall(a: np.ndarray, b: np.ndarray, normal: np.ndarray) -> float:
    """Length of the wall two rectangles ``[x0, y0, x1, y1]`` share, for a door with this normal."""
    axis = 1 if abs(normal[0]) > 0.5 else 0  # a wall across x runs along y
    return float(min(a[axis + 2], b[axis + 2]) - max(a[axis], b[axis]))


def true_rooms(world_or_scenario: World | ScenarioConfig) -> TrueRooms:
    """The simulator's spaces as boxes ``[min, max] x [floor, ceiling]``, grouped into rooms."""
    world = as_world(world_or_scenario)
    cfg = world.cfg
    n = len(cfg.spaces)
    joins = [d.spaces for d in world.doors
             if d.width >= _shared_wall(world.rects[d.spaces[0]], world.rects[d.spaces[1]], d.normal) - 1e-6]
    ij = np.array(joins, dtype=np.int64).reshape(-1, 2)
    _, comp = connected_components(coo_matrix((np.ones(len(ij)), (ij[:, 0], ij[:, 1])), shape=(n, n)), directed=False)
    _, first = np.unique(comp, return_index=True)
    order = np.argsort(first)  # rooms in the order of their first space
    room_of_comp = np.empty(len(order), dtype=np.int64)
    room_of_comp[order] = np.arange(len(order))
    box_room = room_of_comp[comp]
    names = ["+".join(cfg.spaces[s].name for s in np.flatnonzero(box_room == r)) for r in range(len(order))]
    kinds = ["corridor" if all(cfg.spaces[s].kind == "corridor" for s in np.flatnonzero(box_room == r)) else "room"
             for r in range(len(order))]
    b = cfg.building
    lo = np.array([[s.min[0], s.min[1], b.floor_z] for s in cfg.spaces], dtype=np.float64)
    hi = np.array([[s.max[0], s.max[1], b.floor_z + b.height] for s in cfg.spaces], dtype=np.float64)
    return TrueRooms(names, kinds, lo, hi, box_room)


def perfect_octree(world_or_scenario: World | ScenarioConfig, resolution: float = 0.1,
                   num_classes: int = NUM_CLASSES) -> SemanticOctree:
    """The ground-truth voxel grid as a semantic octree (every cell observed, confidently free or
    occupied by its true class): the flawless map, as a reference for the scene-graph builder."""
    grid = as_world(world_or_scenario).gt_voxel_grid(resolution)
    labels = grid.labels.reshape(-1)
    known = labels >= 0
    codes = morton.points_to_codes(grid.centers().reshape(-1, 3)[known], resolution)
    order = np.argsort(codes)
    rows = np.zeros((len(codes), num_classes + 1), dtype=np.int16)
    rows[:, 1:] = -3 * SCALE
    lab = labels[known].astype(np.int64)
    occ = np.flatnonzero(lab > 0)
    rows[occ, lab[occ]] = 6 * SCALE
    tree = SemanticOctree(resolution, num_classes)
    tree.add(codes[order], rows[order])
    return tree
