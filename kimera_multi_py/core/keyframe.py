"""The per-keyframe input every source gives an agent: odometry step and a labelled scan."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class KeyframeInput:
    """What a robot's sensors give the agent at a keyframe (sensor frame)."""

    index: int
    stamp: float
    odometry: np.ndarray  # T_{k-1,k}, identity at k = 0
    points: np.ndarray  # (n, 3) end points, misses at max range
    labels: np.ndarray  # (n,) int, 0 for misses
    hit: np.ndarray  # (n,) bool
    max_range: float
