"""Structure axes: the dominant horizontal directions of a map's walls (its Manhattan frame).

Object boxes are axis-aligned in this frame (:class:`.objects.Landmark`), as man-made buildings
align their furniture with their walls. An axis-aligned box of a partial view depends on the axes
it is taken in: the visible faces of a table seen from one corner span an L, whose box in axes
turned 30 degrees from the table's is off-centre by a large part of the table. The map's own axes
are arbitrary (the robot's heading when it started, or when a submap began), the walls' are not.

Each keyframe's structure points give surface normals (the least principal axis of a point's
``k`` neighbours, Pauly et al.'s normal estimate); vertical surfaces (``|n_z| < max_normal_z``)
vote with ``exp(4 i phi)``, ``phi`` the heading of their normal, so that the four directions of a
Manhattan frame vote alike (the 4-fold circular mean). A keyframe whose normals are mostly
oblique (the map's frame is not upright) does not vote. Votes are kept per submap in the submap's
reference frame and turned by the submap's current correction when summed, so the axes re-anchor
exactly with the submaps. Walls off the Manhattan grid only weaken the vote; without enough
support (``min_support`` votes, or a resultant shorter than ``min_coherence`` times their number) there are
no axes and every box keeps its own reference frame's.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

_LEVEL = 0.95  # |n_z| above this: a horizontal surface (within 18 degrees)
_UPRIGHT = np.cos(np.radians(10.0))  # a correction turning z by more than 10 degrees is no yaw


def upright(T: np.ndarray) -> bool:
    """Does a pose or a rotation keep +z within 10 degrees (so that it acts as a yaw)?"""
    return bool(T[2, 2] >= _UPRIGHT)


def heading(T: np.ndarray) -> float:
    """Yaw (rad) of a pose's or a rotation's x axis about +z."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def vertical_surfaces(points: np.ndarray, k: int = 8, max_spread: float = 0.5, max_normal_z: float = 0.3,
                      voxel: float = 0.1, max_points: int = 1024,
                      max_oblique: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """The points on vertical surfaces and the headings ``phi`` of their normals (rad).

    The points are thinned to one per ``voxel`` (dense patches do not outvote the rest) and then
    to at most ``max_points``: a few hundred settle the axes. Nothing when more than
    ``max_oblique`` of the normals are neither vertical nor horizontal: the frame is not upright
    (in an upright frame 5-7 % of a keyframe's structure normals are, at edges; in a frame tilted
    by tens of degrees, half or more)."""
    none = (np.zeros((0, 3)), np.zeros(0))
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    _, first = np.unique(np.floor(P / voxel).astype(np.int64), axis=0, return_index=True)
    P = P[np.sort(first)]
    P = P[:: -(-len(P) // max_points) or 1]
    if len(P) <= k:
        return none
    dist, idx = cKDTree(P).query(P, k=k)
    ok = dist[:, -1] <= max_spread  # a neighbourhood spread over the room is no surface
    if not ok.any():
        return none
    nb = P[idx[ok]]
    d = nb - nb.mean(axis=1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))
    n = vec[:, :, 0]  # eigenvalues ascend: the normal is the least principal axis
    nz = np.abs(n[:, 2])
    if np.mean((nz >= max_normal_z) & (nz <= _LEVEL)) > max_oblique:
        return none
    vertical = nz < max_normal_z
    return P[ok][vertical], np.arctan2(n[vertical, 1], n[vertical, 0])


def wall_votes(points: np.ndarray, **kwargs: float) -> tuple[complex, int]:
    """Sum of ``exp(4 i phi)`` over the points on vertical surfaces (:func:`vertical_surfaces`,
    whose keywords it takes), and their number."""
    _, phi = vertical_surfaces(points, **kwargs)  # type: ignore[arg-type]
    return complex(np.exp(4j * phi).sum()), int(len(phi))


class StructureAxes:
    """The votes of every submap's walls, in the submap's reference frame (see the module doc)."""

    def __init__(self, min_support: float = 50.0, min_coherence: float = 0.3) -> None:
        self.min_support = float(min_support)
        self.min_coherence = float(min_coherence)
        self._votes: dict[int, np.ndarray] = {}  # per submap: [sum cos 4phi, sum sin 4phi, votes]

    def add(self, submap: int, points_world: np.ndarray, correction: np.ndarray) -> None:
        """Vote with one keyframe's structure points (world frame), seen in ``submap``, whose
        reference frame the world reaches through ``correction``."""
        if not upright(correction):
            return
        z, n = wall_votes(points_world)
        if n == 0:
            return
        # a heading in the world is the heading in the reference frame plus the correction's yaw
        z *= np.exp(-4j * heading(correction))
        self._votes[submap] = self._votes.get(submap, np.zeros(3)) + np.array([z.real, z.imag, n])

    def yaw(self, correction: Callable[[int], np.ndarray]) -> float | None:
        """The heading of the walls' axes in the world now (in ``[-pi/4, pi/4)``), each submap at
        ``correction(submap)``; None without enough coherent support."""
        # a submap turned out of the upright since it voted no longer shows where its walls run
        used = [(v, correction(s)) for s, v in self._votes.items()]
        used = [(v, C) for v, C in used if upright(C)]
        total = sum((complex(v[0], v[1]) * np.exp(4j * heading(C)) for v, C in used), start=0j)
        support = sum(float(v[2]) for v, _ in used)
        if support < self.min_support or abs(total) < self.min_coherence * support:
            return None
        return float(np.angle(total) / 4.0)
