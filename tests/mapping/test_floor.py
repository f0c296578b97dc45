import numpy as np
import pytest

from kimera_multi_py.core.geometry import inverse, se3_exp, yaw_pose
from kimera_multi_py.core.semantics import class_id
from kimera_multi_py.mapping.floor import FloorReference, Plane, fit_plane
from kimera_multi_py.mapping.registration import ScanRegistration
from kimera_multi_py.mapping.scan_odometry import ScanOdometry
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.sensors import RangeCategorySensor, flip_confusion, ray_pattern
from kimera_multi_py.sim.world import World

from ..sim.helpers import OFFICE

FLOOR = class_id("floor")
ODOM_INFO = np.diag(np.repeat(1.0 / np.square([np.deg2rad(0.15), 0.02]), 3))


def _plane_points(n: np.ndarray, d: float, rng: np.random.Generator, count: int = 600,
                  noise: float = 0.01) -> np.ndarray:
    """Points on ``n . p + d = 0`` over a 6 x 6 m patch, with Gaussian noise along the normal."""
    n = n / np.linalg.norm(n)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    ab = rng.uniform(-3, 3, (count, 2))
    return -d * n + ab[:, :1] * u + ab[:, 1:] * v + rng.normal(0, noise, (count, 1)) * n


def test_fit_plane_recovers_a_tilted_plane_through_outliers():
    rng = np.random.default_rng(0)
    n = np.array([0.02, -0.03, 1.0])
    n /= np.linalg.norm(n)
    pts = np.vstack([_plane_points(n, 1.0, rng), rng.uniform(-3, 3, (60, 3))])  # 10 % off the plane
    fit = fit_plane(pts, Plane(np.array([0.0, 0.0, 1.0]), 0.9), band=0.3)
    assert fit is not None
    assert np.degrees(np.arccos(min(1.0, fit.normal @ n))) < 0.1
    assert abs(fit.offset - 1.0) < 0.003 and fit.rms < 0.015
    # nothing near the guess: no plane
    assert fit_plane(pts, Plane(np.array([0.0, 0.0, 1.0]), -2.0), band=0.2) is None


def test_the_reference_corrects_roll_pitch_and_height_but_not_yaw_or_position_on_the_floor():
    rng = np.random.default_rng(1)
    ref = FloorReference()
    floor = _plane_points(np.array([0.0, 0.0, 1.0]), 1.0, rng)  # sensor 1 m above a level floor
    assert np.allclose(ref.correct(np.eye(4), floor), np.eye(4)) and ref.plane is not None
    true = yaw_pose(3.0, -2.0, 0.0, 0.7)
    drifted = true @ se3_exp(np.array([0.01, -0.02, 0.03, 0.05, -0.04, 0.08]))  # pitch, roll, height off
    seen = (inverse(true)[:3, :3] @ floor.T).T + inverse(true)[:3, 3]  # the same floor from the true pose
    out = drifted
    for _ in range(8):  # a robot standing still: each fit pulls by the filter's gain, and the
        out = ref.correct(out, seen)  # estimate converges onto the floor
    assert abs(out[2, 3] - true[2, 3]) < 0.003  # height restored
    up = out[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(min(1.0, up[2]))) < 0.1  # level again
    # yaw and the position along the floor are the drifted pose's: the plane cannot see them
    assert np.allclose(out[:2, 3], drifted[:2, 3], atol=0.01)
    yaw = np.arctan2(out[1, 0], out[0, 0])
    assert abs(yaw - np.arctan2(drifted[1, 0], drifted[0, 0])) < np.deg2rad(0.1)
    assert abs(yaw - 0.7) > np.deg2rad(1.0)
    assert ref.stats.corrected == 8


def test_a_floor_off_the_prediction_or_out_of_view_leaves_the_pose_alone():
    rng = np.random.default_rng(2)
    ref = FloorReference()
    ref.correct(np.eye(4), _plane_points(np.array([0.0, 0.0, 1.0]), 1.0, rng))
    pose = yaw_pose(1.0, 0.0, 0.0, 0.0)
    ramp = _plane_points(np.array([np.sin(np.deg2rad(5.0)), 0.0, np.cos(np.deg2rad(5.0))]), 1.0, rng)
    assert np.array_equal(ref.correct(pose, ramp), pose) and ref.stats.gated == 1  # 5 degrees off
    step_up = _plane_points(np.array([0.0, 0.0, 1.0]), 0.7, rng)  # 0.3 m higher: another level
    assert np.array_equal(ref.correct(pose, step_up), pose) and ref.stats.missing == 1
    assert np.array_equal(ref.correct(pose, np.zeros((10, 3))), pose) and ref.stats.missing == 2


def test_the_first_floor_must_be_level_and_below_the_sensor():
    rng = np.random.default_rng(3)
    ref = FloorReference()
    wall = _plane_points(np.array([1.0, 0.0, 0.3]), -2.0, rng)  # a steep surface labelled floor
    ref.correct(np.eye(4), wall)
    ceiling = _plane_points(np.array([0.0, 0.0, -1.0]), 1.5, rng)  # level, but above the sensor
    ref.correct(np.eye(4), ceiling)
    assert ref.plane is None and ref.stats.missing == 2
    with pytest.raises(ValueError, match="floor"):
        FloorReference(band=0.0)


def test_on_the_office_the_floor_stops_the_registration_chain_drifting_in_height_and_tilt():
    """A 12 m drive down the office corridor with odometry that pitches 0.3 degrees per
    keyframe (four times the filter's model): registration alone carries part of that into height;
    with the floor it stays level."""
    world = World(load_scenario(OFFICE))
    sensor = RangeCategorySensor(ray_pattern("pinhole", 90.0, 60.0, 48, 64), 8.0, 0.02, flip_confusion(0.1))
    bias = se3_exp(np.array([0.0, np.deg2rad(0.3), 0.0, 0.0, 0.0, 0.0]))
    poses = [yaw_pose(1.0 + 0.5 * k, 6.0, 1.05, 0.0) for k in range(24)]
    out = {}
    for use_floor in (False, True):
        rng = np.random.default_rng(4)
        so = ScanOdometry(ScanRegistration(), ODOM_INFO, window=8, floor=FloorReference() if use_floor else None)
        for k, pose in enumerate(poses):
            scan, _ = sensor.measure(world, pose, rng)
            hit = scan.hit
            odom = np.eye(4) if k == 0 else inverse(poses[k - 1]) @ pose @ bias
            so.step(k, odom, scan.points()[hit], scan.points()[hit & (scan.labels == FLOOR)])
        est = poses[0] @ np.array(so.poses)
        dz = np.abs(est[:, 2, 3] - 1.05).max()
        tilt = float(np.degrees(np.arccos(np.clip(est[:, 2, 2], -1.0, 1.0))).max())  # z axis off vertical
        out[use_floor] = (dz, tilt, so.floor.stats.corrected if so.floor else 0)
    assert out[True][0] < 0.01 and out[True][1] < 0.15 and out[True][2] >= 20
    assert out[False][0] > 3 * out[True][0] or out[False][1] > 3 * out[True][1]


def test_noisy_fits_are_filtered_not_copied_into_the_chain():
    """A robot standing still over small noisy patches of floor: each fit alone is tilted by
    tenths of a degree, and the chain (the filter) by much less."""
    rng = np.random.default_rng(5)
    ref = FloorReference()
    ref.correct(np.eye(4), _plane_points(np.array([0.0, 0.0, 1.0]), 1.0, rng))
    pose, fits, chain = np.eye(4), [], []
    for _ in range(60):
        patch = _plane_points(np.array([0.0, 0.0, 1.0]), 1.0, rng, count=80, noise=0.02) * [0.15, 0.15, 1.0]
        fit = fit_plane(patch, Plane(np.array([0.0, 0.0, 1.0]), 1.0), band=0.2, min_points=50)
        assert fit is not None
        fits.append(np.degrees(np.arccos(min(1.0, fit.normal[2]))))
        assert np.degrees(fit.uncertainty(np.zeros(3))[0]) > 0.3  # a 0.9 m patch: the tilt is poorly fixed
        pose = ref.correct(pose, patch)
        chain.append(np.degrees(np.arccos(min(1.0, pose[2, 2]))))
    assert np.sqrt(np.mean(np.square(chain))) < 0.3 * np.sqrt(np.mean(np.square(fits)))
