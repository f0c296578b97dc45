"""A bag read back gives the keyframes the simulator gave, for every input kind the reader takes."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.core.semantics import CLASS_COLORS, CLASS_IDS, CLASS_NAMES
from kimera_multi_py.io.bag.config import BagConfig, load_bag_config
from kimera_multi_py.io.bag.reader import BagSource, bag_robots
from kimera_multi_py.sim.bag_recording import write_bag
from kimera_multi_py.sim.scenario import load_scenario
from kimera_multi_py.sim.simulation import Simulation
from kimera_multi_py.sim.source import SimSource
from kimera_multi_py.team.build import source_from_spec
from tests.io.bag.conftest import TINY, HandBag, pose_x

FLOAT32 = 8.0 * 2.0**-23 * 2  # float32 rounding of a coordinate within the 8 m range


def assert_same_stream(bag: BagSource, sim: SimSource) -> None:
    assert bag.num_keyframes == sim.num_keyframes
    n = 0
    for a, b in zip(bag, sim, strict=True):
        assert a.index == b.index and a.stamp == pytest.approx(b.stamp, abs=1e-9)
        np.testing.assert_allclose(a.odometry, b.odometry, atol=1e-9)
        assert a.points.shape == b.points.shape
        np.testing.assert_allclose(a.points, b.points, atol=FLOAT32)
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_array_equal(a.hit, b.hit)
        assert a.max_range == b.max_range
        n += 1
    assert n == sim.num_keyframes


@pytest.mark.parametrize("kind", ["cloud", "ros1", "camera"])
def test_bag_gives_the_simulators_keyframes(tiny_bags, kind):
    cfg = load_scenario(TINY)
    assert bag_robots(tiny_bags[kind]) == [0, 1]
    for r in range(2):
        assert_same_stream(BagSource(tiny_bags[kind], r), SimSource(cfg, None, r))


def test_source_spec_and_restart(tiny_bags):
    src = source_from_spec(f"bag:{tiny_bags['cloud']}", 1, start=4)
    assert isinstance(src, BagSource) and src.next_index == 4
    first = next(src)
    assert first.index == 4
    whole = list(BagSource(tiny_bags["cloud"], 1))
    np.testing.assert_array_equal(first.points, whole[4].points)
    np.testing.assert_allclose(first.odometry, whole[4].odometry)
    assert src.state() == {"robot": 1, "next": 5}


def test_tf_motion_with_a_sensor_extrinsic(tmp_path):
    """Odometry from /tf (odom -> base_link) and the sensor 0.3 m ahead, 0.5 m up, yawed and
    pitched on /tf_static: the keyframes and the ground truth are the sensor's, as simulated."""
    cfg = load_scenario(TINY)
    ext = np.eye(4)
    c, s = np.cos(0.4), np.sin(0.4)
    ext[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[np.cos(0.1), 0, np.sin(0.1)], [0, 1, 0],
                                                                           [-np.sin(0.1), 0, np.cos(0.1)]])
    ext[:3, 3] = [0.3, 0.0, 0.5]
    config = write_bag(tmp_path / "tf", cfg, "ros2", extrinsic=ext, scenario_path=TINY)
    bag_cfg = load_bag_config(config).model_copy(update={"motion": "tf"})
    src = BagSource(tmp_path / "tf", 1, config=bag_cfg)
    np.testing.assert_allclose(src.T_base_keyframe, ext, atol=1e-12)  # found on /tf_static
    truth = src.ground_truth()
    assert_same_stream(src, SimSource(cfg, None, 1))
    sim = Simulation(cfg)
    np.testing.assert_allclose(truth, sim.plans[1].poses, atol=1e-9)


def test_colour_table_and_class_mapping(tmp_path):
    """rgb8 segmentation read through a colour table whose ids are the dataset's own; the config
    maps them onto the vocabulary and leaves chairs out: chair returns are dropped and counted."""
    cfg = load_scenario(TINY)
    config = write_bag(tmp_path / "seg", cfg, "ros2", camera=True, label_encoding="bgr8")
    table = tmp_path / "dataset_colours.csv"
    rows = [f"{n},{c[0]},{c[1]},{c[2]},{100 + i}\n" for i, (n, c) in enumerate(zip(CLASS_NAMES, CLASS_COLORS,
                                                                                     strict=True))]
    table.write_text("name,red,green,blue,id\n" + "".join(rows))
    classes = {100 + i: n for i, n in enumerate(CLASS_NAMES) if n not in ("free", "chair")}
    bag_cfg = load_bag_config(config).model_copy(update={"colour_table": table, "classes": classes})
    bag, sim = BagSource(tmp_path / "seg", 0, config=bag_cfg), SimSource(cfg, None, 0)
    chairs = 0
    for a, b in zip(bag, sim, strict=True):
        keep = ~(b.hit & (b.labels == CLASS_IDS["chair"]))
        chairs += int((~keep).sum())
        np.testing.assert_array_equal(a.labels, b.labels[keep])
        np.testing.assert_allclose(a.points, b.points[keep], atol=FLOAT32)
    assert chairs > 0 and bag.dropped["unmapped"] == chairs


def test_keyframes_by_distance_and_angle(tiny_bags):
    """Every 1 m or 45 deg: fewer keyframes, each far enough from the last, odometry chained between them."""
    every = BagSource(tiny_bags["cloud"], 0)
    poses = every.poses
    cfg = load_bag_config(str(tiny_bags["cloud"]) + ".toml")
    sparse_cfg = cfg.model_copy(update={"keyframes": cfg.keyframes.model_copy(update={"distance": 1.0,
                                                                                       "angle_deg": 45.0})})
    sparse = BagSource(tiny_bags["cloud"], 0, config=sparse_cfg)
    assert 2 < sparse.num_keyframes < every.num_keyframes
    chosen = [int(np.flatnonzero(np.isclose(every.stamps, t))[0]) for t in sparse.stamps]
    for a, b in zip(chosen[:-1], chosen[1:], strict=True):
        rel = np.linalg.inv(poses[a]) @ poses[b]
        turned = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1)))
        assert np.linalg.norm(rel[:3, 3]) >= 1.0 - 1e-9 or turned >= 45.0 - 1e-6
    kfs = list(sparse)
    for k in range(1, len(kfs)):
        np.testing.assert_allclose(kfs[k].odometry, np.linalg.inv(poses[chosen[k - 1]]) @ poses[chosen[k]],
                                   atol=1e-9)


def test_float64_clouds_are_lossless(tmp_path):
    cfg = load_scenario(TINY)
    write_bag(tmp_path / "f64", cfg, "ros2", float64=True)
    for a, b in zip(BagSource(tmp_path / "f64", 0), SimSource(cfg, None, 0), strict=True):
        np.testing.assert_array_equal(a.points, b.points)


def test_16uc1_depth_back_projects_in_millimetres(tmp_path):
    """A 16UC1 depth image (mm) and mono8 labels 4 ms apart: pixels back-project with K into the
    body convention; no reading (0) and unlabelled near returns are dropped, unlabelled far ones are misses."""
    bag = HandBag(tmp_path / "d")
    m = bag.m
    K = np.array([[50.0, 0.0, 2.0], [0.0, 40.0, 1.0], [0.0, 0.0, 1.0]])
    depth = np.array([[2000, 0, 1500, 1000, 9000], [2500, 3000, 500, 700, 800], [1200, 1300, 1400, 1500, 1600]],
                     dtype=np.uint16)
    labels = np.array([[1, 5, 2, 0, 0], [3, 3, 4, 5, 6], [1, 1, 1, 1, 1]], dtype=np.uint8)
    for k in range(3):
        t = 1.0 + k
        bag.put("/odom", m.ODOM, m.odometry(t, "odom", "base_link", pose_x(0.6 * k)), t)
        bag.put("/depth", m.IMAGE, m.image(t, "cam", "16UC1", depth), t)
        bag.put("/labels", m.IMAGE, m.image(t + 0.004, "cam", "mono8", labels), t + 0.004)
        bag.put("/camera_info", m.INFO, m.camera_info(t, "cam", K, 3, 5), t)
    bag.close()
    cfg = BagConfig(depth="/depth", labels="/labels", extrinsic=[0, 0, 0, 0, 0, 0, 1], max_range=8.0)
    src = BagSource(tmp_path / "d", 0, config=cfg)
    kf = next(src)
    # pixel (v=0, u=0): z = 2 m; optical x = (0 - 2) / 50 * 2, y = (0 - 1) / 40 * 2
    np.testing.assert_allclose(kf.points[0], [2.0, 0.08, 0.05])
    assert kf.labels[0] == 1 and kf.hit[0]
    # kept: every pixel but the 0 mm one (v=0, u=1) and the unlabelled 1 m one (v=0, u=3)
    assert len(kf.points) == 13 and src.dropped["unmapped"] == 1
    miss = ~kf.hit
    assert miss.sum() == 1 and np.linalg.norm(kf.points[miss][0]) == pytest.approx(8.0)  # the 9 m one
    assert src.num_keyframes == 3
