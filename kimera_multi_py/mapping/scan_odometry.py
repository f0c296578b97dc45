"""Scan-to-map odometry: each keyframe's scan registered to the robot's recent local map.

The local map is the last ``window`` keyframes' scans placed at their registration-refined
poses (the robot's own frame; PGO never moves it). Each new scan is registered to it from the
odometry's prediction (:class:`~kimera_multi_py.mapping.registration.ScanRegistration`), and
the result becomes a second measurement of the keyframe step: ``Z = R_{k-1}^-1 T``, with the
information of the registration's Hessian restricted to the directions where it is at least
``min_ratio`` times the odometry's (:func:`constrained_information`). A registration that
disagrees with the odometry beyond ``gate`` (squared Mahalanobis distance under the
odometry's noise) is not trusted at all. The step the robot chains is the fusion of both.

With a :class:`~kimera_multi_py.mapping.floor.FloorReference`, each fused pose is then moved in
roll, pitch and height onto the floor the keyframe sees (the points labelled floor), so the chain
does not drift in those three directions; with a
:class:`~kimera_multi_py.mapping.heading.HeadingReference`, the walls' grid then does the same
for yaw. The step returned is the one to the corrected pose.

The state is plain numpy (the window's clouds are rebuilt into library objects at every
keyframe), so a checkpoint restores it exactly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from kimera_multi_py.core.geometry import inverse, se3_exp, se3_log, transform_points
from kimera_multi_py.mapping.floor import FloorReference
from kimera_multi_py.mapping.heading import HeadingReference
from kimera_multi_py.mapping.registration import ScanRegistration, constrained_information, fuse


@dataclass
class ScanOdometryStats:
    registered: int = 0  # registration used (possibly in some directions only)
    degenerate: int = 0  # some direction fell back to the odometry
    gated: int = 0  # disagreed with the odometry: not used
    failed: int = 0  # too few points
    seconds: float = 0.0  # wall time spent registering (a machine measure)


class ScanOdometry:
    """One robot's scan-to-map odometry (see the module docstring)."""

    def __init__(self, registration: ScanRegistration, odom_information: np.ndarray, window: int = 8,
                 min_ratio: float = 1.0, gate: float = 25.0, floor: FloorReference | None = None,
                 heading: HeadingReference | None = None) -> None:
        if window < 1:
            raise ValueError(f"scan odometry: the local map needs a window of >= 1 keyframes, not {window}")
        self.registration = registration
        self.odom_information = np.asarray(odom_information, dtype=np.float64)
        self.window = int(window)
        self.min_ratio = float(min_ratio)
        self.gate = float(gate)
        self.floor = floor
        self.heading = heading
        self.poses: list[np.ndarray] = []  # registration-refined chain R_k, own frame
        self.clouds: dict[int, np.ndarray] = {}  # the window's scans, sensor frame, float32
        self.edges: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # k -> (Z_{k-1,k}, information)
        self.stats = ScanOdometryStats()

    def step(self, k: int, odometry: np.ndarray, points: np.ndarray, floor: np.ndarray | None = None,
             walls: np.ndarray | None = None) -> np.ndarray:
        """Register keyframe ``k``'s scan ``points`` (sensor frame) and return the fused step
        ``T_{k-1,k}`` (the odometry itself where the registration cannot tell). ``floor`` and
        ``walls``: the scan's points labelled floor and wall, for the floor and heading references
        (none: no such correction)."""
        if k != len(self.poses):
            raise ValueError(f"scan odometry: keyframe {k} out of order (expected {len(self.poses)})")
        odometry = np.asarray(odometry, dtype=np.float64)
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        step = odometry
        if k == 0:
            self.poses.append(odometry.copy())
        else:
            t0 = time.perf_counter()
            step = self._register(k, odometry, pts)
            self.stats.seconds += time.perf_counter() - t0
            self.poses.append(self.poses[-1] @ step)
        corrected = False
        if self.floor is not None and floor is not None:
            self.poses[-1] = self.floor.correct(self.poses[-1], floor)
            corrected = True
        if self.heading is not None and walls is not None:
            self.poses[-1] = self.heading.correct(self.poses[-1], walls)
            corrected = True
        if corrected and k:
            step = inverse(self.poses[-2]) @ self.poses[-1]
        self.clouds[k] = pts
        self.clouds.pop(k - self.window, None)
        return step

    def _register(self, k: int, odometry: np.ndarray, pts: np.ndarray) -> np.ndarray:
        prev = self.poses[-1]
        window = [j for j in range(max(0, k - self.window), k) if j in self.clouds]
        target = np.concatenate([transform_points(self.poses[j], self.clouds[j]) for j in window])
        res = self.registration.register(target, pts, prev @ odometry)
        if res is None or not res.converged:
            self.stats.failed += 1
            return odometry
        Z = inverse(prev) @ res.T
        kept = constrained_information(res.information, self.odom_information, self.min_ratio)
        if not np.any(kept.information):
            self.stats.degenerate += 1
            return odometry
        d = se3_log(inverse(odometry) @ Z)
        if kept.prior_distance(d) > self.gate:
            self.stats.gated += 1
            return odometry
        self.stats.registered += 1
        self.stats.degenerate += kept.degenerate
        # the factor's measurement: the registration where it knows, the odometry where it does not
        # (a degenerate registration slides along the corridor; no use of Z may see that)
        Z = odometry @ se3_exp(kept.project(d))
        self.edges[k] = (Z, kept.information)
        return fuse(odometry, self.odom_information, Z, kept.information)
