import numpy as np
import pytest

from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp, transform_points, yaw_pose
from kimera_multi_py.frontend.loop_closure import DescriptorSpec, constellation_descriptor, similarity, verify

SPEC = DescriptorSpec(num_classes=8)


def room(rng, n=10):
    xyz = np.column_stack([rng.uniform(0, 6, n), rng.uniform(0, 5, n), rng.uniform(0.2, 1.5, n)])
    return xyz, rng.integers(0, 8, n)


def test_descriptor_is_viewpoint_invariant_and_discriminative():
    rng = np.random.default_rng(0)
    xyz, cls = room(rng)
    T = yaw_pose(3.0, -1.0, 0.0, 1.2)
    d1 = constellation_descriptor(xyz, cls, SPEC)
    d2 = constellation_descriptor(transform_points(T, xyz), cls, SPEC)
    other = constellation_descriptor(*room(rng), SPEC)
    assert d1.shape == (SPEC.size,) and d1.dtype == np.float32
    sims = similarity(d1, np.stack([d2, other]))
    assert sims[0] == pytest.approx(1.0, abs=1e-5) and sims[1] < 0.8
    assert np.all(constellation_descriptor(np.zeros((0, 3)), np.zeros(0, int), SPEC) == 0)


def test_verify_recovers_the_relative_pose_with_clutter_and_missing_objects():
    rng = np.random.default_rng(1)
    xyz, cls = room(rng, 12)
    T = make_pose(so3_exp([0.0, 0.0, 0.8]), [2.0, 1.0, 0.05])
    dst = transform_points(inverse(T), xyz[:9]) + rng.normal(0, 0.03, (9, 3))  # 3 objects unseen
    dst = np.vstack([dst, rng.uniform(0, 5, (3, 3))])  # 3 clutter detections
    dst_cls = np.concatenate([cls[:9], rng.integers(0, 8, 3)])
    v = verify(xyz, cls, dst, dst_cls)
    assert v.accepted, v.reason
    assert np.allclose(v.T, T, atol=0.05)
    assert v.num_inliers >= 8 and np.all(v.inliers[:, 0] == v.inliers[:, 1])


def test_verify_rejects_unrelated_places_and_degenerate_sets():
    rng = np.random.default_rng(2)
    a, ca = room(rng)
    b, cb = room(rng)
    assert not verify(a, ca, b, cb).accepted
    line = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])
    v = verify(line, np.arange(6), line + [0.1, 0, 0], np.arange(6))
    assert not v.accepted and "collinear" in v.reason
