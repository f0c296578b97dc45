"""Occupancy agreement of two robots' maps under a frame hypothesis (docs/algorithms/pgo.md).

A frame hypothesis that puts a robot one room off moves what the robot saw as free space into
another robot's walls and furniture, and its walls into the other's free space. Closures cannot
see this (the rooms look the same); the maps can. This module counts it:

* each map's cells get a state from their occupancy log-odds ``lse(h[1:])`` (the free class is
  the pivot ``h[0] = 0``): *occupied* above ``+threshold``, *free* below ``-threshold``, else
  unknown (one hit or one pass is not enough either way with the default model);
* both maps are binned on a coarse grid (``coarse`` metres): a coarse cell is occupied if any of
  its cells is, free if it holds free cells and no occupied one;
* a coarse cell *conflicts* when one map has it occupied and the other has it free with no
  occupied cell in its 26 neighbours (so a wall seen a few centimetres apart by the two robots,
  the residual error of a correct alignment, is not a conflict), and another conflicting cell
  shares its vertical column (a displaced wall or cabinet conflicts over its height; a lone cell
  is a grazing ray or a thin edge);
* ``overlap`` counts the coarse cells both maps know (occupied or free).

A frame hypothesis from closures at one place is only as precise as those closures: a degree
of yaw is 30 cm at 17 m. :func:`refined_agreement` therefore first registers the occupied cells
of one map onto the other's from the hypothesis (small_gicp's GICP, a few correspondence
distances down to one cell), and scores the frame it reaches (converged within the iteration cap
or not: the score decides) when that frame stays near the hypothesis; a hypothesis one room off
stays one room off, because its walls match the next room's.

Everything is vectorised: sort, unique and ``searchsorted`` on packed integer keys.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.core.geometry import inverse, so3_log, transform_points
from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.registration import ScanRegistration
from kimera_multi_py.mapping.semantic_octree import SCALE

OCCUPIED, FREE = np.int8(1), np.int8(-1)
_BITS = 21  # per axis in a packed coarse key
_OFF = 1 << (_BITS - 1)
_MIN_COLUMN = 2  # conflicting cells one above the other that make a conflict
_NEIGHBOURS = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)],
                       dtype=np.int64)


@dataclass(frozen=True)
class MapAgreement:
    """How two maps agree under one hypothesis (coarse cells)."""

    overlap: int  # cells both maps know
    conflicts: int  # of them, occupied in one and clear free space in the other
    verdict: bool | None = None  # a team's verdict over several maps (:func:`team_agreement`)

    @property
    def ratio(self) -> float:
        """Conflicts per known common cell (0 when the maps do not overlap)."""
        return self.conflicts / self.overlap if self.overlap else 0.0

    def refutes(self, min_conflicts: int, min_ratio: float) -> bool:
        """True when the conflicts are too many to be residual misalignment (or the team's
        verdict, for an agreement summed over several robots' maps)."""
        if self.verdict is not None:
            return self.verdict
        return self.conflicts >= min_conflicts and self.ratio >= min_ratio

    def as_dict(self) -> dict[str, float | int | bool]:
        out: dict[str, float | int | bool] = {"overlap": self.overlap, "conflicts": self.conflicts,
                                              "ratio": round(self.ratio, 4)}
        if self.verdict is not None:
            out["refuted"] = self.verdict
        return out


def frame_key(T: np.ndarray) -> tuple[int, ...]:
    """A cache key of frame ``T``: frames within 10 cm and about 1 degree are one (their map
    agreement is the same after refinement)."""
    return (*np.round(T[:3, 3] / 0.1).astype(int).tolist(), *np.round(so3_log(T[:3, :3]) / 0.02).astype(int).tolist())


@dataclass(frozen=True)
class CellStates:
    """A map's known cells: centres (n, 3) in the map's frame and their state (+1 occupied, -1 free).

    What every comparison against this map computes of it alone (its coarse cells, the
    neighbourhood of its occupied ones, its occupied cells prepared for registration) is kept
    with it: a map is compared with several frame hypotheses of another in turn."""

    centres: np.ndarray
    state: np.ndarray
    _derived: dict[object, object] = field(default_factory=dict, compare=False, repr=False)

    def __len__(self) -> int:
        return len(self.state)

    def coarse(self, coarse: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Coarse keys and states in the map's own frame (:func:`_coarse`), and the dilated
        coarse keys of its occupied cells."""
        key = ("coarse", coarse)
        if key not in self._derived:
            k, st = _coarse(self, coarse, None)
            self._derived[key] = (k, st, _dilate(k[st == OCCUPIED]))
        return self._derived[key]  # type: ignore[return-value]

    def registration_target(self) -> tuple[object, object]:
        """The occupied cells prepared for registration (:data:`_REGISTRATION`), as a target or as
        a source: downsampled, with covariances and a search tree."""
        if "target" not in self._derived:
            self._derived["target"] = _REGISTRATION.prepare(self.centres[self.state == OCCUPIED])
        return self._derived["target"]  # type: ignore[return-value]


def occupancy_logodds(values: np.ndarray) -> np.ndarray:
    """``lse(h[1:])`` of fixed-point octree rows (``h[0]`` is the free pivot)."""
    h = values[:, 1:].astype(np.float64) / SCALE
    if h.shape[1] == 0:
        return np.zeros(len(h))
    hmax = h.max(axis=1)
    return hmax + np.log(np.exp(h - hmax[:, None]).sum(axis=1))


def occupancy_states(values: np.ndarray, threshold: float = 1.0) -> np.ndarray:
    """``OCCUPIED`` where :func:`occupancy_logodds` exceeds ``threshold``, ``FREE`` where it is
    below ``-threshold``, else 0; the same states, computing the log-sum-exp only where the
    largest log-odds ``m`` leaves them open. As computed, ``lse = m + log(s)`` with ``1 <= s <= K``
    (``K`` terms, the largest exactly ``exp(0)``): ``m > threshold`` is occupied, and
    ``m + log(K) < -|threshold|`` (with a margin for rounding) is free."""
    v = np.asarray(values)
    k = v.shape[1] - 1 if v.ndim == 2 else 0
    if k <= 0 or not len(v):
        return _states(np.zeros(len(v)), threshold)
    m = v[:, 1:].max(axis=1).astype(np.float64) / SCALE
    occupied = m > threshold
    free = ~occupied & (m + (np.log(k) + 1e-9) < -abs(threshold))  # below -|t|: nor can it be occupied
    state = np.where(occupied, OCCUPIED, np.where(free, FREE, np.int8(0))).astype(np.int8)
    open_ = np.flatnonzero(~(occupied | free))
    if len(open_):
        state[open_] = _states(occupancy_logodds(v[open_]), threshold)
    return state


def _states(lo: np.ndarray, threshold: float) -> np.ndarray:
    """Occupied above ``threshold`` (first), free below ``-threshold``, else 0."""
    return np.where(lo > threshold, OCCUPIED, np.where(lo < -threshold, FREE, np.int8(0))).astype(np.int8)


def cell_states(codes: np.ndarray, values: np.ndarray, resolution: float, threshold: float = 1.0) -> CellStates:
    """The occupied and free cells of finest-level ``codes`` with octree ``values`` (clamped rows)."""
    state = occupancy_states(values, threshold)
    keep = state != 0
    centres = morton.node_centers(np.asarray(codes, np.int64)[keep], np.zeros(int(keep.sum()), np.int8), resolution)
    return CellStates(centres, state[keep])


def _pack(ijk: np.ndarray) -> np.ndarray:
    ijk = ijk.astype(np.int64) + _OFF
    return (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]


def _coarse(cells: CellStates, coarse: float, T: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique coarse keys and their state (occupied wins over free)."""
    pts = cells.centres if T is None else transform_points(T, cells.centres)
    keys = _pack(np.floor(pts / coarse).astype(np.int64))
    occupied = cells.state == OCCUPIED
    occ_keys = np.unique(keys[occupied])
    free_keys = np.setdiff1d(np.unique(keys[~occupied]), occ_keys, assume_unique=True)
    allk = np.concatenate([occ_keys, free_keys])
    state = np.concatenate([np.full(len(occ_keys), OCCUPIED), np.full(len(free_keys), FREE)]).astype(np.int8)
    order = np.argsort(allk)
    return allk[order], state[order]


def _dilate(keys: np.ndarray) -> np.ndarray:
    """``keys`` and their 26 neighbours (sorted, unique)."""
    if len(keys) == 0:
        return keys
    step = (_NEIGHBOURS[:, 0] << (2 * _BITS)) + (_NEIGHBOURS[:, 1] << _BITS) + _NEIGHBOURS[:, 2]
    return np.unique((keys[:, None] + step[None, :]).ravel())


def _member(sorted_keys: np.ndarray, query: np.ndarray) -> np.ndarray:
    if len(sorted_keys) == 0:
        return np.zeros(len(query), dtype=bool)
    i = np.minimum(np.searchsorted(sorted_keys, query), len(sorted_keys) - 1)
    return sorted_keys[i] == query


def map_agreement(a: CellStates, b: CellStates, T_b_a: np.ndarray | None = None, coarse: float = 0.3) -> MapAgreement:
    """Agreement of map ``a`` moved into ``b``'s frame by ``T_b_a`` (identity: same frame) with ``b``."""
    if T_b_a is None:
        ka, sa, dilated_a = a.coarse(coarse)
    else:
        ka, sa = _coarse(a, coarse, T_b_a)
        dilated_a = None
    kb, sb, dilated_b = b.coarse(coarse)
    common, ia, ib = np.intersect1d(ka, kb, assume_unique=True, return_indices=True)
    if len(common) == 0:
        return MapAgreement(0, 0)
    near_a = _member(_dilate(ka[sa == OCCUPIED]) if dilated_a is None else dilated_a, common)
    near_b = _member(dilated_b, common)
    a_in_b_free = (sa[ia] == OCCUPIED) & (sb[ib] == FREE) & ~near_b
    b_in_a_free = (sb[ib] == OCCUPIED) & (sa[ia] == FREE) & ~near_a
    conflict = common[a_in_b_free | b_in_a_free]
    # a displaced wall or piece of furniture conflicts over its height; a lone conflicting cell in
    # its column is a grazing ray or a thin edge, which a correct frame also shows
    _, column, count = np.unique(conflict >> _BITS, return_inverse=True, return_counts=True)
    return MapAgreement(int(len(common)), int((count[column] >= _MIN_COLUMN).sum()))


_REGISTRATION = ScanRegistration(voxel=0.2, max_correspondence=(1.0, 0.5, 0.25), max_iterations=20)


def refined_agreement(a: CellStates, b: CellStates, T_b_a: np.ndarray, coarse: float = 0.3,
                      max_shift: float = 1.0, max_turn: float = 0.2) -> MapAgreement:
    """The better :func:`map_agreement` of ``T_b_a`` itself and of the frame near it where ``a``'s
    occupied cells fit ``b``'s (GICP from ``T_b_a``, converged or not, considered when it moved less than
    ``max_shift`` m and ``max_turn`` rad): a frame is refuted only when no frame near it agrees."""
    T = np.asarray(T_b_a, dtype=np.float64)
    plain = map_agreement(a, b, T, coarse)
    if plain.conflicts == 0:
        return plain
    known = bool((a.state == OCCUPIED).any() and (b.state == OCCUPIED).any())
    # one map is compared under several hypotheses: its preparation is kept with it
    reg = _REGISTRATION.register(b.registration_target(), a.registration_target(), T) if known else None
    # GICP's own convergence flag is not asked for: whether it stopped within its iteration cap
    # varies between builds of the same library, and the score of the frame it reached decides
    if reg is None:
        return plain
    step = inverse(T) @ reg.T
    if np.linalg.norm(step[:3, 3]) > max_shift or np.linalg.norm(so3_log(step[:3, :3])) > max_turn:
        return plain
    refined = map_agreement(a, b, reg.T, coarse)
    return refined if refined.conflicts < plain.conflicts else plain


def team_agreement(per_robot: dict[int, MapAgreement], root: int, min_conflicts: int,
                   min_ratio: float) -> tuple[MapAgreement, list[int], list[int]]:
    """One frame against several robots' maps, each on its own, so that one robot in a wrong frame
    cannot outvote the rest: refuted when it contradicts the frame's ``root`` robot, or more of
    the robots whose maps overlap enough to tell (``min_conflicts / min_ratio`` common cells)
    than agree with it. Returns the summed agreement carrying that verdict, the conflicting
    robots and the agreeing ones."""
    conflicting = sorted(r for r, a in per_robot.items() if a.refutes(min_conflicts, min_ratio))
    enough = min_conflicts / max(min_ratio, 1e-9)
    agreeing = sorted(r for r, a in per_robot.items() if r not in conflicting and a.overlap >= enough)
    refuted = root in conflicting or len(conflicting) > len(agreeing)
    total = MapAgreement(sum(a.overlap for a in per_robot.values()), sum(a.conflicts for a in per_robot.values()),
                         refuted)
    return total, conflicting, agreeing
