"""A synthetic voxel world for map checks: a floor plan of free rectangles, walls around them,
boxes of furniture, extruded to a storey; what a robot saw is every cell near its path."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from kimera_multi_py.alignment.map_check import FREE, OCCUPIED, CellStates
from kimera_multi_py.core.geometry import inverse, transform_points

RES = 0.1
HEIGHT = 24  # cells: a 2.4 m storey


@dataclass
class Floor:
    """Free rectangles (x0, y0, x1, y1) and furniture boxes (x0, y0, x1, y1) on a 0.1 m grid."""

    spaces: list[tuple[float, float, float, float]]
    boxes: list[tuple[float, float, float, float]] = field(default_factory=list)
    margin: float = 1.0

    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell centres (x, y) and per cell: free, occupied (walls and furniture)."""
        xs0 = min(s[0] for s in self.spaces) - self.margin
        ys0 = min(s[1] for s in self.spaces) - self.margin
        xs1 = max(s[2] for s in self.spaces) + self.margin
        ys1 = max(s[3] for s in self.spaces) + self.margin
        x = np.arange(xs0, xs1, RES) + RES / 2
        y = np.arange(ys0, ys1, RES) + RES / 2
        X, Y = np.meshgrid(x, y, indexing="ij")
        free = np.zeros(X.shape, dtype=bool)
        for x0, y0, x1, y1 in self.spaces:
            free |= (X > x0) & (X < x1) & (Y > y0) & (Y < y1)
        furniture = np.zeros_like(free)
        for x0, y0, x1, y1 in self.boxes:
            furniture |= (X > x0) & (X < x1) & (Y > y0) & (Y < y1)
        near_free = np.zeros_like(free)  # one cell around free space: the walls
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                near_free |= np.roll(np.roll(free, dx, 0), dy, 1)
        walls = near_free & ~free
        return np.stack([X, Y], -1), free & ~furniture, walls | (furniture & free)


def seen(floor: Floor, path_xy: np.ndarray, radius: float = 3.0, T_world_own: np.ndarray | None = None) -> CellStates:
    """The cells within ``radius`` of the path, in the robot's own frame (``T_world_own`` its origin)."""
    xy, free, occupied = floor.grid()
    near = cKDTree(path_xy[:, :2]).query(xy.reshape(-1, 2))[0].reshape(xy.shape[:2]) < radius
    states = np.where(occupied, OCCUPIED, np.where(free, FREE, np.int8(0))).astype(np.int8)
    mask = near & (states != 0)
    pts2, st = xy[mask], states[mask]
    z = (np.arange(HEIGHT) + 0.5) * RES
    pts = np.column_stack([np.repeat(pts2, HEIGHT, axis=0), np.tile(z, len(pts2))])
    st3 = np.repeat(st, HEIGHT)
    if T_world_own is not None:
        pts = transform_points(inverse(T_world_own), pts)
    return CellStates(pts, st3)
