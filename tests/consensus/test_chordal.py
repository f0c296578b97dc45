"""Chordal relaxation (whole graph and one block): exact on noiseless graphs, DPGO weights."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp
from kimera_multi_py.pgo.chordal import chordal_block, chordal_poses, edge_weights


def fake_graph(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A random trajectory with odometry and a few loop closures, exact measurements."""
    rng = np.random.default_rng(seed)
    poses = make_pose(so3_exp(rng.normal(scale=1.0, size=(n, 3))), rng.normal(scale=5.0, size=(n, 3)))
    ei = np.concatenate([np.arange(n - 1), rng.integers(0, n, 6)])
    ej = np.concatenate([np.arange(1, n), rng.integers(0, n, 6)])
    keep = ei != ej
    ei, ej = ei[keep], ej[keep]
    meas = inverse(poses[ei]) @ poses[ej]
    return poses, ei, ej, meas


def perturb(poses: np.ndarray, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_pose(poses[:, :3, :3] @ so3_exp(rng.normal(scale=0.3, size=(len(poses), 3))),
                     poses[:, :3, 3] + rng.normal(size=(len(poses), 3)))


def test_whole_graph_recovers_noiseless_poses() -> None:
    poses, ei, ej, meas = fake_graph(30)
    rng = np.random.default_rng(2)
    info = np.stack([np.diag(rng.uniform(1, 100, 6)) for _ in ei])
    start = perturb(poses)
    start[0] = poses[0]
    est = chordal_poses(start, ei, ej, meas, info)
    assert np.allclose(est, poses, atol=1e-6)


def test_block_with_fixed_neighbours_and_an_unanchored_component() -> None:
    poses, ei, ej, meas = fake_graph(20, seed=3)
    kappa, tau = np.ones(len(ei)), np.ones(len(ei))
    # poses 0..9 unknown, 10..19 fixed (indices n + k); 20 and 21: a component no edge anchors
    extra = make_pose(so3_exp(np.array([[0.1, 0.2, 0.3], [0.0, -0.4, 0.2]])),
                      np.array([[1.0, 2.0, 3.0], [2.0, 2.0, 2.0]]))
    unknown = np.concatenate([poses[:10], extra])
    n = len(unknown)
    remap = np.concatenate([np.arange(10), n + np.arange(10)])
    bi = np.concatenate([remap[ei], [10]])
    bj = np.concatenate([remap[ej], [11]])
    bmeas = np.concatenate([meas, (inverse(extra[0]) @ extra[1])[None]])
    est = chordal_block(n, bi, bj, bmeas, np.append(kappa, 1.0), np.append(tau, 1.0),
                        poses[10:], perturb(unknown, seed=4))
    assert np.allclose(est[:10], poses[:10], atol=1e-6)
    assert np.all(np.isfinite(est[10:]))
    assert np.allclose(inverse(est[10]) @ est[11], inverse(extra[0]) @ extra[1], atol=1e-6)


def test_dpgo_weights_of_a_diagonal_information() -> None:
    info = np.diag([4.0, 4.0, 4.0, 9.0, 9.0, 9.0])[None]
    kappa, tau = edge_weights(info)
    assert kappa[0] == pytest.approx(3.0 / (2.0 * 0.75))
    assert tau[0] == pytest.approx(9.0)
