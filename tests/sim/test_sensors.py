import numpy as np
import pytest
from scipy import stats

from kimera_multi_py.core.geometry import relative, se3_log, yaw_pose
from kimera_multi_py.core.semantics import NUM_CLASSES
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.scenario import HumanConfig
from kimera_multi_py.sim.sensors import OdometryModel, RangeCategorySensor, flip_confusion, ray_pattern

from .helpers import TINY


@pytest.fixture(scope="module")
def tiny_world():
    return Simulation(load_scenario(TINY), seed=0).world


@pytest.mark.parametrize("model", ["pinhole", "spherical"])
def test_ray_pattern_spans_the_field_of_view(model):
    d = ray_pattern(model, 90.0, 60.0, 30, 40)
    assert d.shape == (1200, 3) and np.allclose(np.linalg.norm(d, axis=1), 1.0)
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    assert 40 < az.max() < 45 and -45 < az.min() < -40
    assert d[0, 1] > 0 and d[0, 2] > 0  # first ray: top-left (y left, z up)


def test_label_flips_match_the_configured_rate_and_are_uniform(tiny_world):
    p, n_rays = 0.1, 60_000
    rng = np.random.default_rng(7)
    dirs = rng.normal(size=(n_rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    sensor = RangeCategorySensor(dirs, 20.0, 0.02, flip_confusion(p))
    noisy, true = sensor.measure(tiny_world, yaw_pose(2.0, 2.5, 1.05, 0.3), rng)
    hit = true.hit
    assert hit.sum() > 0.95 * n_rays
    flipped = noisy.labels[hit] != true.labels[hit]
    rate, sd = flipped.mean(), np.sqrt(p * (1 - p) / hit.sum())
    assert abs(rate - p) < 4 * sd, (rate, p)
    # flips from walls land uniformly on the other K-1 classes
    from_wall = flipped & (true.labels[hit] == 1)
    counts = np.bincount(noisy.labels[hit][from_wall], minlength=NUM_CLASSES + 1)[1:]
    assert counts[0] == 0
    assert stats.chisquare(counts[1:]).pvalue > 1e-3
    # range noise is Gaussian with the configured sigma
    err = noisy.ranges[hit] - true.ranges[hit]
    assert abs(err.std() - 0.02) < 0.02 * 0.03 and abs(err.mean()) < 0.001


def test_label_noise_off_keeps_labels(tiny_world):
    sensor = RangeCategorySensor(ray_pattern("pinhole", 90, 60, 20, 20), 8.0, 0.0, flip_confusion(0.0))
    noisy, true = sensor.measure(tiny_world, yaw_pose(2.0, 2.5, 1.05, 0.0), np.random.default_rng(0))
    assert np.array_equal(noisy.labels, true.labels) and np.array_equal(noisy.ranges, true.ranges)


def test_odometry_noise_statistics_match_configuration():
    rot_sigma, trans_sigma = np.deg2rad(0.5), 0.03
    model = OdometryModel(rot_sigma, trans_sigma)
    rng = np.random.default_rng(3)
    T_rel = yaw_pose(0.5, 0.1, 0.0, 0.2)
    errs = np.array([se3_log(relative(T_rel, model.measure(T_rel, rng))) for _ in range(20_000)])
    std = errs.std(0)
    assert np.allclose(std[:3], rot_sigma, rtol=0.03) and np.allclose(std[3:], trans_sigma, rtol=0.03)
    assert np.all(np.abs(errs.mean(0)) < 4 * std / np.sqrt(len(errs)))


def test_simulated_odometry_drifts_and_starts_at_identity():
    sim = Simulation(load_scenario(TINY), seed=1)
    kfs = list(sim.keyframes(0))
    assert np.array_equal(kfs[0].odometry, np.eye(4))
    errs = np.array([se3_log(relative(relative(a.true_pose, b.true_pose), b.odometry))
                     for a, b in zip(kfs[:-1], kfs[1:], strict=True)])
    cfg = sim.cfg.odometry
    assert np.allclose(errs[:, :3].std(0), np.deg2rad(cfg.rot_sigma_deg), rtol=0.25)
    assert np.allclose(errs[:, 3:].std(0), cfg.trans_sigma, rtol=0.25)


def test_humans_are_seen_with_the_human_label():
    cfg = load_scenario(TINY)
    cfg = cfg.model_copy(update={"humans": [HumanConfig(waypoints=[(1.0, 5.0), (7.0, 5.0)], speed=0.5)]})
    sim = Simulation(cfg, seed=0)
    h = sim.humans_at(0.0)
    assert len(h) == 1 and np.allclose(h.center[0, :2], [1.0, 5.0])
    assert np.allclose(sim.humans_at(12.0).center[0, :2], [7.0, 5.0])  # 6 m at 0.5 m/s
    assert np.allclose(sim.humans_at(14.0).center[0, :2], [6.0, 5.0])  # and walking back
    origin = np.array([1.0, 4.5, 0.05 + 1.75 / 2])  # at the height of its centre
    r, lab = sim.world.raycast(origin, np.array([[0.0, 1.0, 0.0]]), 8.0, sim.humans_at(0.0))
    assert lab[0] == 12 and r[0] == pytest.approx(0.5 - 0.25, abs=1e-9)
