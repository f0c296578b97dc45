"""A run's results as a ROS 2 bag for Foxglove and RViz: ``--out-bag`` (docs/bags.md).

Per robot ``r``, in the team frame ``team``: ``/robot{r}/path`` (nav_msgs/Path, the optimised
keyframe poses), ``/robot{r}/team_map`` (sensor_msgs/PointCloud2 of the occupied cells' centres
with a ``class`` field) and ``/robot{r}/objects`` (visualization_msgs/MarkerArray, one box per
object in its class colour).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.semantics import CLASS_COLORS, CLASS_NAMES
from kimera_multi_py.io.bag.pointcloud import cloud_payload
from kimera_multi_py.io.bag.typestores import Messages

FRAME = "team"


@dataclass
class RobotOutput:
    """What one robot ends a run with, as plain arrays."""

    robot: int
    stamps: np.ndarray  # (n,)
    poses: np.ndarray  # (n, 4, 4) in the team frame
    cells: np.ndarray  # (m, 3) occupied cell centres
    cell_classes: np.ndarray  # (m,) class ids
    cell_size: float
    objects: list[dict[str, Any]] = field(default_factory=list)  # class, lo, hi


def _markers(m: Messages, stamp: float, objects: list[dict[str, Any]]) -> Any:
    t = m.t
    zero_time = t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)
    markers = []
    for i, ob in enumerate(objects):
        lo, hi, cls = np.asarray(ob["lo"], dtype=float), np.asarray(ob["hi"], dtype=float), int(ob["class"])
        T = np.eye(4)
        T[:3, 3] = (lo + hi) / 2
        size = np.maximum(hi - lo, 0.01)
        c = CLASS_COLORS[cls] / 255.0
        markers.append(t["visualization_msgs/msg/Marker"](
            header=m.header(stamp, FRAME), ns=CLASS_NAMES[cls], id=i, type=1, action=0, pose=m.pose(T),
            scale=t["geometry_msgs/msg/Vector3"](x=size[0], y=size[1], z=size[2]),
            color=t["std_msgs/msg/ColorRGBA"](r=c[0], g=c[1], b=c[2], a=0.6), lifetime=zero_time,
            frame_locked=False, points=[], colors=[], texture_resource="",
            texture=t["sensor_msgs/msg/CompressedImage"](header=m.header(stamp, FRAME), format="",
                                                         data=np.zeros(0, dtype=np.uint8)),
            uv_coordinates=[], text=CLASS_NAMES[cls], mesh_resource="",
            mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, dtype=np.uint8)),
            mesh_use_embedded_materials=False))
    return t[Messages.MARKERS](markers=markers)


def write_outputs_bag(path: str | Path, robots: list[RobotOutput]) -> Path:
    """Write each robot's path, team map and objects into a new ROS 2 bag at ``path``."""
    path = Path(path)
    if path.exists():
        raise ConfigError("out-bag", f"{path} exists already")
    m = Messages("ros2")
    writer = m.writer(path)
    try:
        for r in robots:
            ns = f"/robot{r.robot}"
            stamp = float(r.stamps[-1]) if len(r.stamps) else 0.0
            ns_t = int(round(stamp * 1e9))
            poses = [m.pose_stamped(float(s), FRAME, T) for s, T in zip(r.stamps, r.poses, strict=True)]
            conn = writer.add_connection(f"{ns}/path", m.PATH, typestore=m.store)
            writer.write(conn, ns_t, m.serialize(m.t[m.PATH](header=m.header(stamp, FRAME), poses=poses), m.PATH))
            fields, step, data = cloud_payload(np.asarray(r.cells, dtype=float).reshape(-1, 3), r.cell_classes)
            conn = writer.add_connection(f"{ns}/team_map", m.CLOUD, typestore=m.store)
            writer.write(conn, ns_t, m.serialize(m.cloud(stamp, FRAME, fields, step, data, len(r.cells)), m.CLOUD))
            conn = writer.add_connection(f"{ns}/objects", m.MARKERS, typestore=m.store)
            writer.write(conn, ns_t, m.serialize(_markers(m, stamp, r.objects), m.MARKERS))
    except BaseException:
        writer.abort()
        raise
    writer.close()
    return path
