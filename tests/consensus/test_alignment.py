"""Robust frame alignment: GNC rotation + translation averaging, with 50% outliers."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.alignment.frames import align_frames, gnc_rotation_average, supported_edges
from kimera_multi_py.core.geometry import inverse, make_pose, se3_exp, so3_exp


def scene(k: int, outlier_fraction: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    T_team_own = se3_exp(np.array([0.4, -1.0, 2.0, 5.0, -3.0, 1.0]))
    own = se3_exp(rng.normal(scale=[0.5, 0.5, 0.5, 5, 5, 5], size=(k, 6)))
    nb = se3_exp(rng.normal(scale=[0.5, 0.5, 0.5, 5, 5, 5], size=(k, 6)))  # team frame
    own_is_i = rng.random(k) < 0.5
    own_team = T_team_own @ own
    Z = np.where(own_is_i[:, None, None], inverse(own_team) @ nb, inverse(nb) @ own_team)
    Z = Z @ se3_exp(rng.normal(scale=0.01, size=(k, 6)))  # measurement noise
    bad = rng.permutation(k)[: int(outlier_fraction * k)]
    Z[bad] = se3_exp(rng.normal(scale=[2, 2, 2, 10, 10, 10], size=(len(bad), 6)))
    outlier = np.zeros(k, bool)
    outlier[bad] = True
    return own, nb, Z, own_is_i, T_team_own, outlier


def test_alignment_with_half_outliers() -> None:
    own, nb, Z, own_is_i, T_true, outlier = scene(40, 0.5)
    res = align_frames(own, nb, Z, own_is_i)
    assert res.ok
    assert np.array_equal(res.inliers, ~outlier)
    err = inverse(T_true) @ res.T
    assert np.linalg.norm(err[:3, 3]) < 0.1
    assert np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1)) < 0.01


def test_alignment_needs_three_inliers() -> None:
    own, nb, Z, own_is_i, _, _ = scene(2, 0.0)
    assert not align_frames(own, nb, Z, own_is_i).ok
    own, nb, Z, own_is_i, T_true, _ = scene(3, 0.0)
    res = align_frames(own, nb, Z, own_is_i)
    assert res.ok and np.allclose(res.T, T_true, atol=0.15)  # 3 noisy edges, long lever arms


def test_rotation_average_rejects_outliers() -> None:
    rng = np.random.default_rng(3)
    R = so3_exp(np.array([0.3, 0.2, -0.1]))
    good = R @ so3_exp(rng.normal(scale=0.02, size=(12, 3)))
    axis = rng.normal(size=(10, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    bad = R @ so3_exp(axis * rng.uniform(1.0, 3.0, size=(10, 1)))  # >= 1 rad away
    est, w = gnc_rotation_average(np.concatenate([good, bad]), barc2=8 * np.sin(0.25) ** 2)
    assert np.all(w[:12] > 0.5) and np.all(w[12:] < 0.5)
    assert np.linalg.norm(est - R) < 0.02
    assert make_pose(est).shape == (4, 4)


def test_support_screen_keeps_every_consistent_group() -> None:
    # 20 true edges, 10 random outliers, then 12 aliased edges: one consistent group 6 m off
    own, nb, Z, own_is_i, _, outlier = scene(30, 1 / 3, seed=1)
    own2, nb2, Z2, own_is_i2, _, _ = scene(12, 0.0, seed=2)
    nb2 = make_pose(np.eye(3), np.array([6.0, 0.0, 0.0])) @ nb2  # the identical room, elsewhere
    keep = supported_edges(np.concatenate([own, own2]), np.concatenate([nb, nb2]),
                           np.concatenate([Z, Z2]), np.concatenate([own_is_i, own_is_i2]))
    assert np.array_equal(keep[:30], ~outlier)  # random outliers agree with nothing
    assert keep[30:].all()  # the aliased group is left to the joint GNC
