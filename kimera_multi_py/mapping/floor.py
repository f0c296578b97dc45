"""The floor as an absolute reference for roll, pitch and height.

A ground robot drives on one floor, and its range sensor sees that floor at most keyframes. A
plane fitted to the points labelled ``floor`` gives the keyframe's roll, pitch and height above
the floor directly, the way gravity gives an IMU its roll and pitch. Scan-to-map registration
drifts in those three directions like in any other: on office with 3 robots, the
registration-refined chain ended 0.04-0.26 m off in height (RMS over each run). Measured against
the floor seen at the start, the chain stops drifting in them; yaw and the position along the
floor keep the registration's (the plane says nothing about them).

* :func:`fit_plane`: least squares on the points near a guess of the plane, with the points
  beyond ``3 x RMS`` dropped a few times (mislabelled points, furniture standing on the floor).
  One SVD per iteration, no loop over points.
* :class:`FloorReference`: the floor plane in the robot's own frame, taken from the first good
  fit (the sensor frame's z axis points up, REP 103, so that fit must be nearly level). Each
  later fit, gated against the plane the chain predicts, moves the keyframe's pose towards it:
  the smallest rotation and the shift along the normal that make the prediction match the fit,
  each scaled by a one-state Kalman gain. The chain's tilt and height uncertainty grows by
  ``step_sigmas`` per keyframe; a fit's own uncertainty comes from its residuals and the spread
  of its points (:meth:`Plane.uncertainty`; a patch of floor seen at the foot of a wall fixes
  the tilt poorly), never below ``min_sigmas``. Taking every fit as exact, as this did first,
  passed each fit's noise into the chain: on office seed 2 (robot 0), pitch 0.25 degrees and height
  1.2 cm RMS against 0.12 degrees and 1.1 cm filtered.

A keyframe with too little floor in view (facing a wall) keeps its pose. A fit far from the
prediction (a ramp, another storey, a mislabelled surface) is not used: the robot then drifts
as before until it sees the reference floor again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kimera_multi_py.core.geometry import inverse, so3_exp

_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Plane:
    """The points ``p`` with ``normal · p + offset = 0``; the normal points to the sensor's side."""

    normal: np.ndarray  # (3,) unit
    offset: float
    inliers: int = 0
    rms: float = 0.0  # of the inliers' distances (m)
    centroid: np.ndarray | None = None  # of the inliers
    spread: float = 0.0  # the inliers' least in-plane variance (m^2): how well they fix the tilt

    def uncertainty(self, at: np.ndarray) -> tuple[float, float]:
        """Standard deviations of the normal's direction (rad) and of the plane's height at the
        point ``at`` (m), from the residuals as independent point noise."""
        n = max(self.inliers, 1)
        tilt2 = self.rms**2 / (n * max(self.spread, 1e-6))
        lever2 = 0.0  # squared distance along the plane from the points' centroid to ``at``
        if self.centroid is not None:
            d = np.asarray(at, dtype=np.float64) - self.centroid
            lever2 = float(d @ d - (d @ self.normal) ** 2)
        return float(np.sqrt(tilt2)), float(np.sqrt(self.rms**2 / n + lever2 * tilt2))

    def transformed(self, T: np.ndarray) -> Plane:
        """The same plane in the frame ``A`` when this one is in frame ``B`` and ``T = T_A_B``."""
        n = T[:3, :3] @ self.normal
        c = None if self.centroid is None else T[:3, :3] @ self.centroid + T[:3, 3]
        return Plane(n, float(self.offset - n @ T[:3, 3]), self.inliers, self.rms, c, self.spread)


def fit_plane(points: np.ndarray, guess: Plane, band: float = 0.2, min_points: int = 50,
              iterations: int = 6) -> Plane | None:
    """The plane through ``points`` ``(n, 3)`` near ``guess`` (within ``band`` metres of it), or
    None when fewer than ``min_points`` support it. The normal is oriented like the guess's."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = P[np.abs(P @ guess.normal + guess.offset) < band]
    if len(P) < min_points:
        return None
    n, d, rms, spread = guess.normal, guess.offset, float("inf"), 0.0
    c = P.mean(axis=0)
    for _ in range(iterations):
        c = P.mean(axis=0)
        _, sv, vt = np.linalg.svd(P - c, full_matrices=False)
        n, spread = vt[-1], float(sv[1] ** 2 / len(P))
        n = n if n @ guess.normal >= 0 else -n
        d = float(-n @ c)
        r = np.abs(P @ n + d)
        rms = float(np.sqrt(np.mean(r**2)))
        keep = r <= max(3.0 * rms, 1e-3)
        if keep.all() or keep.sum() < min_points:
            break
        P = P[keep]
    return Plane(n, d, len(P), rms, c, spread)


@dataclass
class FloorStats:
    corrected: int = 0  # keyframes whose roll, pitch and height the floor set
    missing: int = 0  # too little floor in view
    gated: int = 0  # a fit too far from the predicted floor: not used


class FloorReference:
    """One robot's floor in its own frame, and the pose corrections it gives (module docstring).

    ``band``: metres around the predicted floor that a point may be to count; ``max_rms``: the
    largest residual of a fit used as the reference; ``max_tilt``: the largest angle (rad)
    between that first fit's normal and the sensor's up axis; ``gate_angle`` (rad) and
    ``gate_offset`` (m): how far a later fit may be from the predicted floor to be used;
    ``step_sigmas``: the chain's tilt (rad) and height (m) noise per keyframe; ``min_sigmas``:
    the least uncertainty of a fit's tilt and height.
    """

    def __init__(self, band: float = 0.2, min_points: int = 50, max_rms: float = 0.03,
                 max_tilt: float = np.deg2rad(15.0), gate_angle: float = np.deg2rad(3.0),
                 gate_offset: float = 0.15, step_sigmas: tuple[float, float] = (np.deg2rad(0.08), 0.01),
                 min_sigmas: tuple[float, float] = (np.deg2rad(0.05), 0.005)) -> None:
        if (band <= 0 or min_points < 3 or max_rms <= 0 or gate_angle <= 0 or gate_offset <= 0
                or min(step_sigmas) <= 0 or min(min_sigmas) <= 0):
            raise ValueError("floor: band, max_rms, the gates and the sigmas must be > 0, and min_points >= 3")
        self.band = float(band)
        self.min_points = int(min_points)
        self.max_rms = float(max_rms)
        self.max_tilt = float(max_tilt)
        self.gate_angle = float(gate_angle)
        self.gate_offset = float(gate_offset)
        self.q = np.square(np.asarray(step_sigmas, dtype=np.float64))  # per keyframe: tilt, height
        self.r_min = np.square(np.asarray(min_sigmas, dtype=np.float64))
        self.variance = np.zeros(2)  # of the chain's tilt and height against the reference
        self.plane: Plane | None = None  # the floor in the robot's own frame
        self.stats = FloorStats()

    def correct(self, pose: np.ndarray, floor: np.ndarray) -> np.ndarray:
        """The pose (own frame) of a keyframe whose points labelled floor are ``floor`` (sensor
        frame), moved in roll, pitch and height onto the reference floor; ``pose`` itself when
        the floor cannot tell."""
        pose = np.asarray(pose, dtype=np.float64)
        pts = np.asarray(floor, dtype=np.float64).reshape(-1, 3)
        if self.plane is None:
            self._adopt(pose, pts)
            return pose
        self.variance += self.q
        predicted = self.plane.transformed(inverse(pose))
        fit = fit_plane(pts, predicted, self.band, self.min_points)
        if fit is None:
            self.stats.missing += 1
            return pose
        axis = np.cross(predicted.normal, fit.normal)
        angle = float(np.arctan2(np.linalg.norm(axis), predicted.normal @ fit.normal))
        shift = fit.offset - predicted.offset
        innovation = self.variance + np.maximum(np.square(fit.uncertainty(np.zeros(3))), self.r_min)
        if angle > self.gate_angle or abs(shift) > self.gate_offset:
            self.stats.gated += 1
            return pose
        gain = self.variance / innovation
        self.variance *= 1.0 - gain
        out = pose.copy()
        if angle > 0:  # R' = R Exp(-angle * axis) maps the predicted normal onto the fitted one
            out[:3, :3] = pose[:3, :3] @ so3_exp(-gain[0] * angle * axis / np.linalg.norm(axis))
        # along the reference normal, by the fitted height's difference from the prediction
        out[:3, 3] = pose[:3, 3] + gain[1] * shift * self.plane.normal
        self.stats.corrected += 1
        return out

    def _adopt(self, pose: np.ndarray, pts: np.ndarray) -> None:
        """The first nearly level, tight fit below the sensor becomes the reference."""
        if len(pts) < self.min_points:
            self.stats.missing += 1
            return
        fit = fit_plane(pts, Plane(_UP, -float(np.median(pts[:, 2]))), self.band, self.min_points)
        if fit is None or fit.rms > self.max_rms or fit.normal @ _UP < np.cos(self.max_tilt) or fit.offset <= 0:
            self.stats.missing += 1
            return
        self.plane = fit.transformed(pose)
