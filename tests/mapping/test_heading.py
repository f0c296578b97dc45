import numpy as np
import pytest

from kimera_multi_py.core.geometry import inverse, transform_points
from kimera_multi_py.mapping.axes import heading
from kimera_multi_py.mapping.heading import HeadingReference, rotate_yaw


def _room(yaw: float, rng: np.random.Generator, size=(6.0, 5.0), noise=0.02) -> np.ndarray:
    """Wall points of a ``size`` room turned by ``yaw`` about its corner (world frame)."""
    w, d = size
    s = rng.uniform(0, 1, (4, 400))
    z = rng.uniform(0, 2.5, (4, 400))
    walls = [np.c_[s[0] * w, np.zeros(400), z[0]], np.c_[s[1] * w, np.full(400, d), z[1]],
             np.c_[np.zeros(400), s[2] * d, z[2]], np.c_[np.full(400, w), s[3] * d, z[3]]]
    P = np.concatenate(walls) + rng.normal(0, noise, (1600, 3))
    c, sn = np.cos(yaw), np.sin(yaw)
    return P @ np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]).T


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    return rotate_yaw(np.r_[np.c_[np.eye(3), [x, y, 1.0]], [[0, 0, 0, 1]]], yaw)


def test_a_drifting_yaw_is_held_to_the_walls_grid():
    """A chain whose yaw drifts 0.1 degrees per keyframe (4 degrees over the run) stays within a
    few tenths of a degree of the truth once the walls set the reference."""
    rng = np.random.default_rng(0)
    room = _room(np.deg2rad(20.0), rng)
    ref = HeadingReference()
    errors, raw = [], []
    out = dead = prev = _pose(2.0, 2.0, 0.0)
    for k in range(40):
        true = _pose(2.0 + 0.05 * k, 2.0, np.deg2rad(5.0 * k))
        step = rotate_yaw(inverse(prev) @ true, np.deg2rad(0.1)) if k else np.eye(4)
        est, dead, prev = out @ step, dead @ step, true
        out = ref.correct(est, transform_points(inverse(true), room))
        errors.append(np.degrees(np.angle(np.exp(1j * (heading(out) - heading(true))))))
        raw.append(np.degrees(np.angle(np.exp(1j * (heading(dead) - heading(true))))))
        np.testing.assert_allclose(out[:3, 3], est[:3, 3])  # a pure yaw about the pose's position
    assert ref.stats.corrected == 39 and abs(raw[-1]) > 3.8
    assert np.max(np.abs(errors)) < 0.6 and abs(errors[-1]) < 0.4


def test_walls_off_the_grid_and_no_walls_leave_the_pose():
    rng = np.random.default_rng(1)
    ref = HeadingReference()
    pose = _pose(1.0, 1.0, 0.3)
    assert np.array_equal(ref.correct(pose, np.zeros((0, 3))), pose)
    assert ref.reference is None and ref.stats.missing == 1
    ref.correct(pose, transform_points(inverse(pose), _room(0.0, rng)))  # adopts the grid
    assert ref.reference is not None
    later = rotate_yaw(pose, np.deg2rad(0.2))
    for _ in range(20):  # a room turned 30 degrees from the first: its walls are no evidence
        assert np.array_equal(ref.correct(later, transform_points(inverse(pose), _room(np.deg2rad(30), rng))), later)
    assert ref.stats.gated == 20 and ref.stats.corrected == 0


def test_a_tilted_pose_or_scattered_points_give_no_measurement():
    rng = np.random.default_rng(2)
    ref = HeadingReference()
    tilted = _pose(0, 0, 0)
    tilted[:3, :3] = np.array([[1, 0, 0], [0, np.cos(0.5), -np.sin(0.5)], [0, np.sin(0.5), np.cos(0.5)]])
    assert np.array_equal(ref.correct(tilted, _room(0.0, rng)), tilted)
    assert np.array_equal(ref.correct(_pose(0, 0, 0), rng.uniform(-3, 3, (2000, 3))), _pose(0, 0, 0))
    assert ref.reference is None and ref.stats.missing == 2


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="heading"):
        HeadingReference(measurement_sigma=0.0)
