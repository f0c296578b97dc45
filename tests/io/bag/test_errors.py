"""Bad bags: each problem is one line naming the topic, before any keyframe is read; the CLI exits 1."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.io.bag.config import BagConfig
from kimera_multi_py.io.bag.errors import BagError
from kimera_multi_py.io.bag.reader import BagSource
from tests.io.bag.conftest import HandBag, cloud_msg, pose_x

EXE = Path(sys.executable).parent / "kimera-multi"


def _moving_bag(path: Path, n: int = 6, cloud_dtype: str = "u2", odom: bool = True, tf: bool = False,
                frame: str = "base_link") -> HandBag:
    bag = HandBag(path)
    m = bag.m
    for k in range(n):
        t = 1.0 + 0.5 * k
        T = pose_x(0.5 * k)
        if odom:
            bag.put("/odom", m.ODOM, m.odometry(t, "odom", "base_link", T), t)
        if tf:
            bag.put("/tf", m.TF, m.tf_message([m.transform(t, "odom", "base_link", T)]), t)
        bag.put("/points", m.CLOUD, cloud_msg(m, t, frame, cloud_dtype), t)
    return bag


def _error(path: Path, config: BagConfig | None = None) -> str:
    with pytest.raises(BagError) as err:
        BagSource(path, 0, config=config or BagConfig())
    text = str(err.value)
    assert "\n" not in text
    return text


def test_a_good_hand_written_bag_reads(tmp_path):
    src = BagSource(_moving_bag(tmp_path / "ok").close(), 0, config=BagConfig(max_range=10.0))
    kfs = list(src)
    assert len(kfs) == 6 and all(len(k.points) == 20 and k.hit.all() for k in kfs)
    np.testing.assert_allclose(kfs[1].odometry, pose_x(0.5), atol=1e-12)


def test_missing_topic_lists_the_bags_topics(tmp_path):
    path = _moving_bag(tmp_path / "b").close()
    text = _error(path, BagConfig(points="/velodyne_points"))
    assert "/velodyne_points: not in the bag" in text
    assert "/odom (nav_msgs/msg/Odometry)" in text and "/points (sensor_msgs/msg/PointCloud2)" in text


def test_missing_topic_on_the_command_line_exits_1(tmp_path):
    path = _moving_bag(tmp_path / "b").close()
    cfg = tmp_path / "bag.toml"
    cfg.write_text('points = "/velodyne_points"\n')
    proc = subprocess.run([str(EXE), "replay", "--source", f"bag:{path}", "--bag-config", str(cfg),
                           "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "/velodyne_points: not in the bag" in lines[0], proc.stderr


def test_unsupported_class_field_type(tmp_path):
    text = _error(_moving_bag(tmp_path / "b", cloud_dtype="f4").close())
    assert "/points" in text and "unsupported class field type" in text


def test_unsupported_depth_encoding(tmp_path):
    bag = _moving_bag(tmp_path / "b")
    m = bag.m
    for k in range(3):
        bag.put("/depth", m.IMAGE, m.image(1.0 + k, "cam", "rgb8", np.zeros((4, 5, 3), np.uint8)), 1.0 + k)
    text = _error(bag.close(), BagConfig(depth="/depth"))
    assert "/depth: unsupported depth encoding 'rgb8'" in text


def test_stream_with_no_motion(tmp_path):
    bag = HandBag(tmp_path / "b")
    for k in range(5):
        bag.put("/odom", bag.m.ODOM, bag.m.odometry(1.0 + k, "odom", "base_link", np.eye(4)), 1.0 + k)
        bag.put("/points", bag.m.CLOUD, cloud_msg(bag.m, 1.0 + k), 1.0 + k)
    text = _error(bag.close())
    assert "/odom: no motion" in text


def test_depth_and_labels_never_within_tolerance(tmp_path):
    bag = _moving_bag(tmp_path / "b")
    m = bag.m
    K = np.array([[4.0, 0, 2.0], [0, 4.0, 1.5], [0, 0, 1]])
    for k in range(5):
        t = 1.0 + 0.5 * k
        bag.put("/depth", m.IMAGE, m.image(t, "cam", "32FC1", np.ones((4, 5), np.float32)), t)
        bag.put("/labels", m.IMAGE, m.image(t + 0.2, "cam", "mono8", np.ones((4, 5), np.uint8)), t + 0.2)
        bag.put("/camera_info", m.INFO, m.camera_info(t, "cam", K, 4, 5), t)
    text = _error(bag.close(), BagConfig(depth="/depth", labels="/labels", extrinsic=[0, 0, 0, 0, 0, 0, 1]))
    assert "/labels: never within 0.02 s of a depth image on /depth" in text


def test_tf_chain_with_a_gap(tmp_path):
    """Motion from TF, but nothing links base_link to the base frame the config names."""
    path = _moving_bag(tmp_path / "b", odom=False, tf=True, frame="base_footprint").close()
    text = _error(path, BagConfig(motion="tf", base_frame="base_footprint"))
    assert "/tf: TF chain with a gap: no chain odom -> base_footprint" in text and "odom->base_link" in text


def test_sensor_extrinsics_with_a_gap(tmp_path):
    """The cloud's frame is not linked to the base frame on /tf_static."""
    text = _error(_moving_bag(tmp_path / "b", frame="velodyne").close())
    assert "/tf_static: TF chain with a gap" in text and "base_link -> velodyne" in text


def test_a_bag_that_yields_no_keyframe_says_so(tmp_path):
    bag = _moving_bag(tmp_path / "b", n=3)
    bag.topic("/empty_points", bag.m.CLOUD)
    text = _error(bag.close(), BagConfig(points="/empty_points"))
    assert "/empty_points: no messages (robot 0 yields no keyframe)" in text


def test_not_a_bag(tmp_path):
    (tmp_path / "x.bag").write_bytes(b"not a bag")
    assert "not a readable ROS 1 or ROS 2 bag" in _error(tmp_path / "x.bag")


def test_scans_outside_the_odometry_span(tmp_path):
    bag = _moving_bag(tmp_path / "b", n=3, odom=False)
    for k in range(3):
        t = 100.0 + k
        bag.put("/odom", bag.m.ODOM, bag.m.odometry(t, "odom", "base_link", pose_x(0.5 * k)), t)
    text = _error(bag.close())
    assert "/odom: no odometry for the scans: no scan stamp (1.000..2.000 s) within the motion's time span" in text


def test_a_topic_of_another_type(tmp_path):
    text = _error(_moving_bag(tmp_path / "b").close(), BagConfig(points="/odom"))
    assert "/odom: is nav_msgs/msg/Odometry, expected sensor_msgs/msg/PointCloud2" in text
