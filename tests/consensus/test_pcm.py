import numpy as np

from kimera_multi_py.core.geometry import inverse, make_pose, se3_exp, so3_exp, yaw_pose
from kimera_multi_py.frontend.pcm import PcmNoise, consistency_errors, pcm

# the drift() model below: 0.003 rad and 0.01 m per 0.5 m step
NOISE = PcmNoise(odom_rot_per_m=0.005, odom_trans_per_m=0.015)


def walk(n, rng, start):
    """A planar random walk of n poses with 0.5 m steps, from ``start``."""
    poses = [start]
    for _ in range(n - 1):
        poses.append(poses[-1] @ yaw_pose(0.5, 0.0, 0.0, rng.normal(0, 0.3)))
    return np.array(poses)


def drift(true, rng, rot=0.003, trans=0.01):
    """Dead-reckoned estimate of ``true`` in its own frame (identity at the start)."""
    est = [np.eye(4)]
    for a, b in zip(true[:-1], true[1:], strict=True):
        noise = se3_exp(np.concatenate([rng.normal(0, rot, 3), rng.normal(0, trans, 3)]))
        est.append(est[-1] @ inverse(a) @ b @ noise)
    return np.array(est)


def scenario(rng, n_true=12, n_false=6, aliased=0):
    A_true = walk(200, rng, np.eye(4))
    B_true = walk(200, rng, yaw_pose(3.0, -2.0, 0.0, 1.0))
    A, B = drift(A_true, rng), drift(B_true, rng)
    i = rng.integers(0, 200, n_true + n_false + aliased)
    j = rng.integers(0, 200, n_true + n_false + aliased)
    Z = np.einsum("kab,kbc->kac", inverse(A_true[i]), B_true[j])
    Z = Z @ se3_exp(np.concatenate([rng.normal(0, 0.01, (len(i), 3)), rng.normal(0, 0.03, (len(i), 3))], 1))
    truth = np.zeros(len(i), dtype=bool)
    truth[:n_true] = True
    for k in range(n_true, n_true + n_false):  # random wrong closures
        Z[k] = make_pose(so3_exp(rng.normal(0, 1.0, 3)), rng.normal(0, 5.0, 3))
    shift = yaw_pose(6.0, 0.0, 0.0, 0.0)  # an identical room 6 m away: all aliases agree
    for k in range(n_true + n_false, len(i)):
        Z[k] = inverse(A_true[i[k]]) @ shift @ B_true[j[k]]
    path = np.arange(200) * 0.5
    return Z, A[i], B[j], path[i], path[j], truth


def test_a_closure_is_consistent_with_itself():
    rng = np.random.default_rng(0)
    Z, A, B, pa, pb, _ = scenario(rng, n_true=5, n_false=0)
    r2 = consistency_errors(Z, A, B, pa, pb, PcmNoise())
    assert np.allclose(np.diag(r2), 0.0, atol=1e-9)


def test_pcm_keeps_inliers_and_rejects_random_and_aliased_outliers():
    for seed in range(5):
        rng = np.random.default_rng(seed)
        Z, A, B, pa, pb, truth = scenario(rng, n_true=10, n_false=8, aliased=4)
        accepted = pcm(Z, A, B, pa, pb, NOISE)
        assert not np.any(accepted & ~truth), f"seed {seed}: accepted an outlier"
        assert accepted[truth].mean() >= 0.9, f"seed {seed}: lost inliers"


def test_pcm_min_size_refuses_a_lone_closure():
    rng = np.random.default_rng(3)
    Z, A, B, pa, pb, _ = scenario(rng, n_true=1, n_false=0)
    assert pcm(Z, A, B, pa, pb).tolist() == [True]
    assert pcm(Z, A, B, pa, pb, min_size=2).tolist() == [False]
    assert pcm(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)), np.zeros((0, 4, 4)), [], []).size == 0


def test_an_alias_group_as_large_as_the_true_group_is_kept_apart_from_it():
    """Twin rooms: the alias closures agree with each other as well as the true ones do, so PCM
    alone cannot choose. It must never mix the two groups; with ``groups=2`` it keeps both, whole
    and disjoint, for the back end's GNC to decide; random outliers join neither."""
    for seed in range(5):
        rng = np.random.default_rng(seed)
        Z, A, B, pa, pb, truth = scenario(rng, n_true=8, n_false=6, aliased=8)
        alias = np.zeros(len(truth), dtype=bool)
        alias[14:] = True
        one = pcm(Z, A, B, pa, pb, NOISE)
        assert not (one & ~truth & ~alias).any(), f"seed {seed}: accepted a random outlier"
        assert one[truth].any() != one[alias].any(), f"seed {seed}: mixed the true and the alias group"
        assert max(one[truth].mean(), one[alias].mean()) >= 0.875, f"seed {seed}: the chosen group is cut"
        two = pcm(Z, A, B, pa, pb, NOISE, groups=2)
        assert not (two & ~truth & ~alias).any(), f"seed {seed}: accepted a random outlier"
        assert two[truth].mean() >= 0.875 and two[alias].mean() >= 0.875, f"seed {seed}: lost a group"
        assert one[two].sum() == one.sum()  # the first group is the classic PCM answer
