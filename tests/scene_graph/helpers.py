"""Hand-made maps for scene-graph tests: rectangular spaces, doors, a floor and a ceiling."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.observation import SCALE
from kimera_multi_py.mapping.semantic_octree import SemanticOctree

RES = 0.1
HEIGHT = 2.5
WALL = 1
K = 12

Rect = tuple[float, float, float, float]  # x0, y0, x1, y1


def box_world(spaces: list[Rect], doors: list[Rect], height: float = HEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """Centres and free flags of every cell of a floor plan: cells inside a space (walls 0.1 m thick on
    the boundaries) or inside a door's opening (a rectangle across a wall) are free, the rest of the
    bounding box (walls, floor, ceiling, outside) is occupied."""
    r = np.array(spaces, dtype=float)
    lo, hi = r[:, :2].min(0) - 0.3, r[:, 2:].max(0) + 0.3
    lo_z, hi_z = -0.3, height + 0.3
    axes = [(np.arange(round(a / RES), round(b / RES)) + 0.5) * RES
            for a, b in ((lo[0], hi[0]), (lo[1], hi[1]), (lo_z, hi_z))]
    c = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    t = 0.05
    zin = (c[:, 2] > 0.0) & (c[:, 2] < height)
    free = np.zeros(len(c), dtype=bool)
    for x0, y0, x1, y1 in spaces:
        free |= (c[:, 0] > x0 + t) & (c[:, 0] < x1 - t) & (c[:, 1] > y0 + t) & (c[:, 1] < y1 - t)
    for x0, y0, x1, y1 in doors:
        free |= (c[:, 0] > x0) & (c[:, 0] < x1) & (c[:, 1] > y0) & (c[:, 1] < y1)
    return c, free & zin


def octree_of(centers: np.ndarray, free: np.ndarray, occupied_class: int = WALL) -> SemanticOctree:
    """A semantic octree whose cells are confidently free or occupied (by ``occupied_class``)."""
    tree = SemanticOctree(RES, K)
    codes = morton.points_to_codes(centers, RES)
    order = np.argsort(codes)
    rows = np.zeros((len(codes), K + 1), dtype=np.int16)
    rows[:, 1:] = -3 * SCALE
    rows[~free, occupied_class] = 6 * SCALE
    tree.add(codes[order], rows[order])
    return tree


def add_box(centers: np.ndarray, free: np.ndarray, lo: tuple[float, float, float],
            hi: tuple[float, float, float]) -> np.ndarray:
    """``free`` with the cells inside a furniture box made occupied."""
    inside = np.all((centers > np.array(lo)) & (centers < np.array(hi)), axis=1)
    return free & ~inside


# two 4 x 4 m rooms side by side, a 1 m door in the wall at x = 4 (y in [1.5, 2.5])
TWO_ROOMS = ([(0.0, 0.0, 4.0, 4.0), (4.0, 0.0, 8.0, 4.0)], [(3.9, 1.5, 4.1, 2.5)])
# an L-shaped room: a 6 x 2.5 m arm and a 2.5 x 6 m arm meeting at a corner
L_ROOM = ([(0.0, 0.0, 6.0, 2.5), (0.0, 0.0, 2.5, 6.0)], [])
