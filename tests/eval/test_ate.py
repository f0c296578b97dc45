import numpy as np
import pytest

from kimera_multi_py.core.geometry import make_pose, so3_exp
from kimera_multi_py.eval.metrics import align_se3, ate_rmse


def fake_trajectory(n, rng):
    return np.cumsum(rng.normal(size=(n, 3)), axis=0)


def test_ate_is_zero_after_rigid_motion():
    rng = np.random.default_rng(0)
    gt = fake_trajectory(100, rng)
    T = make_pose(so3_exp(np.array([0.3, -0.2, 1.0])), np.array([5.0, -2.0, 1.0]))
    est = gt @ T[:3, :3].T + T[:3, 3]
    assert ate_rmse(est, gt) == pytest.approx(0.0, abs=1e-9)
    assert ate_rmse(est, gt, align=False) > 1.0
    assert np.allclose(align_se3(est, gt), np.linalg.inv(T), atol=1e-9)


def test_ate_of_known_noise_and_no_scale_correction():
    rng = np.random.default_rng(1)
    gt = fake_trajectory(2000, rng)
    noise = rng.normal(scale=0.1, size=gt.shape)
    assert ate_rmse(gt + noise, gt) == pytest.approx(np.sqrt(3) * 0.1, rel=0.05)
    assert ate_rmse(2.0 * gt, gt) > 1.0  # SE(3) alignment does not fix scale


def test_ate_rejects_mismatched_lengths():
    with pytest.raises(ValueError, match="equal shapes"):
        ate_rmse(np.zeros((3, 3)), np.zeros((4, 3)))
