"""What a robot's loop-closure front end keeps (docs/architecture.md): the object constellation
of a keyframe, a verified closure, and the counts of candidates and verifications."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Constellation:
    """Objects seen around a keyframe, in that keyframe's frame."""

    keyframe: int
    stamp: float
    xyz: np.ndarray  # (m, 3)
    classes: np.ndarray  # (m,) class ids
    descriptor: np.ndarray
    cloud: np.ndarray  # (p, 3) semantic points of the window, keyframe frame
    cloud_labels: np.ndarray  # (p,)


@dataclass
class Closure:
    """A verified loop closure: ``Z = T_a^{-1} T_b`` between own keyframe a and peer keyframe b."""

    own_kf: int
    peer: int
    peer_kf: int
    Z: np.ndarray
    inliers: int
    own_pose: np.ndarray  # dead-reckoned poses used by PCM
    peer_pose: np.ndarray
    accepted: bool = False


@dataclass
class LoopClosureStats:
    candidates: int = 0  # verification requests sent (inter) or attempted (intra)
    verified: int = 0  # passed geometric verification
    rejected_verification: int = 0
    rejected_view_angle: int = 0  # of them: the two views faced too far apart (max_view_angle)
