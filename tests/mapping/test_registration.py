import numpy as np
import pytest

from kimera_multi_py.core.geometry import inverse, se3_exp, se3_log, so3_log, yaw_pose
from kimera_multi_py.mapping.registration import ScanRegistration, constrained_information, fuse
from kimera_multi_py.mapping.scan_odometry import ScanOdometry
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.sensors import RangeCategorySensor, flip_confusion, ray_pattern
from kimera_multi_py.sim.world import World

from ..sim.helpers import TINY, scenario

ODOM_INFO = np.diag(np.repeat(1.0 / np.square([np.deg2rad(0.3), 0.02]), 3))


def _sensor(rows: int = 48, cols: int = 64) -> RangeCategorySensor:
    return RangeCategorySensor(ray_pattern("pinhole", 90.0, 60.0, rows, cols), 8.0, 0.02, flip_confusion(0.0))


def _scan(world: World, pose: np.ndarray, rng: np.random.Generator, sensor: RangeCategorySensor) -> np.ndarray:
    scan, _ = sensor.measure(world, pose, rng)
    return scan.points()[scan.hit]


def _errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    E = inverse(T_true) @ T
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(E[:3, :3]))))


def _corridor() -> World:
    """A 40 m corridor with bare walls: nothing tells positions along it apart."""
    return World(scenario({"name": "corridor", "spaces": [{"name": "c", "kind": "corridor", "min": [0.0, 0.0],
                                                           "max": [40.0, 2.0]}],
                           "robots": [{"waypoints": [[1.0, 1.0], [39.0, 1.0]]}]}))


def test_registration_recovers_a_known_transform_between_two_scans_of_one_room():
    world = World(load_scenario(TINY))
    rng = np.random.default_rng(3)
    sensor = _sensor()
    A = yaw_pose(2.0, 3.2, 1.0, -np.pi / 2)  # room_a, looking at the furniture
    T_ab = yaw_pose(0.15, -0.08, 0.0, np.deg2rad(4.0)) @ se3_exp(np.array([0.004, -0.003, 0.0, 0.0, 0.0, 0.01]))
    src, dst = _scan(world, A, rng, sensor), _scan(world, A @ T_ab, rng, sensor)
    res = ScanRegistration(voxel=0.05).register(src, dst, np.eye(4))
    assert res is not None and res.converged
    trans, rot = _errors(res.T, T_ab)
    assert trans <= 0.01 and rot <= 0.2
    # the information is a positive-definite 6x6 matrix in metres and radians
    assert res.information.shape == (6, 6) and np.all(np.linalg.eigvalsh(res.information) > 0)
    # starting far off it would not be that good: the guess matters, the result is not a constant
    assert _errors(np.eye(4), T_ab)[0] > 0.1


def test_too_few_points_give_no_registration_and_bad_guesses_raise():
    reg = ScanRegistration(min_points=30)
    pts = np.random.default_rng(0).uniform(0, 1, (10, 3))
    assert reg.register(pts, pts, np.eye(4)) is None
    with pytest.raises(ValueError, match="initial guess"):
        reg.register(pts, pts, np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="voxel"):
        ScanRegistration(voxel=0.0)


def test_in_a_featureless_corridor_registration_is_degenerate_and_odometry_keeps_the_estimate():
    world = _corridor()
    rng = np.random.default_rng(1)
    sensor = _sensor(24, 32)
    so = ScanOdometry(ScanRegistration(), ODOM_INFO, window=4)
    odom_err = se3_exp(np.array([0.0, 0.0, 0.0, 0.08, 0.0, 0.0]))  # odometry overshoots 8 cm along the axis
    poses = [yaw_pose(5.0 + 0.5 * k, 1.0, 1.0, 0.0) for k in range(4)]
    steps = [so.step(0, np.eye(4), _scan(world, poses[0], rng, sensor))]
    for k in range(1, 4):
        odom = inverse(poses[k - 1]) @ poses[k] @ odom_err
        steps.append(so.step(k, odom, _scan(world, poses[k], rng, sensor)))
        d = se3_log(inverse(odom) @ steps[-1])
        assert abs(d[3]) < 1e-3  # along the corridor the fused step is the odometry's
    assert so.stats.degenerate == 3 and so.stats.registered == 3
    # the kept information has (almost) nothing along the axis, but constrains the lateral offset
    info = so.edges[3][1]
    assert info[3, 3] < 0.01 * ODOM_INFO[3, 3] and info[4, 4] > ODOM_INFO[4, 4]


def test_registration_is_not_degenerate_in_a_furnished_room_and_corrects_the_odometry():
    world = World(load_scenario(TINY))
    rng = np.random.default_rng(2)
    so = ScanOdometry(ScanRegistration(), ODOM_INFO, window=4)
    poses = [yaw_pose(2.0 + 0.1 * k, 3.2 - 0.1 * k, 1.0, -np.pi / 2 + 0.05 * k) for k in range(4)]
    odom_err = se3_exp(np.array([0.0, 0.0, np.deg2rad(0.5), 0.04, -0.03, 0.0]))
    so.step(0, np.eye(4), _scan(world, poses[0], rng, _sensor()))
    for k in range(1, 4):
        truth = inverse(poses[k - 1]) @ poses[k]
        step = so.step(k, truth @ odom_err, _scan(world, poses[k], rng, _sensor()))
        assert _errors(step, truth)[0] < 0.5 * _errors(truth @ odom_err, truth)[0]
    assert so.stats.registered == 3 and so.stats.gated == 0


def test_constrained_information_keeps_strong_directions_and_drops_weak_ones():
    prior = np.eye(6)
    H = np.diag([10.0, 10.0, 10.0, 10.0, 10.0, 0.01])
    c = constrained_information(H, prior, 1.0)
    assert c.degenerate and np.allclose(c.information, np.diag([10.0] * 5 + [0.0]))
    assert np.allclose(c.ratios, sorted(np.diag(H)))
    assert not constrained_information(H, prior, 0.001).degenerate


def test_fuse_weighs_two_measurements_by_their_information():
    Z0, Z1 = np.eye(4), se3_exp(np.array([0.0, 0.0, 0.0, 0.1, 0.2, 0.0]))
    I0 = np.eye(6)
    I1 = np.diag([0.0, 0.0, 0.0, 3.0, 0.0, 0.0])  # knows only x
    X = fuse(Z0, I0, Z1, I1)
    assert np.allclose(X[:3, 3], [0.075, 0.0, 0.0], atol=1e-9)
