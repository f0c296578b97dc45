"""Bags for the bag tests: written by the simulator's recorder, or by hand for the bad ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.io.bag.typestores import Messages
from kimera_multi_py.sim.bag_recording import write_bag
from kimera_multi_py.sim.scenario import load_scenario

REPO = Path(__file__).resolve().parents[3]
TINY = REPO / "sims" / "tiny.toml"
SMALL = REPO / "sims" / "small.toml"


@pytest.fixture(scope="session")
def tiny_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The tiny scenario (seed 0) as bags: PointCloud2 (ROS 2, ROS 1), depth + labels (ROS 2; 32FC1,
    and 64FC1 as ``camera64``)."""
    d = tmp_path_factory.mktemp("bags")
    cfg = load_scenario(TINY)
    return {"cloud": write_bag(d / "cloud", cfg, "ros2", scenario_path=TINY).with_suffix(""),
            "ros1": Path(str(write_bag(d / "cloud.bag", cfg, "ros1", scenario_path=TINY)).removesuffix(".toml")),
            "camera": write_bag(d / "camera", cfg, "ros2", camera=True, scenario_path=TINY).with_suffix(""),
            "camera64": write_bag(d / "camera64", cfg, "ros2", camera=True, scenario_path=TINY,
                                  float64=True).with_suffix("")}


class HandBag:
    """A bag written message by message (ROS 2 unless ``fmt``), for the bad-bag tests."""

    def __init__(self, path: Path, fmt: str = "ros2") -> None:
        self.path, self.m = path, Messages(fmt)
        self.writer = self.m.writer(path)
        self.conns: dict[str, object] = {}

    def put(self, topic: str, msgtype: str, msg: object, stamp: float) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.m.store)
        self.writer.write(self.conns[topic], int(stamp * 1e9), self.m.serialize(msg, msgtype))

    def topic(self, topic: str, msgtype: str) -> None:
        self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.m.store)

    def close(self) -> Path:
        self.writer.close()
        return self.path


def pose_x(x: float, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[0, 3] = x
    return T


def cloud_msg(m: Messages, stamp: float, frame: str = "sensor", dtype: str = "u2", n: int = 20) -> object:
    rng = np.random.default_rng(int(stamp * 10))
    pts = rng.uniform(-3, 3, (n, 3))
    arr = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("class", "<" + dtype)])
    arr["x"], arr["y"], arr["z"], arr["class"] = pts[:, 0], pts[:, 1], pts[:, 2], 1 + np.arange(n) % 5
    codes = {"u1": 2, "u2": 4, "i4": 5, "f4": 7}
    layout = arr.dtype.fields or {}
    fields = [(k, layout[k][1], codes[layout[k][0].str[1:]]) for k in ("x", "y", "z", "class")]
    return m.cloud(stamp, frame, fields, arr.dtype.itemsize, arr.tobytes(), n)
