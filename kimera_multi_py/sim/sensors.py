"""Sensor models: a range-category sensor (depth camera or LiDAR pattern) and noisy odometry."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kimera_multi_py.core.geometry import se3_exp
from kimera_multi_py.core.semantics import NUM_CLASSES
from kimera_multi_py.sim.world import Primitives, World


@dataclass
class Scan:
    """One range-category scan in the sensor frame (x forward, y left, z up).

    ``ranges`` are inf where nothing was hit within ``max_range``; ``labels`` are 0 there.
    """

    directions: np.ndarray  # (n, 3) unit rays in the sensor frame
    ranges: np.ndarray  # (n,) float64
    labels: np.ndarray  # (n,) int16
    max_range: float

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.ranges)

    def points(self) -> np.ndarray:
        """End points ``(n, 3)`` in the sensor frame; misses are placed at ``max_range``."""
        r = np.where(self.hit, self.ranges, self.max_range)
        return self.directions * r[:, None]

    def __len__(self) -> int:
        return len(self.ranges)


def ray_pattern(model: str, h_fov_deg: float, v_fov_deg: float, rows: int, cols: int) -> np.ndarray:
    """Unit ray directions ``(rows*cols, 3)``, row-major from top-left, in the sensor frame."""
    h, v = np.deg2rad(h_fov_deg), np.deg2rad(v_fov_deg)
    u = (np.arange(cols) + 0.5) / cols - 0.5  # -0.5 .. 0.5, left to right
    w = 0.5 - (np.arange(rows) + 0.5) / rows  # 0.5 .. -0.5, top to bottom
    W, U = np.meshgrid(w, u, indexing="ij")
    if model == "pinhole":
        d = np.stack([np.ones_like(U), -2 * U * np.tan(h / 2), 2 * W * np.tan(v / 2)], -1)
    else:  # spherical (LiDAR-like): uniform in azimuth and elevation
        az, el = -U * h, W * v
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    d = d.reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def flip_confusion(p: float, k: int = NUM_CLASSES) -> np.ndarray:
    """K x K confusion matrix: keep the label with 1-p, else a uniformly random other class."""
    if k == 1:
        return np.ones((1, 1))
    return np.full((k, k), p / (k - 1)) + np.eye(k) * (1 - p - p / (k - 1))


class RangeCategorySensor:
    """Casts a fixed ray pattern into the world; adds Gaussian range noise and label confusion."""

    def __init__(self, directions: np.ndarray, max_range: float, range_sigma: float,
                 confusion: np.ndarray) -> None:
        self.directions = np.asarray(directions, dtype=float)
        self.max_range = float(max_range)
        self.range_sigma = float(range_sigma)
        self.confusion = np.asarray(confusion, dtype=float)
        self._cum = np.cumsum(self.confusion, axis=1)
        self._cum[:, -1] = 1.0

    def measure(self, world: World, T_world_sensor: np.ndarray, rng: np.random.Generator,
                dynamic: Primitives | None = None) -> tuple[Scan, Scan]:
        """Return ``(noisy, true)`` scans taken from ``T_world_sensor``."""
        R, t = T_world_sensor[:3, :3], T_world_sensor[:3, 3]
        ranges, labels = world.raycast(t, self.directions @ R.T, self.max_range, dynamic)
        truth = Scan(self.directions, ranges, labels, self.max_range)
        hit = np.isfinite(ranges)
        noisy_r = ranges.copy()
        noisy_r[hit] = np.maximum(ranges[hit] + rng.normal(0.0, self.range_sigma, hit.sum()), 0.0)
        noisy_l = labels.copy()
        u = rng.random(hit.sum())
        rows = self._cum[labels[hit] - 1]
        noisy_l[hit] = (np.sum(u[:, None] > rows, axis=1) + 1).astype(np.int16)
        return Scan(self.directions, noisy_r, noisy_l, self.max_range), truth


class OdometryModel:
    """Relative keyframe poses perturbed by ``Exp([rot noise, trans noise])`` on the right."""

    def __init__(self, rot_sigma: float, trans_sigma: float) -> None:
        self.rot_sigma = float(rot_sigma)
        self.trans_sigma = float(trans_sigma)

    def measure(self, T_rel: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        xi = np.concatenate([rng.normal(0.0, self.rot_sigma, 3), rng.normal(0.0, self.trans_sigma, 3)])
        return T_rel @ se3_exp(xi)
