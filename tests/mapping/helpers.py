"""Generators of synthetic scans and independent reference implementations for map tests."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.octree_block import PRUNE_MAX_LEVEL

WALL, FLOOR, CEILING, CHAIR, TABLE, HUMAN = 1, 2, 3, 5, 6, 12
K = 12


def sphere_dirs(n: int, rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def ray_box_exit(
    origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Distance along each ray to the inside of an axis-aligned box's boundary (origin inside)."""
    with np.errstate(divide="ignore"):
        t = np.where(
            dirs > 0, (hi - origin) / dirs, np.where(dirs < 0, (lo - origin) / dirs, np.inf)
        )
    return t.min(axis=1)


def ray_box_entry(
    origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Distance to enter a box from outside (inf if missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - origin) / dirs, (hi - origin) / dirs
    tn, tf = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
    return np.where((tf >= tn) & (tn > 0), tn, np.inf)


# surfaces sit mid-voxel on a 0.1 m grid, as in the simulator's office
ROOM_LO = np.array([-3.05, -2.55, 0.05])
ROOM_HI = np.array([3.05, 2.55, 2.55])
TABLE_LO = np.array([1.05, -0.45, 0.05])
TABLE_HI = np.array([2.15, 0.25, 0.75])


def room_scan(
    origin: np.ndarray,
    n: int = 5000,
    seed: int = 0,
    table: bool = True,
    human: np.ndarray | None = None,
    noise: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """End points and labels of rays cast from ``origin`` inside a box room with a table.

    Faces: floor (z min), ceiling (z max), walls; ``human`` is an optional (lo, hi) box.
    ``noise`` is the probability of a random wrong label.
    """
    rng = np.random.default_rng(seed)
    o = np.asarray(origin, dtype=float)
    d = sphere_dirs(n, rng)
    t = ray_box_exit(o, d, ROOM_LO, ROOM_HI)
    p = o + d * t[:, None]
    lab = np.full(n, WALL)
    lab[np.abs(p[:, 2] - ROOM_LO[2]) < 1e-9] = FLOOR
    lab[np.abs(p[:, 2] - ROOM_HI[2]) < 1e-9] = CEILING
    boxes = []
    if table:
        boxes.append((TABLE_LO, TABLE_HI, TABLE))
    if human is not None:
        boxes.append((human[0], human[1], HUMAN))
    for lo, hi, c in boxes:
        tb = ray_box_entry(o, d, lo, hi)
        closer = tb < t
        t = np.where(closer, tb, t)
        lab[closer] = c
        p = o + d * t[:, None]
    return p, flip_labels(lab, noise, rng)


def flip_labels(lab: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Replace a fraction ``noise`` of labels by a uniformly random *other* class."""
    lab = lab.copy()
    flip = rng.random(len(lab)) < noise
    lab[flip] = (lab[flip] - 1 + rng.integers(1, K, flip.sum())) % K + 1
    return lab


def aw_traverse(origin: np.ndarray, end: np.ndarray, res: float) -> list[tuple[int, int, int]]:
    """Amanatides & Woo voxel walk from ``origin`` to ``end`` (end voxel excluded), per ray."""
    u0, u1 = origin / res, end / res
    cur = np.floor(u0).astype(int)
    last = np.floor(u1).astype(int)
    d = u1 - u0
    step = np.sign(d).astype(int)
    with np.errstate(divide="ignore"):
        t_max = np.where(d > 0, (cur + 1 - u0) / d, np.where(d < 0, (cur - u0) / d, np.inf))
        t_delta = np.where(d != 0, 1.0 / np.abs(d), np.inf)
    out = []
    for _ in range(100000):
        if np.array_equal(cur, last):
            break
        out.append(tuple(cur))
        a = int(np.argmin(t_max))
        cur[a] += step[a]
        t_max[a] += t_delta[a]
    return out


def keys_of(codes: np.ndarray) -> set[tuple[int, int, int]]:
    """Relative integer voxel coordinates (floor(x / res)) of Morton codes."""
    return {tuple(k) for k in (morton.decode(codes) - morton.KEY_OFFSET).tolist()}


class ReferenceMap:
    """Per-voxel dictionary with the same fixed-point update rule (no tree, no pruning)."""

    def __init__(self, model) -> None:
        self.model = model
        self.cells: dict[int, np.ndarray] = {}

    def add(self, codes: np.ndarray, rows: np.ndarray) -> None:
        for c, r in zip(codes.tolist(), rows, strict=True):
            old = self.cells.get(c, self.model.prior_row).astype(np.int32)
            self.cells[c] = np.clip(old + r, self.model.lo, self.model.hi).astype(np.int16)


def canonical_leaves(
    cells: dict[int, np.ndarray], max_level: int = PRUNE_MAX_LEVEL
) -> dict[tuple[int, int], bytes]:
    """Maximal pruning of a voxel dictionary, done naively: ``{(start, level): row bytes}``."""
    nodes = {(c, 0): r.tobytes() for c, r in cells.items()}
    for lev in range(1, max_level + 1):
        groups: dict[int, list[tuple[int, int]]] = {}
        for start, level in nodes:
            if level == lev - 1:
                groups.setdefault(start >> (3 * lev), []).append((start, level))
        for parent, kids in groups.items():
            vals = {nodes[k] for k in kids}
            if len(kids) == 8 and len(vals) == 1:
                v = vals.pop()
                for k in kids:
                    del nodes[k]
                nodes[(parent << (3 * lev), lev)] = v
    return nodes


def tree_leaves(tree) -> dict[tuple[int, int], bytes]:
    return {
        (int(c), int(lv)): r.tobytes()
        for c, lv, r in zip(tree.codes, tree.levels, tree.values, strict=True)
    }
