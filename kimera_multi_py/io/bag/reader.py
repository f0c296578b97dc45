"""A ROS 1 or ROS 2 bag as a robot's keyframe source (docs/bags.md).

Opening a :class:`BagSource` reads the bag's small streams whole (odometry or TF, the scans'
headers) and decides every keyframe: scans are posed by the motion interpolated at their
stamps, composed with the sensor's extrinsics, and one becomes a keyframe after
``keyframes.distance`` metres or ``keyframes.angle_deg`` degrees of motion. Everything a user
must fix is found here, before the run, and raised as one :class:`BagError` line naming the
topic. Iterating then reads and converts only the keyframes' scans.

The keyframe frame is the sensor's origin with the body convention (x forward, y left, z up):
a camera's optical frame is turned into it. Points are in that frame; a return at or beyond
``max_range`` is a miss (free space up to ``max_range``); a point whose class does not map onto
the vocabulary is dropped and counted in :attr:`BagSource.dropped`.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.typesys import Stores, get_typestore

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.io.bag.config import BagConfig, config_for, read_colour_table
from kimera_multi_py.io.bag.depth import DEPTH_ENCODINGS, LABEL_ENCODINGS, R_FLU_OPTICAL, camera_matrix
from kimera_multi_py.io.bag.errors import BagError
from kimera_multi_py.io.bag.pointcloud import CLASS_TYPES, cloud_dtype
from kimera_multi_py.io.bag.scan import labelled_rays
from kimera_multi_py.io.bag.tf import PoseSeries, TfGap, TfTree, msg_pose, pose7

log = logging.getLogger(__name__)

CLOUD, IMAGE, INFO = "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
ODOM, POSE = "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped"
TFM = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")  # ROS 1's older tf has the same layout
MOTION_EPS = 1e-6  # metres and radians: below this a whole stream has not moved


def _stamp(msg: Any) -> float:
    """Seconds of a header stamp: its nanoseconds, rounded once."""
    return (int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)) / 1e9


def open_bag(path: Path) -> AnyReader:
    """An opened :class:`AnyReader` (ROS 1 ``.bag`` file or ROS 2 folder); unreadable -> BagError."""
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, FileNotFoundError, OSError, ValueError) as exc:
        raise BagError(str(path), "", f"not a readable ROS 1 or ROS 2 bag: {exc}") from None
    return reader


def namespaced_robots(topics: Iterable[str]) -> list[int]:
    """The robot ids ``r`` of a bag's ``/robot{r}/...`` topics."""
    return sorted({int(m.group(1)) for t in topics if (m := re.match(r"^/robot(\d+)/", t))})


def bag_robots(path: str | Path) -> list[int]:
    """The robots of a team's bag (its ``/robot{r}`` namespaces); ``[0]`` for a bag of one robot."""
    reader = open_bag(Path(path))
    try:
        return namespaced_robots(reader.topics) or [0]
    finally:
        reader.close()


@dataclass
class _Plan:
    """The keyframes a bag yields: per keyframe the scan's message ordinals, stamp and pose."""

    scan: np.ndarray  # ordinals of the scan (depth image or cloud) messages
    labels: np.ndarray  # ordinals of the matched semantic images (depth input only)
    stamps: np.ndarray
    poses: np.ndarray  # T_odom_keyframe
    T_base_kf: np.ndarray  # the keyframe frame in the base frame (extrinsics, optical turn)


class BagSource:
    """Robot ``robot``'s keyframes from a bag, from ``start`` on (an iterator; see the module docstring).

    ``config`` is a :class:`BagConfig` or a file; default: the bag's own ``BAG.toml``, else the defaults.
    """

    def __init__(self, path: str | Path, robot: int, start: int = 0, resume: dict[str, Any] | None = None,
                 config: BagConfig | str | Path | None = None) -> None:
        self.path = Path(path)
        self.cfg = config if isinstance(config, BagConfig) else config_for(self.path, config)[0]
        self.robot, self.start = int(robot), int(start)
        self.dropped = {"unmapped": 0, "invalid": 0}
        self._colours = read_colour_table(self.cfg.colour_table) if self.cfg.colour_table else None
        self._reader = open_bag(self.path)
        try:
            self.namespace = self._namespace()
            self._plan = self._index()
        except BaseException:
            self._reader.close()
            raise
        n = len(self._plan.stamps)
        if not 0 <= self.start <= n:
            raise ConfigError("start", f"{self.path}: robot {robot} has keyframes 0..{n - 1}, cannot start at {start}")
        if resume is not None and (not isinstance(resume, dict) or resume.get("robot") != self.robot
                                   or resume.get("next") != self.start):
            raise ConfigError("resume", f"not the state of robot {self.robot}'s bag at keyframe {self.start}")
        self._next = self.start
        self._messages: Iterator[KeyframeInput] | None = None

    # ------------------------------------------------------------------ protocol
    @property
    def num_keyframes(self) -> int:
        return len(self._plan.stamps)

    @property
    def next_index(self) -> int:
        return self._next

    @property
    def stamps(self) -> np.ndarray:
        return self._plan.stamps

    @property
    def poses(self) -> np.ndarray:
        """T_odom_keyframe of every keyframe (the chained odometry the agent receives)."""
        return self._plan.poses

    @property
    def T_base_keyframe(self) -> np.ndarray:
        """The keyframe frame in the base frame (the extrinsic, and an optical frame's turn)."""
        return self._plan.T_base_kf

    @property
    def manifest(self) -> dict[str, Any]:
        """The agents' noise model, as a recording's manifest states it (see team/build.py)."""
        noise, kf = self.cfg.noise, self.cfg.keyframes
        dist = noise.keyframe_distance if noise.keyframe_distance is not None else (kf.distance or 0.5)
        return {"sensor": {"odometry": {"rot_sigma_deg": noise.rot_sigma_deg, "trans_sigma": noise.trans_sigma},
                           "keyframe_distance": dist, "max_range": self.cfg.max_range}}

    def state(self) -> dict[str, Any]:
        return {"robot": self.robot, "next": self._next}

    def __iter__(self) -> Iterator[KeyframeInput]:
        return self

    def __next__(self) -> KeyframeInput:
        if self._next >= self.num_keyframes:
            if self._messages is not None and any(self.dropped.values()):
                log.warning("%s: robot %d: dropped %d points of unmapped classes and %d non-finite points",
                            self.path, self.robot, self.dropped["unmapped"], self.dropped["invalid"],
                            extra={"robot": self.robot})
                self._messages = None
            self.close()
            raise StopIteration
        if self._messages is None:
            self._messages = self._keyframes(self._next)
        kf = next(self._messages)
        self._next += 1
        return kf

    def close(self) -> None:
        """Close the bag; a second call (the iterator closes it at its end) does nothing."""
        if self._reader.stack is not None:
            self._reader.close()

    def ground_truth(self) -> np.ndarray | None:
        """The true T_world_keyframe at every keyframe, from the bag's ``ground_truth`` topic (poses
        of the base frame, PoseStamped or Odometry); None when the bag has no such topic."""
        cfg = self.cfg
        if cfg.ground_truth is None:
            return None
        reader = open_bag(self.path)
        try:
            topic = cfg.topic(cfg.ground_truth, self.namespace)
            if topic not in reader.topics:
                return None
            msgtype = reader.topics[topic].msgtype
            if msgtype not in (POSE, ODOM):
                raise BagError(str(self.path), topic, f"is {msgtype}, expected {POSE} or {ODOM}")
            rows = []
            conns = [c for c in reader.connections if c.topic == topic]
            for conn, _, data in reader.messages(connections=conns):
                msg: Any = reader.deserialize(data, conn.msgtype)
                pose = msg.pose.pose if msgtype == ODOM else msg.pose
                rows.append((_stamp(msg), msg_pose(pose.position, pose.orientation)))
        finally:
            reader.close()
        try:
            truth = PoseSeries(np.array([t for t, _ in rows]), np.array([p for _, p in rows]).reshape(-1, 4, 4))
            return truth.at(self.stamps, cfg.sync_tolerance) @ self.T_base_keyframe
        except TfGap as exc:
            raise BagError(str(self.path), topic, f"ground truth: {exc}") from None

    # ------------------------------------------------------------------ topics
    def _namespace(self) -> str:
        """The config's namespace; else ``/robot{r}`` if the bag has it, else the bag's only robot's, else none."""
        if self.cfg.namespace is not None:
            return self.cfg.namespace.format(robot=self.robot).rstrip("/")
        robots = namespaced_robots(self._reader.topics)
        if self.robot in robots:
            return f"/robot{self.robot}"
        return f"/robot{robots[0]}" if len(robots) == 1 else ""

    def _topic(self, name: str, msgtype: str | tuple[str, ...], global_ok: bool = False) -> str:
        """The namespaced topic ``name``, checked to exist with one of the types ``msgtype``."""
        topics = self._reader.topics
        topic = self.cfg.topic(name, self.namespace)
        if topic not in topics and global_ok and name in topics:
            topic = name
        if topic not in topics:
            have = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(topics.items())) or "none"
            raise BagError(str(self.path), topic, f"not in the bag (robot {self.robot}); its topics: {have}")
        types = (msgtype,) if isinstance(msgtype, str) else msgtype
        if topics[topic].msgtype not in types:
            raise BagError(str(self.path), topic, f"is {topics[topic].msgtype}, expected {' or '.join(types)}")
        return topic

    def _read(self, topic: str, raw: bool = False) -> Iterator[tuple[int, Any]]:
        conns = [c for c in self._reader.connections if c.topic == topic]
        for conn, ts, data in self._reader.messages(connections=conns):
            yield ts, (data if raw else self._deserialize(topic, data, conn.msgtype))

    def _deserialize(self, topic: str, data: bytes, msgtype: str) -> Any:
        try:
            return self._reader.deserialize(data, msgtype)
        except (AnyReaderError, ValueError, IndexError, KeyError) as exc:
            raise BagError(str(self.path), topic, f"malformed {msgtype} message: {exc}") from None

    # ------------------------------------------------------------------ index
    def _index(self) -> _Plan:
        cfg = self.cfg
        scan_topic = self._topic(cfg.depth, IMAGE) if cfg.camera else self._topic(cfg.points, CLOUD)  # type: ignore[arg-type]
        tree = self._tf_tree()
        motion_topic, motion = self._motion(tree)
        stamps, frame, labels = self._scan_index(scan_topic)
        T_base_sensor = self._extrinsic(tree, frame, stamps[0])
        T_sensor_kf = np.eye(4)
        if cfg.is_optical:
            T_sensor_kf[:3, :3] = R_FLU_OPTICAL.T
        posed = motion.covers(stamps, cfg.sync_tolerance) if isinstance(motion, PoseSeries) else None
        try:
            if posed is None:
                posed = tree.covers(cfg.odom_frame, cfg.base_frame, stamps, cfg.sync_tolerance)
            if not posed.any():
                raise TfGap(f"no scan stamp ({stamps[0]:.3f}..{stamps[-1]:.3f} s) within the motion's time span")
            base = motion.at(stamps[posed], cfg.sync_tolerance) if isinstance(motion, PoseSeries) else \
                tree.lookup(cfg.odom_frame, cfg.base_frame, stamps[posed], cfg.sync_tolerance)
        except TfGap as exc:
            what = "TF chain with a gap" if cfg.motion == "tf" else "no odometry for the scans"
            raise BagError(str(self.path), motion_topic, f"{what}: {exc}") from None
        unposed = int((~posed & np.isfinite(stamps)).sum())
        if unposed:
            log.warning("%s: robot %d: %d of %d scans lie outside the motion's time span and are skipped",
                        self.path, self.robot, unposed, len(posed), extra={"robot": self.robot})
        poses = base @ T_base_sensor @ T_sensor_kf
        order = np.flatnonzero(posed)
        keep = self._select(poses)
        if not len(keep):
            raise BagError(str(self.path), scan_topic, f"robot {self.robot} yields no keyframe")
        idx = order[keep]
        return _Plan(idx, labels[idx] if labels is not None else idx, stamps[idx], poses[keep],
                     T_base_sensor @ T_sensor_kf)

    def _select(self, poses: np.ndarray) -> np.ndarray:
        """Keyframes by distance and angle moved since the last one (the first scan always)."""
        kf = self.cfg.keyframes
        if len(poses) == 0:
            return np.zeros(0, dtype=np.int64)
        if kf.distance == 0 and kf.angle_deg == 0:
            return np.arange(len(poses))
        angle = np.deg2rad(kf.angle_deg)
        chosen, last = [0], poses[0]
        for i in range(1, len(poses)):
            rel = inverse(last) @ poses[i]
            turned = np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1.0, 1.0))
            if np.linalg.norm(rel[:3, 3]) >= kf.distance or turned >= angle:
                chosen.append(i)
                last = poses[i]
        return np.asarray(chosen)

    def _tf_tree(self) -> TfTree:
        tree = TfTree()
        for name, static in ((self.cfg.tf_static, True), (self.cfg.tf, False)):
            topic = self.cfg.topic(name, self.namespace)
            topic = topic if topic in self._reader.topics else name
            if topic in self._reader.topics:
                if self._reader.topics[topic].msgtype not in TFM:
                    raise BagError(str(self.path), topic, f"is {self._reader.topics[topic].msgtype}, "
                                                          f"expected {TFM[0]}")
                for _, msg in self._read(topic):
                    tree.add(msg, static)
        return tree

    def _motion(self, tree: TfTree) -> tuple[str, PoseSeries | TfTree]:
        cfg = self.cfg
        if cfg.motion == "tf":
            topic = self._topic(cfg.tf, TFM, global_ok=True)
            try:  # the chain exists
                tree.lookup(cfg.odom_frame, cfg.base_frame, np.zeros(0), np.inf)
            except TfGap as exc:
                raise BagError(str(self.path), topic, f"TF chain with a gap: {exc}") from None
            stamps = sorted({s for e in tree.edges if e not in tree.static for s in tree.series(e).stamps})
            if not stamps:
                raise BagError(str(self.path), topic, f"no motion: {cfg.odom_frame} -> {cfg.base_frame} is static")
            poses = tree.lookup(cfg.odom_frame, cfg.base_frame, np.array(stamps), cfg.sync_tolerance)
            self._check_motion(topic, poses)
            return topic, tree
        topic = self._topic(cfg.odometry, ODOM)
        rows = [(_stamp(m), msg_pose(m.pose.pose.position, m.pose.pose.orientation)) for _, m in self._read(topic)]
        poses = np.array([p for _, p in rows]).reshape(-1, 4, 4)
        if not np.all(np.isfinite(poses)):
            raise BagError(str(self.path), topic, "non-finite poses (NaN or inf)")
        self._check_motion(topic, poses)
        return topic, PoseSeries(np.array([s for s, _ in rows]), poses)

    def _check_motion(self, topic: str, poses: np.ndarray) -> None:
        if len(poses) < 2:
            raise BagError(str(self.path), topic, f"no motion: {len(poses)} pose(s) in the stream")
        moved = np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1).max()
        turned = np.abs(poses[:, :3, :3] - poses[0, :3, :3]).max()
        if moved < MOTION_EPS and turned < MOTION_EPS:
            raise BagError(str(self.path), topic, f"no motion: all {len(poses)} poses are the same")

    def _extrinsic(self, tree: TfTree, frame: str, t0: float) -> np.ndarray:
        cfg = self.cfg
        if cfg.extrinsic is not None:
            return pose7(cfg.extrinsic)
        sensor = (cfg.sensor_frame or frame).lstrip("/")
        if sensor == cfg.base_frame.lstrip("/") or not sensor:
            return np.eye(4)
        try:
            return tree.lookup(cfg.base_frame, sensor, np.array([t0]), np.inf)[0]
        except TfGap as exc:
            topic = self.cfg.topic(cfg.tf_static, self.namespace)
            raise BagError(str(self.path), topic, f"TF chain with a gap (the sensor's extrinsics; or set "
                                                  f"extrinsic in the bag config): {exc}") from None

    def _scan_index(self, topic: str) -> tuple[np.ndarray, str, np.ndarray | None]:
        """Stamps of the scans, the sensor frame and (depth input) each scan's semantic image ordinal."""
        cfg, stamps, frame = self.cfg, [], ""
        for _, msg in self._read(topic):
            if not frame:
                frame = msg.header.frame_id
                self._check_scan(topic, msg)
            stamps.append(_stamp(msg))
        if not stamps:
            raise BagError(str(self.path), topic, f"no messages (robot {self.robot} yields no keyframe)")
        s = np.asarray(stamps)
        if not cfg.camera:
            return s, frame, None
        lt = self._topic(cfg.labels, IMAGE)
        ltimes = []
        for i, (_, msg) in enumerate(self._read(lt)):
            if i == 0:
                self._check_labels(lt, msg)
            ltimes.append(_stamp(msg))
        info_topic = self._topic(cfg.camera_info, INFO)
        info = next((m for _, m in self._read(info_topic)), None)
        try:
            self._K = camera_matrix(info)
        except (ValueError, AttributeError, TypeError) as exc:
            raise BagError(str(self.path), info_topic, f"unusable camera model: {exc}") from None
        lts = np.asarray(ltimes)
        order = np.argsort(lts, kind="stable")
        at = np.clip(np.searchsorted(lts[order], s), 1, max(len(lts) - 1, 1))
        near = np.where(np.abs(lts[order][at - 1] - s) <= np.abs(lts[order][np.minimum(at, len(lts) - 1)] - s),
                        at - 1, np.minimum(at, len(lts) - 1)) if len(lts) else np.zeros(0, dtype=int)
        match = order[near] if len(lts) else np.zeros(len(s), dtype=int)
        ok = np.abs(lts[match] - s) <= cfg.sync_tolerance if len(lts) else np.zeros(len(s), dtype=bool)
        if not ok.any():
            span = f"{lts.min():.3f}..{lts.max():.3f} s" if len(lts) else "no messages"
            raise BagError(str(self.path), lt, f"never within {cfg.sync_tolerance} s of a depth image on {topic} "
                                               f"(depth {s.min():.3f}..{s.max():.3f} s, labels {span})")
        if (~ok).any():
            log.warning("%s: %d depth images have no semantic image within %g s and are skipped", topic,
                        int((~ok).sum()), cfg.sync_tolerance, extra={"robot": self.robot})
        s = np.where(ok, s, np.nan)
        return s, frame, np.where(ok, match, -1)

    def _check_scan(self, topic: str, msg: Any) -> None:
        if self.cfg.camera:
            if msg.encoding not in DEPTH_ENCODINGS:
                raise BagError(str(self.path), topic, f"unsupported depth encoding {msg.encoding!r} "
                                                      f"(supported: {', '.join(DEPTH_ENCODINGS)})")
            return
        try:
            dtype = cloud_dtype(msg)
        except ValueError as exc:
            raise BagError(str(self.path), topic, str(exc)) from None
        names = dtype.names or ()
        if not {"x", "y", "z"} <= set(names):
            raise BagError(str(self.path), topic, f"no x, y, z fields (fields: {', '.join(names)})")
        f = self.cfg.class_field
        if f not in names:
            raise BagError(str(self.path), topic, f"no class field {f!r} (fields: {', '.join(names)}); set "
                                                  f"class_field in the bag config")
        kind = dtype.fields[f][0].str[1:]  # type: ignore[index]
        if kind not in CLASS_TYPES:
            raise BagError(str(self.path), topic, f"unsupported class field type {dtype.fields[f][0]}"  # type: ignore[index]
                                                  f" (supported: uint8, uint16, int32)")

    def _check_labels(self, topic: str, msg: Any) -> None:
        if msg.encoding not in LABEL_ENCODINGS:
            raise BagError(str(self.path), topic, f"unsupported semantic image encoding {msg.encoding!r} "
                                                  f"(supported: {', '.join(LABEL_ENCODINGS)})")
        if msg.encoding in ("rgb8", "bgr8") and self._colours is None:
            raise BagError(str(self.path), topic, f"{msg.encoding} semantic images need colour_table in the "
                                                  f"bag config")

    # ------------------------------------------------------------------ keyframes
    def _keyframes(self, first: int) -> Iterator[KeyframeInput]:
        """Keyframes ``first..`` converted from their messages (read once, in bag order)."""
        plan, cfg = self._plan, self.cfg
        scan_topic = cfg.topic(cfg.depth if cfg.camera else cfg.points, self.namespace)  # type: ignore[arg-type]
        label_topic = cfg.topic(cfg.labels, self.namespace)
        want = {scan_topic: set(plan.scan[first:].tolist())}
        if cfg.camera:
            want[label_topic] = set(plan.labels[first:].tolist())
        conns = [c for c in self._reader.connections if c.topic in want]
        seen = dict.fromkeys(want, -1)
        held: dict[tuple[str, int], Any] = {}
        k = first
        for conn, _, data in self._reader.messages(connections=conns):
            seen[conn.topic] += 1
            if seen[conn.topic] in want[conn.topic]:
                held[(conn.topic, seen[conn.topic])] = self._deserialize(conn.topic, data, conn.msgtype)
            while k < len(plan.stamps) and (scan_topic, int(plan.scan[k])) in held and (
                    not cfg.camera or (label_topic, int(plan.labels[k])) in held):
                scan = held.pop((scan_topic, int(plan.scan[k])))
                labels = held.pop((label_topic, int(plan.labels[k])), None) if cfg.camera else None
                yield self._convert(k, scan, labels)
                k += 1

    def _odometry(self, k: int) -> np.ndarray:
        return np.eye(4) if k == 0 else inverse(self._plan.poses[k - 1]) @ self._plan.poses[k]

    def _convert(self, k: int, scan: Any, labels: Any) -> KeyframeInput:
        try:
            pts, ids, hit = labelled_rays(self.cfg, scan, labels, getattr(self, "_K", None), self._colours,
                                          self.dropped)
        except (ValueError, KeyError, TypeError) as exc:
            cfg = self.cfg
            topic = cfg.topic(cfg.depth if cfg.camera else cfg.points, self.namespace)  # type: ignore[arg-type]
            raise BagError(str(self.path), topic, f"keyframe {k}: unreadable scan: {exc}") from None
        return KeyframeInput(k, float(self._plan.stamps[k]), self._odometry(k), pts, ids, hit,
                             float(self.cfg.max_range))
