"""The message types of ROS 1 (Noetic) and ROS 2 (Humble), built and serialised with ``rosbags``.

The two differ in small ways (ROS 1 headers carry ``seq``, its CameraInfo spells ``D K R P``
in capitals, ``tf2_msgs/TFMessage`` is not in rosbags' Noetic store); :class:`Messages` hides
them so a writer builds each message once (docs/bags.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore
from scipy.spatial.transform import Rotation

TF_MSG = "geometry_msgs/TransformStamped[] transforms\n"


def typestore(fmt: str) -> Typestore:
    """The type store of ``ros1`` (Noetic, with tf2_msgs/TFMessage) or ``ros2`` (Humble)."""
    if fmt == "ros1":
        store = get_typestore(Stores.ROS1_NOETIC)
        store.register(get_types_from_msg(TF_MSG, "tf2_msgs/msg/TFMessage"))
        return store
    return get_typestore(Stores.ROS2_HUMBLE)


class Messages:
    """Builders of the messages a bag writer needs, for one ROS version."""

    CLOUD = "sensor_msgs/msg/PointCloud2"
    IMAGE = "sensor_msgs/msg/Image"
    INFO = "sensor_msgs/msg/CameraInfo"
    ODOM = "nav_msgs/msg/Odometry"
    TF = "tf2_msgs/msg/TFMessage"
    POSE = "geometry_msgs/msg/PoseStamped"
    PATH = "nav_msgs/msg/Path"
    MARKERS = "visualization_msgs/msg/MarkerArray"

    def __init__(self, fmt: str) -> None:
        self.fmt = fmt
        self.store = typestore(fmt)
        self.t = self.store.types

    def writer(self, path: Path) -> Writer1 | Writer2:
        w: Writer1 | Writer2 = Writer1(path) if self.fmt == "ros1" else Writer2(path, version=8)
        w.open()
        return w

    def serialize(self, msg: Any, msgtype: str) -> memoryview:
        return self.store.serialize_ros1(msg, msgtype) if self.fmt == "ros1" else self.store.serialize_cdr(msg, msgtype)

    def _new(self, typename: str, **fields: Any) -> Any:
        return self.t[typename](**fields)

    def header(self, stamp: float, frame: str) -> Any:
        ns = int(round(stamp * 1e9))
        time = self._new("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        extra = {"seq": 0} if self.fmt == "ros1" else {}
        return self._new("std_msgs/msg/Header", stamp=time, frame_id=frame, **extra)

    def pose(self, T: np.ndarray) -> Any:
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        return self._new("geometry_msgs/msg/Pose",
                         position=self._new("geometry_msgs/msg/Point", x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                         orientation=self._new("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))

    def transform(self, stamp: float, parent: str, child: str, T: np.ndarray) -> Any:
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        tr = self._new("geometry_msgs/msg/Transform",
                       translation=self._new("geometry_msgs/msg/Vector3", x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                       rotation=self._new("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))
        return self._new("geometry_msgs/msg/TransformStamped", header=self.header(stamp, parent),
                         child_frame_id=child, transform=tr)

    def tf_message(self, transforms: list[Any]) -> Any:
        return self._new(self.TF, transforms=transforms)

    def odometry(self, stamp: float, parent: str, child: str, T: np.ndarray) -> Any:
        cov = np.zeros(36)
        pose = self._new("geometry_msgs/msg/PoseWithCovariance", pose=self.pose(T), covariance=cov)
        zero = self._new("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
        twist = self._new("geometry_msgs/msg/TwistWithCovariance",
                          twist=self._new("geometry_msgs/msg/Twist", linear=zero, angular=zero), covariance=cov)
        return self._new(self.ODOM, header=self.header(stamp, parent), child_frame_id=child, pose=pose, twist=twist)

    def pose_stamped(self, stamp: float, frame: str, T: np.ndarray) -> Any:
        return self._new(self.POSE, header=self.header(stamp, frame), pose=self.pose(T))

    def cloud(self, stamp: float, frame: str, fields: list[tuple[str, int, int]], step: int, data: bytes,
              n: int) -> Any:
        pf = [self._new("sensor_msgs/msg/PointField", name=name, offset=off, datatype=dt, count=1)
              for name, off, dt in fields]
        return self._new(self.CLOUD, header=self.header(stamp, frame), height=1, width=n, fields=pf,
                         is_bigendian=False, point_step=step, row_step=step * n,
                         data=np.frombuffer(data, dtype=np.uint8), is_dense=True)

    def image(self, stamp: float, frame: str, encoding: str, pixels: np.ndarray) -> Any:
        h, w = pixels.shape[:2]
        data = np.frombuffer(np.ascontiguousarray(pixels).astype(pixels.dtype.newbyteorder("<")).tobytes(),
                             dtype=np.uint8)
        return self._new(self.IMAGE, header=self.header(stamp, frame), height=h, width=w, encoding=encoding,
                         is_bigendian=0, step=len(data) // h, data=data)

    def camera_info(self, stamp: float, frame: str, K: np.ndarray, rows: int, cols: int) -> Any:
        P = np.hstack([K, np.zeros((3, 1))])
        roi = self._new("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                        do_rectify=False)
        arrays = {"d": np.zeros(5), "k": K.ravel().astype(np.float64), "r": np.eye(3).ravel(),
                  "p": P.ravel().astype(np.float64)}
        if self.fmt == "ros1":
            arrays = {k.upper(): v for k, v in arrays.items()}
        return self._new(self.INFO, header=self.header(stamp, frame), height=rows, width=cols,
                         distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **arrays)
