"""Intra-robot closures against the robot's own odometry: identical rooms 6 m apart.

A robot tours room A, the corridor, room B (same furniture, 6 m east of A) and returns to A,
with the simulator's odometry noise (0.15° and 2 cm per keyframe per axis). A closure that
matches room B to room A is 6 m from the odometry prediction: far beyond the drift over the
tour along this path. The true closure back in room A agrees with odometry.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp
from kimera_multi_py.frontend.pcm import PcmNoise, odometry_consistent_path

STEP = 0.5  # m per keyframe
ROT, TRANS = np.deg2rad(0.15), 0.02  # odometry noise per keyframe, per axis
OFFSET = 6.0  # room B is room A moved 6 m along x


def _path() -> np.ndarray:
    """Waypoints: room A loop, the corridor, room B loop, back to room A."""
    room = np.array([[3.0, 3.6], [1.4, 3.2], [1.6, 2.2], [3.2, 2.0], [3.6, 3.4], [3.0, 3.6]])
    corridor = [[3.0, 6.0], [22.0, 6.0], [1.0, 6.0], [22.0, 6.0], [9.0, 6.0]]  # up and down the corridor twice
    pts = [room, corridor, room + [OFFSET, 0.0], [[9.0, 6.0], [3.0, 6.0]], room]
    return np.concatenate([np.asarray(p, dtype=float) for p in pts])


def _keyframes(wp: np.ndarray) -> np.ndarray:
    poses = []
    for a, b in zip(wp[:-1], wp[1:], strict=True):
        d = b - a
        n = max(int(np.ceil(np.linalg.norm(d) / STEP)), 1)
        yaw = float(np.arctan2(d[1], d[0]))
        for s in np.arange(n) / n:
            p = a + s * d
            poses.append(make_pose(so3_exp(np.array([0.0, 0.0, yaw])), np.array([p[0], p[1], 1.0])))
    return np.stack(poses)


def tour(seed: int = 0) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """True poses, dead reckoning, and the keyframes of the room visits (first A, B, last A)."""
    rng = np.random.default_rng(seed)
    true = _keyframes(_path())
    D = [np.eye(4)]
    for k in range(1, len(true)):
        odo = inverse(true[k - 1]) @ true[k]
        noisy = odo @ make_pose(so3_exp(rng.normal(scale=ROT, size=3)), rng.normal(scale=TRANS, size=3))
        D.append(D[-1] @ noisy)
    D = np.stack(D)
    D = true[0] @ D
    in_a = np.flatnonzero((true[:, 0, 3] < 6.0) & (true[:, 1, 3] < 5.0))
    in_b = np.flatnonzero((true[:, 0, 3] > 6.0) & (true[:, 0, 3] < 12.0) & (true[:, 1, 3] < 5.0))
    return true, D, {"a_first": int(in_a[2]), "b": int(in_b[2]), "a_last": int(in_a[-3])}


def _noise() -> PcmNoise:
    per_m = 1.0 / np.sqrt(STEP)  # the agent's model: per-keyframe noise as a random walk per metre
    return PcmNoise(closure_rot=0.05, closure_trans=0.15, odom_rot_per_m=ROT * per_m, odom_trans_per_m=TRANS * per_m)


def test_aliased_intra_candidate_six_metres_off_is_rejected() -> None:
    for seed in range(5):
        true, D, kf = tour(seed)
        a, b = kf["a_first"], kf["b"]
        # room B's keyframe seen as the same spot of room A: the closure claims it is 6 m west
        shift = make_pose(np.eye(3), np.array([-OFFSET, 0.0, 0.0]))
        alias = inverse(true[a]) @ shift @ true[b]
        predicted = inverse(D[a]) @ D[b]
        assert abs(np.linalg.norm((inverse(alias) @ predicted)[:3, 3]) - OFFSET) < 1.5
        span = (b - a) * STEP
        assert span > 80.0  # a long way round (a straight-line drift bound admits 6 m here)
        assert not odometry_consistent_path(alias[None], [a], [b], D, _noise(), STEP)[0]


def test_true_intra_closure_after_a_long_tour_is_kept() -> None:
    for seed in range(5):
        true, D, kf = tour(seed)
        a, b = kf["a_first"], kf["a_last"]
        Z = inverse(true[a]) @ true[b]
        assert (b - a) * STEP > 100.0
        assert odometry_consistent_path(Z[None], [a], [b], D, _noise(), STEP)[0]


def test_bad_keyframes_raise() -> None:
    _, D, _ = tour(0)
    try:
        odometry_consistent_path(np.eye(4)[None], [0], [len(D)], D, _noise(), STEP)
    except ValueError as exc:
        assert "outside" in str(exc)
    else:
        raise AssertionError("expected ValueError")
