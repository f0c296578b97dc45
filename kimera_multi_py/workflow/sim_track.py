"""One robot's keyframe track in a simulated run: its dead-reckoned and true poses and the
scans the evaluation's reference team map is built from (docs/outputs.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.eval.accuracy import ScanRecord
from kimera_multi_py.sim.simulation import Keyframe


@dataclass
class Track:
    """One robot's estimated (own odometry frame) and true (world) keyframe poses."""

    stamps: list[float] = field(default_factory=list)
    est: list[np.ndarray] = field(default_factory=list)
    true: list[np.ndarray] = field(default_factory=list)
    scans: list[ScanRecord] = field(default_factory=list)  # for the team map (evaluation only)

    def add(self, kf: Keyframe) -> np.ndarray:
        pose = kf.odometry.copy() if not self.est else self.est[-1] @ kf.odometry
        self.scans.append(ScanRecord(kf.scan.points().astype(np.float32), kf.scan.labels, kf.scan.max_range))
        self.stamps.append(kf.stamp)
        self.est.append(pose)
        self.true.append(kf.true_pose)
        return pose
