"""The walls' axes as an absolute reference for yaw.

Scan registration drifts in yaw like a gyro does: on office, 0.09 degrees per keyframe, a random
walk that reaches a degree within a hundred keyframes, and a degree turns a point 8 m away by
14 cm. Man-made buildings give the same cure a compass gives: their walls run along two
perpendicular directions (the Manhattan frame). Each keyframe's wall points give those
directions' heading in the robot's own frame (:func:`grid_heading`: the 4-fold circular mean of
the wall normals, refined on the wall planes); the first keyframe that sees coherent walls fixes
the reference, and every later one measures the chain's yaw error against it (modulo 90 degrees).

:class:`HeadingReference` fuses those measurements with the chain like a one-state Kalman filter:
the chain's yaw uncertainty grows by ``step_sigma`` per keyframe (a random walk) and a measurement
of noise ``r`` pulls it back by the gain ``P / (P + r)``. The pose turns about its own
position, so the correction is a pure yaw. A measurement farther than ``gate`` standard
deviations from the prediction and than ``min_gate`` (walls off the grid: a diagonal wall, a
round room) or with incoherent votes is not used; the chain then drifts as before. Where no
walls run along a common grid the robot never adopts a reference and nothing changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kimera_multi_py.mapping.axes import upright, vertical_surfaces


@dataclass
class HeadingStats:
    corrected: int = 0  # keyframes whose yaw the walls set
    missing: int = 0  # too few coherent wall votes
    gated: int = 0  # walls off the reference grid: not used


def _wrap90(angle: float) -> float:
    """``angle`` (rad) modulo 90 degrees, into ``[-45, 45)`` degrees."""
    return float((angle + np.pi / 4) % (np.pi / 2) - np.pi / 4)


def grid_heading(points: np.ndarray, min_votes: int = 50, min_coherence: float = 0.6,
                 tolerance: float = np.deg2rad(15.0), offset_bin: float = 0.15,
                 min_plane: int = 15) -> tuple[float, float] | None:
    """The heading of the walls' grid (rad, modulo 90 degrees) in the frame of ``points``
    (upright), and its standard deviation; None when the walls do not show one.

    The normals' 4-fold circular mean gives a coarse heading (a few tenths of a degree: each
    normal comes from 8 neighbours). The wall planes then refine it: the points whose normal is
    within ``tolerance`` of an axis are binned by their offset along it (``offset_bin``), a bin
    of at least ``min_plane`` points is a wall, and one small angle ``theta`` turns every wall,
    each with its own offset, to fit its points best (least squares, then again without the
    points beyond 3 sigma). A 3 m wall with 2 cm range noise fixes ``theta`` to about 0.1 degree.
    """
    P, phi = vertical_surfaces(points)
    votes = np.exp(4j * phi).sum()
    if len(phi) < min_votes or abs(votes) < min_coherence * len(phi):
        return None
    coarse = float(np.angle(votes)) / 4.0
    turns = np.round((phi - coarse) / (np.pi / 2))
    on = np.abs(phi - coarse - turns * np.pi / 2) < tolerance
    axis = turns[on].astype(np.int64) % 2  # a wall's normal along the first or the second axis
    a = coarse + axis * np.pi / 2
    u = np.c_[np.cos(a), np.sin(a)]
    c = np.einsum("ni,ni->n", P[on, :2], u)  # offset along the normal
    t = np.einsum("ni,ni->n", P[on, :2], np.c_[-u[:, 1], u[:, 0]])  # position along the wall
    _, plane = np.unique(np.c_[axis, np.floor(c / offset_bin).astype(np.int64)], axis=0, return_inverse=True)
    plane = plane.ravel()
    keep = np.bincount(plane)[plane] >= min_plane
    theta, var = 0.0, np.inf
    for _ in range(2):
        if keep.sum() < min_plane:
            return None
        p = np.unique(plane[keep], return_inverse=True)[1].ravel()
        n = np.bincount(p).astype(float)
        dt = t[keep] - (np.bincount(p, t[keep]) / n)[p]
        dc = c[keep] - (np.bincount(p, c[keep]) / n)[p]
        stt = float(dt @ dt)
        if stt <= 0:
            return None
        theta = -float(dt @ dc) / stt  # the walls run at coarse + theta: c = c0 - theta t
        r = dc + theta * dt
        sigma2 = float(r @ r) / max(len(r) - len(n) - 1, 1)
        var = sigma2 / stt
        outlier = np.zeros_like(keep)
        outlier[np.flatnonzero(keep)] = np.abs(r) > 3.0 * np.sqrt(sigma2)
        if not outlier.any():
            break
        keep &= ~outlier
    return _wrap90(coarse + theta), float(np.sqrt(var))


def rotate_yaw(pose: np.ndarray, angle: float) -> np.ndarray:
    """``pose`` turned by ``angle`` (rad) about the vertical through its own position."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.asarray(pose, dtype=np.float64).copy()
    out[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ out[:3, :3]
    return out


class HeadingReference:
    """One robot's wall grid in its own frame, and the yaw corrections it gives (module doc).

    ``step_sigma``: the chain's yaw noise per keyframe (rad); ``measurement_sigma``: one
    keyframe's wall heading noise (rad); ``min_votes`` and ``min_coherence``: the wall normals a
    measurement needs, and the length of their 4-fold resultant over their number; ``gate``: in
    standard deviations of the innovation, but never tighter than ``min_gate`` (rad), so that a
    chain that drifted faster than ``step_sigma`` says is still pulled back; ``sigma_scale``: a
    fit's standard deviation (from its residuals, as if independent) times this is its noise,
    never below ``measurement_sigma``. Against the truth the fits erred 0.11-0.13 degrees on
    office and 0.22-0.28 on tiny (384 rays), 4 and 2.5 times what their residuals say:
    neighbouring points' errors are not independent. Taken at face value, the sparse sensor's
    fits passed their noise into the chain and tiny's twin-room run lost its true closures.
    """

    def __init__(self, step_sigma: float = np.deg2rad(0.1), measurement_sigma: float = np.deg2rad(0.15),
                 min_votes: int = 50, min_coherence: float = 0.6, gate: float = 3.0,
                 min_gate: float = np.deg2rad(2.0), sigma_scale: float = 4.0) -> None:
        if step_sigma <= 0 or measurement_sigma <= 0 or gate <= 0 or not 0 < min_coherence <= 1:
            raise ValueError("heading: the sigmas and the gate must be > 0, min_coherence in (0, 1]")
        self.q = float(step_sigma) ** 2
        self.r = float(measurement_sigma) ** 2  # the least a measurement's variance is taken to be
        self.min_votes = int(min_votes)
        self.min_coherence = float(min_coherence)
        self.gate = float(gate)
        self.min_gate = float(min_gate)
        self.sigma_scale = float(sigma_scale)
        self.reference: float | None = None  # the grid's heading in the robot's own frame (rad)
        self.variance = 0.0  # of the chain's yaw against the reference (rad^2)
        self.stats = HeadingStats()

    def correct(self, pose: np.ndarray, walls: np.ndarray) -> np.ndarray:
        """The pose (own frame, upright) of a keyframe whose points labelled wall are ``walls``
        (sensor frame), turned in yaw towards the reference grid; ``pose`` when the walls
        cannot tell."""
        pose = np.asarray(pose, dtype=np.float64)
        self.variance += self.q
        fit = grid_heading(np.asarray(walls, dtype=np.float64).reshape(-1, 3) @ pose[:3, :3].T,
                           self.min_votes, self.min_coherence) if upright(pose) else None
        if fit is None:
            self.stats.missing += 1
            return pose
        measured, sigma = fit
        if self.reference is None:
            self.reference, self.variance = measured, 0.0
            return pose
        innovation = _wrap90(measured - self.reference)
        s = self.variance + max((self.sigma_scale * sigma) ** 2, self.r)
        if abs(innovation) > max(self.gate * np.sqrt(s), self.min_gate):
            self.stats.gated += 1
            return pose
        gain = self.variance / s
        self.variance *= 1.0 - gain
        self.stats.corrected += 1
        return rotate_yaw(pose, -gain * innovation)
