"""Rooms: Hydra's dilation sweep over the places graph, then seed growth (docs/algorithms/scene_graph.md).

For each δ from ``room_delta_max`` down to ``room_delta_min`` the places with clearance above δ
and the edges with weight above δ form a subgraph; its components of at least
``room_min_places`` places are candidate rooms. Narrow passages (doors) have small clearance,
so at the right δ they disappear and each room is its own component. δ is taken from the
longest run of δ with the same number of components (the plateau), at its middle. Only counts of
at least ``room_plateau_ratio`` times the largest count compete: at large δ rooms do not merge,
they vanish (their clearance is below δ), so a long run of one component there says nothing about
doors (a robot's partial map of the office shows exactly that; Hydra has a ``plateau_ratio`` too). Those
components seed the rooms; every remaining place joins the room of its nearest seed place along
the graph (Euclidean edge lengths). Hydra grows along the highest-clearance edge first instead;
with 0.5 m place cells the low-clearance places along walls are joined by edges weaker than a
door's, so that flood leaks through doors into the next room's edges (see the two-room test).
Rooms that end with fewer than ``room_min_places`` places are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from kimera_multi_py.scene_graph.grid import DistanceField
from kimera_multi_py.scene_graph.params import SceneGraphParams
from kimera_multi_py.scene_graph.places import Places


@dataclass
class Rooms:
    """Room of each place (-1 for none), the chosen δ and the sweep that chose it."""

    place_room: np.ndarray  # (n,) int64
    delta: float
    deltas: np.ndarray
    counts: np.ndarray  # rooms (components of >= room_min_places) at each δ

    @property
    def num_rooms(self) -> int:
        return int(self.place_room.max() + 1) if len(self.place_room) else 0


def _components(places: Places, delta: float, min_places: int) -> np.ndarray:
    """Component label per place at dilation ``delta`` (-1 for small components and dropped places)."""
    n = len(places)
    keep = places.clearance > delta
    e = places.edges
    ek = keep[e[:, 0]] & keep[e[:, 1]] & (places.edge_clearance > delta)
    g = coo_matrix((np.ones(int(ek.sum())), (e[ek, 0], e[ek, 1])), shape=(n, n))
    _, label = connected_components(g, directed=False)
    label = np.where(keep, label, -1)
    sizes = np.bincount(label[keep], minlength=n) if keep.any() else np.zeros(n, dtype=np.int64)
    big = np.flatnonzero(sizes >= min_places)
    out = np.full(n, -1, dtype=np.int64)
    member = keep & np.isin(label, big)
    out[member] = np.searchsorted(big, label[member])
    return out


def _plateau(counts: np.ndarray, ratio: float) -> tuple[int, int]:
    """``(start, end)`` (inclusive) of the longest run of equal counts of at least ``ratio`` times the
    largest count (first of ties)."""
    best = (0, 0)
    best_len = 0
    start = 0
    floor = max(ratio * float(counts.max()), 1.0) if len(counts) else 1.0
    for i in range(1, len(counts) + 1):
        if i == len(counts) or counts[i] != counts[start]:
            if counts[start] >= floor and i - start > best_len:
                best, best_len = (start, i - 1), i - start
            start = i
    return best


def _grow(places: Places, seeds: np.ndarray) -> np.ndarray:
    """Give every unlabelled place the room of its nearest seed place along the graph (Euclidean
    edge lengths; one multi-source Dijkstra)."""
    label = seeds.copy()
    src = np.flatnonzero(seeds >= 0)
    if len(src) == 0 or len(places.edges) == 0:
        return label
    n = len(places)
    e = places.edges
    length = np.linalg.norm(places.positions[e[:, 0]] - places.positions[e[:, 1]], axis=1)
    g = csr_matrix((np.maximum(length, 1e-9), (e[:, 0], e[:, 1])), shape=(n, n))
    dist, _, source = dijkstra(g, directed=False, indices=src, min_only=True, return_predecessors=True)
    reached = np.isfinite(dist) & (label < 0)
    label[reached] = seeds[source[reached]]
    return label


def find_rooms(places: Places, params: SceneGraphParams) -> Rooms:
    """Rooms of the places graph by the dilation sweep (see module docstring)."""
    n = len(places)
    deltas = np.round(np.arange(params.room_delta_max, params.room_delta_min - 1e-9, -params.room_delta_step), 6)
    if n == 0:
        return Rooms(np.zeros(0, np.int64), float(deltas[0]), deltas, np.zeros(len(deltas), np.int64))
    comps = [_components(places, float(d), params.room_min_places) for d in deltas]
    counts = np.array([int(c.max() + 1) for c in comps])
    start, end = _plateau(counts, params.room_plateau_ratio)
    pick = (start + end) // 2
    label = _grow(places, comps[pick]) if counts[pick] > 0 else np.full(n, -1, dtype=np.int64)
    return Rooms(_finish(label, params.room_min_places), float(deltas[pick]), deltas, counts)


def _finish(label: np.ndarray, min_places: int) -> np.ndarray:
    """Drop rooms below ``min_places``, then number rooms by their smallest place id."""
    n = len(label)
    sizes = np.bincount(label[label >= 0], minlength=max(int(label.max()) + 1, 1))
    label = np.where((label >= 0) & (sizes[np.maximum(label, 0)] >= min_places), label, -1)
    rooms = np.unique(label[label >= 0])
    first = np.array([np.flatnonzero(label == r)[0] for r in rooms], dtype=np.int64)
    rank = np.empty(len(rooms), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(rooms))
    out = np.full(n, -1, dtype=np.int64)
    m = label >= 0
    out[m] = rank[np.searchsorted(rooms, label[m])]
    return out


def find_rooms_ceiling(places: Places, field: DistanceField, params: SceneGraphParams) -> Rooms:
    """The DSG paper's alternative: cut free space ``ceiling_offset`` below the ceiling (the highest
    grid layer with at least half as many free cells as the fullest layer), keep the cells of the cut
    with 2-D clearance above ``ceiling_clearance``, and take its connected components (of at least
    ``room_min_area``) as room seeds; places seed by containment, then grow as in the sweep. It
    separates rooms where door frames stop below the ceiling; the simulator's doors are full height."""
    grid = field.grid
    n = len(places)
    counts = grid.free.sum(axis=(0, 1))
    if n == 0 or counts.max() == 0:
        return Rooms(np.full(n, -1, dtype=np.int64), params.ceiling_clearance, np.zeros(0), np.zeros(0, np.int64))
    top = int(np.flatnonzero(counts >= 0.5 * counts.max())[-1])
    k = max(top - int(round(params.ceiling_offset / grid.resolution)), 0)
    cut = grid.free[:, :, k]
    clear = ndimage.distance_transform_edt(cut, sampling=grid.resolution)
    comp, num = ndimage.label(clear > params.ceiling_clearance, structure=np.ones((3, 3), dtype=np.int64))
    area = np.bincount(comp.reshape(-1), minlength=num + 1) * grid.resolution**2
    area[0] = 0.0
    idx = grid.index(places.positions)[:, :2]
    ok = np.all((idx >= 0) & (idx < np.array(cut.shape)), axis=1)
    seed = np.zeros(n, dtype=np.int64)
    seed[ok] = comp[idx[ok, 0], idx[ok, 1]]
    seed = np.where((seed > 0) & (area[seed] >= params.room_min_area), seed - 1, -1)
    label = _grow(places, seed)
    return Rooms(_finish(label, params.room_min_places), params.ceiling_clearance, np.zeros(0),
                 np.zeros(0, np.int64))


def room_edges(places: Places, place_room: np.ndarray) -> np.ndarray:
    """Room pairs ``(r, s)``, r < s, joined by a place edge (through a door)."""
    e = places.edges
    ra, rb = place_room[e[:, 0]], place_room[e[:, 1]]
    cross = (ra >= 0) & (rb >= 0) & (ra != rb)
    pairs = np.sort(np.stack([ra[cross], rb[cross]], 1), axis=1)
    return np.unique(pairs, axis=0).reshape(-1, 2)
