import gtsam
import numpy as np
import pytest

from kimera_multi_py.core import geometry as g


def random_poses(n, rng):
    return g.make_pose(g.so3_exp(rng.normal(size=(n, 3))), rng.normal(size=(n, 3)) * 5)


def test_so3_exp_log_round_trip():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(200, 3))
    w *= (rng.uniform(0, np.pi - 1e-3, 200) / np.linalg.norm(w, axis=1))[:, None]
    assert np.allclose(g.so3_log(g.so3_exp(w)), w, atol=1e-9)
    R = g.so3_exp(w)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)


def test_so3_log_near_pi_and_identity():
    for axis in np.eye(3):
        w = axis * (np.pi - 1e-7)
        assert np.allclose(g.so3_exp(g.so3_log(g.so3_exp(w))), g.so3_exp(w), atol=1e-6)
    assert np.allclose(g.so3_log(np.eye(3)), 0.0)


def test_inverse_and_relative():
    rng = np.random.default_rng(1)
    T = random_poses(10, rng)
    assert np.allclose(T @ g.inverse(T), np.eye(4), atol=1e-12)
    assert np.allclose(T[0] @ g.relative(T[0], T[1]), T[1])


def test_quaternion_round_trip_matches_gtsam():
    rng = np.random.default_rng(2)
    T = random_poses(20, rng)
    q = g.rot_to_quat(T[:, :3, :3])
    assert np.allclose(g.quat_to_rot(q), T[:, :3, :3], atol=1e-9)
    gq = gtsam.Rot3(T[0, :3, :3]).toQuaternion()
    ours = q[0] * np.sign(q[0, 3]) * np.sign(gq.w())
    assert np.allclose(ours, [gq.x(), gq.y(), gq.z(), gq.w()], atol=1e-9)


def test_gtsam_conversion_round_trip():
    T = random_poses(1, np.random.default_rng(3))[0]
    assert np.allclose(g.from_gtsam(g.to_gtsam(T)), T)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_transform(with_scale):
    rng = np.random.default_rng(4)
    src = rng.normal(size=(50, 3))
    R = g.so3_exp(rng.normal(size=3))
    t = rng.normal(size=3)
    s = 1.7 if with_scale else 1.0
    dst = s * src @ R.T + t
    R_, t_, s_ = g.umeyama(src, dst, with_scale=with_scale)
    assert np.allclose(R_, R) and np.allclose(t_, t) and np.isclose(s_, s)


def test_umeyama_rejects_bad_shapes():
    with pytest.raises(ValueError, match="umeyama"):
        g.umeyama(np.zeros((3, 2)), np.zeros((3, 2)))


def test_pair_index_finds_each_key_pair_in_a_table():
    from kimera_multi_py.core.posegraph import pair_index

    rng = np.random.default_rng(3)
    table = rng.integers(-2**62, 2**62, size=(50, 2))
    pick = rng.permutation(50)[:20]
    query = np.vstack([table[pick], rng.integers(-2**62, 2**62, size=(5, 2)), table[pick[:3]][:, ::-1]])
    j = pair_index(query[:, 0], query[:, 1], table[:, 0], table[:, 1])
    expected = {tuple(p): i for i, p in enumerate(table.tolist())}
    assert j.tolist() == [expected.get(tuple(q), -1) for q in query.tolist()]
    assert pair_index(query[:, 0], query[:, 1], table[:0, 0], table[:0, 1]).tolist() == [-1] * len(query)
