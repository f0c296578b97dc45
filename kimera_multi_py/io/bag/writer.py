"""Keyframes -> a ROS 1 or ROS 2 bag of standard messages, and the bag's config (docs/bags.md).

Robot ``r``'s topics are under ``/robot{r}``: the scan (``points``: PointCloud2 with float32 x,
y, z and a ``class`` field; or with ``camera``: ``depth/image`` 32FC1 in metres with +inf for
misses, ``semantic/image`` and ``camera_info``), ``odom`` (nav_msgs/Odometry, T_odom_base),
``tf`` (odom -> base_link), ``tf_static`` (base_link -> the sensor frame) and, when known,
``ground_truth`` (geometry_msgs/PoseStamped, T_world_base). The bag's config, next to it as
``BAG.toml``, names all of them, so ``--source bag:BAG`` reads it back as it was written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.core.semantics import CLASS_COLORS, CLASS_NAMES
from kimera_multi_py.io.bag.config import CONFIG_SUFFIX
from kimera_multi_py.io.bag.depth import R_FLU_OPTICAL
from kimera_multi_py.io.bag.pointcloud import cloud_payload
from kimera_multi_py.io.bag.typestores import Messages

Format = Literal["ros1", "ros2"]
LABEL_WRITE = ("mono8", "mono16", "rgb8", "bgr8")


def stamp_ns(stamp: float) -> int:
    return int(round(stamp * 1e9))


class BagWriter:
    """Writes robots' keyframes into one bag (``fmt`` ``ros1``: a ``.bag`` file; ``ros2``: a folder).

    ``camera`` = ``(K, rows, cols)`` writes depth + semantic images (the scan's rays must be the
    camera's pixels, row-major); ``extrinsic`` is T_base_sensor (sensor frame: x forward, z up);
    ``float64``: the cloud's x, y, z as FLOAT64 fields, depth as 64FC1 (default FLOAT32, 32FC1).
    """

    def __init__(self, path: str | Path, fmt: Format = "ros2", *, camera: tuple[np.ndarray, int, int] | None = None,
                 label_encoding: str = "mono16", extrinsic: np.ndarray | None = None, float64: bool = False) -> None:
        self.path = Path(path)
        if fmt not in ("ros1", "ros2"):
            raise ConfigError("format", f"expected ros1 or ros2, got {fmt!r}")
        if fmt == "ros1" and self.path.suffix != ".bag":
            raise ConfigError("out", f"{self.path}: a ROS 1 bag's file name ends in .bag")
        if label_encoding not in LABEL_WRITE:
            raise ConfigError("label-encoding", f"expected one of {', '.join(LABEL_WRITE)}, got {label_encoding!r}")
        if self.path.exists():
            raise ConfigError("out", f"{self.path} exists already")
        self.fmt = fmt
        self.camera = camera
        self.label_encoding = label_encoding
        self.xyz_type = "f8" if float64 else "f4"
        self.extrinsic = np.eye(4) if extrinsic is None else np.asarray(extrinsic, dtype=np.float64)
        self.msgs = Messages(fmt)
        self.writer = self.msgs.writer(self.path)
        self._conns: dict[str, Any] = {}
        self._robots: set[int] = set()
        self.max_range = 0.0

    # ------------------------------------------------------------------ low level
    def _write(self, topic: str, msgtype: str, msg: Any, stamp: float) -> None:
        if topic not in self._conns:
            self._conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.msgs.store)
        self.writer.write(self._conns[topic], stamp_ns(stamp), self.msgs.serialize(msg, msgtype))

    def _sensor_frame(self) -> str:
        return "camera_optical" if self.camera is not None else "sensor"

    # ------------------------------------------------------------------ keyframes
    def add(self, robot: int, kf: KeyframeInput, T_odom_sensor: np.ndarray,
            true_pose: np.ndarray | None = None) -> None:
        """Robot ``robot``'s keyframe, taken at ``T_odom_sensor`` (the chained odometry)."""
        ns, m = f"/robot{robot}", self.msgs
        self.max_range = max(self.max_range, float(kf.max_range))
        T_base = T_odom_sensor @ np.linalg.inv(self.extrinsic)
        T_base_frame = self.extrinsic.copy()
        if self.camera is not None:
            T_base_frame[:3, :3] = T_base_frame[:3, :3] @ R_FLU_OPTICAL
        if robot not in self._robots:
            self._robots.add(robot)
            static = m.transform(kf.stamp, "base_link", self._sensor_frame(), T_base_frame)
            self._write(f"{ns}/tf_static", m.TF, m.tf_message([static]), kf.stamp)
        self._write(f"{ns}/odom", m.ODOM, m.odometry(kf.stamp, "odom", "base_link", T_base), kf.stamp)
        self._write(f"{ns}/tf", m.TF, m.tf_message([m.transform(kf.stamp, "odom", "base_link", T_base)]), kf.stamp)
        if true_pose is not None:
            true_base = true_pose @ np.linalg.inv(self.extrinsic)
            self._write(f"{ns}/ground_truth", m.POSE, m.pose_stamped(kf.stamp, "world", true_base), kf.stamp)
        if self.camera is None:
            self._add_cloud(ns, kf)
        else:
            self._add_images(ns, kf)

    def _add_cloud(self, ns: str, kf: KeyframeInput) -> None:
        fields, step, data = cloud_payload(kf.points, np.where(kf.hit, kf.labels, 0), xyz_type=self.xyz_type)
        msg = self.msgs.cloud(kf.stamp, self._sensor_frame(), fields, step, data, len(kf.points))
        self._write(f"{ns}/points", self.msgs.CLOUD, msg, kf.stamp)

    def _add_images(self, ns: str, kf: KeyframeInput) -> None:
        assert self.camera is not None
        K, rows, cols = self.camera
        if len(kf.points) != rows * cols:
            raise ConfigError("camera", f"a scan of {len(kf.points)} rays is not a {rows} x {cols} image")
        z = (kf.points @ R_FLU_OPTICAL)[:, 2]  # optical z = sensor x
        depth = np.where(kf.hit, z, np.inf).astype(np.float64 if self.xyz_type == "f8" else np.float32)
        depth = depth.reshape(rows, cols)
        labels = np.where(kf.hit, kf.labels, 0).reshape(rows, cols)
        m, frame = self.msgs, self._sensor_frame()
        encoding = "64FC1" if self.xyz_type == "f8" else "32FC1"
        self._write(f"{ns}/depth/image", m.IMAGE, m.image(kf.stamp, frame, encoding, depth), kf.stamp)
        if self.label_encoding in ("rgb8", "bgr8"):
            img = CLASS_COLORS[labels]
            img = img[..., ::-1] if self.label_encoding == "bgr8" else img
        else:
            img = labels.astype(np.uint8 if self.label_encoding == "mono8" else np.uint16)
        self._write(f"{ns}/semantic/image", m.IMAGE, m.image(kf.stamp, frame, self.label_encoding,
                                                               np.ascontiguousarray(img)), kf.stamp)
        self._write(f"{ns}/camera_info", m.INFO, m.camera_info(kf.stamp, frame, K, rows, cols), kf.stamp)

    def close(self, *, noise: dict[str, float] | None = None, origin: dict[str, Any] | None = None) -> Path:
        """Close the bag and write its config ``BAG.toml``; return the config's path."""
        self.writer.close()
        lines = ["# written by kimera-multi record: how to read this bag (docs/bags.md)",
                 f"max_range = {self.max_range!r}", "sync_tolerance = 0.005", "motion = \"odometry\""]
        if self.camera is not None:
            lines += ['depth = "/depth/image"', 'labels = "/semantic/image"', 'camera_info = "/camera_info"']
            if self.label_encoding in ("rgb8", "bgr8"):
                table = Path(str(self.path) + ".colours.csv")
                table.write_text("name,red,green,blue,id\n" + "".join(
                    f"{n},{c[0]},{c[1]},{c[2]},{i}\n" for i, (n, c) in enumerate(zip(CLASS_NAMES, CLASS_COLORS,
                                                                                      strict=True))))
                lines.append(f'colour_table = "{table.name}"')
        if not np.allclose(self.extrinsic, np.eye(4)):
            q = Rotation.from_matrix(self.extrinsic[:3, :3]).as_quat()
            lines.append(f"# base_link -> sensor is on tf_static too: extrinsic = {_floats(self.extrinsic[:3, 3])}"
                         f" + {_floats(q)}")
        lines += ["", "[keyframes]  # every scan in this bag is a keyframe", "distance = 0.0", "angle_deg = 0.0"]
        if noise:
            lines += ["", "[noise]"] + [f"{k} = {float(v)!r}" for k, v in noise.items()]
        if origin:
            lines += ["", "[origin]"] + [f"{k} = {_toml(v)}" for k, v in origin.items() if v is not None]
        path = Path(str(self.path) + CONFIG_SUFFIX)
        path.write_text("\n".join(lines) + "\n")
        return path

    def abort(self) -> None:
        if hasattr(self.writer, "abort"):
            self.writer.abort()


def _floats(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{float(x):.9g}" for x in v) + "]"


def _toml(v: Any) -> str:
    """A TOML value: an int as is, anything else as a quoted string."""
    if isinstance(v, int) and not isinstance(v, bool):
        return str(v)
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'

