"""One robot's people tracks (docs/algorithms/people.md).

Each track is a constant-velocity Kalman filter on the floor plane (state ``x, y, vx, vy``; the
height is a running mean). At a keyframe every track is predicted to the keyframe's stamp, a
detection gates with a track when its Mahalanobis distance under the innovation covariance is
within ``gate_chi2`` and its distance within ``max_gate``, and detections are assigned to tracks
by ``scipy.optimize.linear_sum_assignment`` on the Mahalanobis cost. A detection left over starts
a new track; while that track is young it may turn out to continue a lost one, when the two agree
walking on at constant velocity across the gap in both directions (:meth:`PeopleTracker._reacquire`;
a single detection near where a track was lost is not enough: it is as often another person
walking past the other way). A track is confirmed (born) once ``confirm_hits`` keyframes saw it,
and dies when it went unseen for ``max_unseen`` seconds (``tentative_unseen`` before it is confirmed).
``association = "nearest"`` replaces the motion model by nearest-neighbour association on the
last positions (the baseline that swaps the ids of people who cross).

Frames. Detections come in the robot's current estimate; every track sample is kept in the
reference frame of the submap it was seen from (the submap's pose when the tracker first met
it), and a track's filter state is anchored in the submap of its last update. When PGO moves a
submap (:meth:`PeopleTracker.set_submap_pose`, as :class:`~kimera_multi_py.mapping.objects.ObjectMap`
does) every sample and state anchored there moves with it exactly.

Bad detections (a non-finite centroid or extent, an empty cluster) are dropped and counted in
:attr:`PeopleTracker.dropped`.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.optimize import linear_sum_assignment

from kimera_multi_py.core.geometry import inverse, transform_points
from kimera_multi_py.people.detection import PersonDetections, detect_people

_INFEASIBLE = 1e9
_H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])


@dataclass
class PeopleParams:
    """Person detection and tracking knobs (primitives; see the module docstrings)."""

    enabled: bool = True
    radius: float = 0.3
    """Cluster linking radius (m)."""
    min_core: int = 3
    min_points: int = 10
    max_width: float = 1.2
    min_height: float = 0.25
    max_height: float = 2.4
    min_purity: float = 0.5
    """Share of the points in a detection's voxels that must be its own."""
    view_span: float = 0.9
    """A cluster spanning this share of the view's elevation angles is cut off by the view, not flat."""
    link_angle: float = 0.05
    """Far away, points are linked within this angle (rad) x their range (about two ray spacings)."""
    edge_angle: float = 0.03
    """A detection within this angle (rad) of the image's side edge is cut off by it (0: never)."""
    depth_offset: float = 0.2
    """How far behind the visible points a person's axis lies (m), along the view ray."""
    meas_sigma: float = 0.15
    """Detection position noise, per axis (m)."""
    accel_sigma: float = 1.0
    """Process noise: white acceleration (m/s^2)."""
    init_speed_sigma: float = 1.0
    """Prior speed uncertainty of a new track, per axis (m/s)."""
    gate_chi2: float = 9.21
    """Mahalanobis gate (chi-square, 2 dof, 99 %)."""
    max_gate: float = 1.5
    """Largest distance (m) between a track's prediction and its detection."""
    confirm_hits: int = 2
    """Keyframes that must see a track before it is confirmed."""
    tentative_unseen: float = 2.0
    """Seconds a tentative track survives unseen."""
    max_unseen: float = 15.0
    """Seconds a confirmed track survives unseen."""
    association: Literal["kalman", "nearest"] = "kalman"
    reacquire_after: float = 1.5
    """Seconds unseen before a confirmed track counts as lost (and may be taken up by a young one)."""
    reacquire_slack: float = 0.3
    """Re-acquisition: how far (m) per second unseen a person may stray from walking on at constant
    velocity, added to ``max_gate``; 0: no re-acquisition."""
    reacquire_hits: int = 4
    """A new track may still turn out to continue a lost one until it has this many hits."""
    reacquire_lateral: float = 0.5
    """A person who turned back while unseen walks back within this distance (m) of their line."""
    reacquire_min_speed: float = 0.2
    """Below this speed (m/s) a track has no direction to have turned back from."""
    turn_cos: float = 0.7
    """Turned back: the young track heads at least this much (cosine) against the lost one."""
    line_seconds: float = 5.0
    """Turned back: a lost track's line is fitted to its samples of its last seconds seen."""
    line_min_length: float = 1.0
    """... when they stretch along about this length (m); otherwise its velocity gives the line."""


@dataclass
class Track:
    """One person as one robot follows them; samples are ``(stamp, submap, position in the
    submap's reference frame)`` at every keyframe that saw them."""

    id: int
    x: np.ndarray  # (4,) x, y, vx, vy in the current estimate (at ``last_seen``)
    P: np.ndarray  # (4, 4)
    z: float
    submap: int  # where the filter state is anchored
    last_seen: float
    hits: int = 1
    confirmed: bool = False
    stamps: list[float] = field(default_factory=list)
    submaps: list[int] = field(default_factory=list)
    refs: list[np.ndarray] = field(default_factory=list)


@dataclass
class KeyframePeople:
    """What one keyframe gave the tracker, for evaluation: the detections (positions in the
    reference frame of ``submap``) and the track each one went to (-1: none)."""

    index: int
    stamp: float
    submap: int
    refs: np.ndarray  # (n, 3)
    tracks: np.ndarray  # (n,)


class PeopleTracker:
    """One robot's people (see the module docstring)."""

    reacquired: int = 0
    """Lost tracks a young track turned out to continue (a class default: older checkpoints lack it)."""

    def __init__(self, dynamic_classes: tuple[int, ...], params: PeopleParams | None = None) -> None:
        self.dynamic_classes = tuple(int(c) for c in dynamic_classes)
        self.params = params or PeopleParams()
        self.tracks: dict[int, Track] = {}  # alive
        self.ended: list[Track] = []  # confirmed tracks that died
        self.dropped: Counter[str] = Counter()
        self.log: list[KeyframePeople] = []
        self._next_id = 0
        self._ref: dict[int, np.ndarray] = {}
        self._pose: dict[int, np.ndarray] = {}

    # ---- frames -------------------------------------------------------------------------------
    def set_submap_pose(self, submap: int, pose: np.ndarray) -> None:
        """Record a submap's pose; a later call moves the tracks anchored in it."""
        pose = np.asarray(pose, dtype=np.float64).copy()
        if submap not in self._ref:
            self._ref[submap] = pose.copy()
            self._pose[submap] = pose
            return
        D = pose @ inverse(self._pose[submap])  # how the submap moved
        self._pose[submap] = pose
        R2 = D[:2, :2]
        for t in self.tracks.values():
            if t.submap == submap:
                t.x[:2] = R2 @ t.x[:2] + D[:2, 3]
                t.x[2:] = R2 @ t.x[2:]
                t.z += float(D[2, 3])
                B = np.zeros((4, 4))
                B[:2, :2] = B[2:, 2:] = R2
                t.P = B @ t.P @ B.T

    def correction(self, submap: int) -> np.ndarray:
        """Current pose of a submap's reference frame in the estimate."""
        if submap not in self._ref:
            return np.eye(4)
        return self._pose[submap] @ inverse(self._ref[submap])

    # ---- keyframes ----------------------------------------------------------------------------
    def update(self, index: int, stamp: float, submap: int, points: np.ndarray, labels: np.ndarray,
               sensor: np.ndarray | None = None) -> PersonDetections:
        """Detect people among a keyframe's end points (estimate frame) and track them."""
        p = self.params
        dets = detect_people(points, labels, self.dynamic_classes, sensor, radius=p.radius, min_core=p.min_core,
                             min_points=p.min_points, max_width=p.max_width, min_height=p.min_height,
                             max_height=p.max_height, depth_offset=p.depth_offset, min_purity=p.min_purity,
                             view_span=p.view_span, link_angle=p.link_angle, edge_angle=p.edge_angle,
                             dropped=self.dropped)
        self.step(index, stamp, submap, dets)
        return dets

    def _predict(self, t: Track, stamp: float) -> tuple[np.ndarray, np.ndarray]:
        dt = max(stamp - t.last_seen, 0.0)
        F = np.eye(4)
        F[0, 2] = F[1, 3] = dt
        q = self.params.accel_sigma ** 2
        Q1 = q * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
        Q = np.zeros((4, 4))
        Q[np.ix_([0, 2], [0, 2])] = Q1
        Q[np.ix_([1, 3], [1, 3])] = Q1
        return F @ t.x, F @ t.P @ F.T + Q

    def _cost(self, tracks: list[Track], xy: np.ndarray, stamp: float) -> tuple[np.ndarray, list[tuple]]:
        """Cost (tracks x detections) with infeasible pairs at ``_INFEASIBLE``; the predictions."""
        p = self.params
        R = p.meas_sigma ** 2 * np.eye(2)
        cost = np.full((len(tracks), len(xy)), _INFEASIBLE)
        preds = []
        for i, t in enumerate(tracks):
            if p.association == "nearest":
                d = np.linalg.norm(xy - t.x[:2], axis=1)
                cost[i] = np.where(d <= p.max_gate, d, _INFEASIBLE)
                preds.append((t.x.copy(), t.P.copy()))
                continue
            x, P = self._predict(t, stamp)
            S = _H @ P @ _H.T + R
            y = xy - x[:2]
            d2 = np.einsum("ni,ij,nj->n", y, np.linalg.inv(S), y)
            ok = (d2 <= p.gate_chi2) & (np.linalg.norm(y, axis=1) <= p.max_gate)
            cost[i] = np.where(ok, d2, _INFEASIBLE)
            preds.append((x, P))
        return cost, preds

    def step(self, index: int, stamp: float, submap: int, dets: PersonDetections) -> list[int]:
        """Associate one keyframe's detections (estimate frame) with the tracks; return the track id
        of each valid detection (-1 for none). Bad detections are dropped and counted."""
        p = self.params
        ok = dets.valid()
        if (bad := int((~ok).sum())):
            self.dropped["bad_detections"] += bad
            dets = dets.take(ok)
        stamp = float(stamp)
        tracks = sorted(self.tracks.values(), key=lambda t: t.id)
        xy = dets.centroids[:, :2]
        cost, preds = self._cost(tracks, xy, stamp)
        rows, cols = linear_sum_assignment(cost) if cost.size else (np.zeros(0, int), np.zeros(0, int))
        owner = np.full(len(dets), -1, dtype=np.int64)
        C_inv = inverse(self.correction(submap))
        for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
            if cost[r, c] >= _INFEASIBLE:
                continue
            t = tracks[r]
            x, P = preds[r]
            if p.association == "nearest":
                t.x = np.array([xy[c, 0], xy[c, 1], 0.0, 0.0])
            else:
                S = _H @ P @ _H.T + p.meas_sigma ** 2 * np.eye(2)
                K = P @ _H.T @ np.linalg.inv(S)
                t.x = x + K @ (xy[c] - x[:2])
                t.P = (np.eye(4) - K @ _H) @ P
            t.z = 0.8 * t.z + 0.2 * float(dets.centroids[c, 2])
            t.hits += 1
            t.confirmed |= t.hits >= p.confirm_hits
            self._sample(t, stamp, submap, C_inv)
            owner[c] = t.id
        for c in np.flatnonzero(owner < 0).tolist():
            P0 = np.diag([p.meas_sigma ** 2] * 2 + [p.init_speed_sigma ** 2] * 2)
            t = Track(self._next_id, np.array([xy[c, 0], xy[c, 1], 0.0, 0.0]), P0, float(dets.centroids[c, 2]),
                      submap, stamp, confirmed=p.confirm_hits <= 1)
            self._next_id += 1
            self._sample(t, stamp, submap, C_inv)
            self.tracks[t.id] = t
            owner[c] = t.id
        self._reacquire(stamp, owner)
        for t in list(self.tracks.values()):
            if stamp - t.last_seen > (p.max_unseen if t.confirmed else p.tentative_unseen):
                del self.tracks[t.id]
                if t.confirmed:
                    self.ended.append(t)
        self.log.append(KeyframePeople(int(index), stamp, int(submap),
                                       transform_points(C_inv, dets.centroids).reshape(-1, 3), owner.copy()))
        return owner.tolist()

    def _reacquire(self, stamp: float, owner: np.ndarray) -> None:
        """A young track (updated now, with ``2..reacquire_hits`` hits: it has a velocity) that
        began at least ``reacquire_after`` s after a confirmed track was last seen continues that
        lost track when each, walking on at constant velocity, meets the other across the gap: the
        lost track carried forward to the young one's first sample, and the young one carried back
        to where the lost one was last seen, are each within ``max_gate`` + ``reacquire_slack`` x
        the time spanned. Pairs are chosen by Hungarian assignment on the normalised misfits; the
        lost track takes the young one's samples (and its place in the log), so the person keeps
        one id. A single detection near where a track was lost decides nothing: it is as often
        another person walking past the other way."""
        p = self.params
        if p.reacquire_slack <= 0 or p.association == "nearest":
            return
        young = [t for t in self.tracks.values() if t.last_seen == stamp and 2 <= t.hits <= p.reacquire_hits]
        if not young:
            return
        first = {t.id: (t.stamps[0], self.positions(t)[0, :2]) for t in young}
        before = max(f[0] for f in first.values()) - p.reacquire_after
        lost = [t for t in self.tracks.values() if t.confirmed and t.last_seen <= before]
        if not lost:
            return
        cost = np.full((len(lost), len(young)), _INFEASIBLE)
        for i, old in enumerate(lost):
            for j, new in enumerate(young):
                t0, p0 = first[new.id]
                if old.last_seen > t0 - p.reacquire_after:  # a shorter gap is the motion gate's to bridge
                    continue
                fwd = np.linalg.norm(old.x[:2] + old.x[2:] * (t0 - old.last_seen) - p0)
                bwd = np.linalg.norm(new.x[:2] - new.x[2:] * (stamp - old.last_seen) - old.x[:2])
                tol_f = p.max_gate + p.reacquire_slack * (t0 - old.last_seen)
                tol_b = p.max_gate + p.reacquire_slack * (stamp - old.last_seen)
                if fwd <= tol_f and bwd <= tol_b:
                    cost[i, j] = (fwd / tol_f) ** 2 + (bwd / tol_b) ** 2
                elif (side := self._turned_back(old, new, t0, p0)) is not None:
                    cost[i, j] = 2.0 + side  # after every straight continuation
        for r, c in zip(*linear_sum_assignment(cost), strict=True):
            if cost[r, c] < _INFEASIBLE:
                self._continue(lost[int(r)], young[int(c)], owner)

    def _turned_back(self, old: Track, new: Track, t0: float, p0: np.ndarray) -> float | None:
        """Whether the young track ``new`` (first at ``p0``, ``t0``) is the lost track ``old``'s
        person walking back along their own line: heading the other way, within
        ``reacquire_lateral`` of the line, and where walking on to a turning point and back at the
        two tracks' speeds puts them. Returns the sideways offset as a share of the bound (None: no)."""
        p = self.params
        v1, v2 = float(np.linalg.norm(old.x[2:])), float(np.linalg.norm(new.x[2:]))
        if min(v1, v2) < p.reacquire_min_speed:
            return None
        u, on = self._line(old)
        if float(u @ new.x[2:]) / v2 > -p.turn_cos:
            return None
        side = abs(float((p0 - on) @ np.array([-u[1], u[0]]))) / p.reacquire_lateral
        ahead = float((p0 - old.x[:2]) @ u)
        turn = (t0 - old.last_seen + ahead / v2) / (1.0 / v1 + 1.0 / v2)  # how far on they turned
        return side if side <= 1.0 and turn >= max(ahead, 0.0) - p.max_gate else None

    def _line(self, t: Track) -> tuple[np.ndarray, np.ndarray]:
        """The line a track walked before it was lost: the unit direction (along its velocity) and a
        point. It is fitted to the samples of its last ``line_seconds`` (principal axis, when they
        span ``line_min_length``): the filter's velocity swings by several degrees from one
        detection to the next, which puts its line half a metre off five metres on."""
        p = self.params
        u = t.x[2:] / max(float(np.linalg.norm(t.x[2:])), 1e-9)
        keep = np.asarray(t.stamps) >= t.last_seen - p.line_seconds
        if keep.sum() < 3:
            return u, t.x[:2]
        xy = self.positions(t)[keep, :2]
        mean = xy.mean(axis=0)
        vt = np.linalg.svd(xy - mean, full_matrices=False)[2]
        if np.ptp((xy - mean) @ vt[0]) < p.line_min_length:  # too short a stretch (standing, a step or two)
            return u, t.x[:2]
        d = vt[0] if float(vt[0] @ u) >= 0 else -vt[0]
        return d, mean

    def _continue(self, old: Track, new: Track, owner: np.ndarray) -> None:
        """``old`` takes over ``new`` (which began after ``old`` was last seen): its samples, state and id."""
        old.stamps += new.stamps
        old.submaps += new.submaps
        old.refs += new.refs
        old.x, old.P, old.z, old.submap, old.last_seen = new.x, new.P, new.z, new.submap, new.last_seen
        old.hits += new.hits
        del self.tracks[new.id]
        owner[owner == new.id] = old.id
        for rec in reversed(self.log):
            if rec.stamp < new.stamps[0]:
                break
            rec.tracks[rec.tracks == new.id] = old.id
        self.reacquired += 1

    def _sample(self, t: Track, stamp: float, submap: int, C_inv: np.ndarray) -> None:
        t.last_seen, t.submap = stamp, submap
        t.stamps.append(stamp)
        t.submaps.append(submap)
        t.refs.append(transform_points(C_inv, np.array([[t.x[0], t.x[1], t.z]]))[0])

    # ---- outputs ------------------------------------------------------------------------------
    def confirmed(self) -> list[Track]:
        """Every confirmed track, alive or ended, by id."""
        return sorted([t for t in self.tracks.values() if t.confirmed] + self.ended, key=lambda t: t.id)

    def positions(self, t: Track) -> np.ndarray:
        """A track's samples in the current estimate (n, 3)."""
        out = np.zeros((len(t.refs), 3))
        subs = np.asarray(t.submaps)
        for s in np.unique(subs).tolist():
            m = subs == s
            out[m] = transform_points(self.correction(s), np.asarray(t.refs)[m])
        return out

    def people(self) -> list[dict[str, object]]:
        """The confirmed tracks as plain data: ``id``, ``stamps``, ``positions`` (estimate)."""
        return [{"id": t.id, "stamps": [float(s) for s in t.stamps], "positions": self.positions(t).tolist()}
                for t in self.confirmed()]
