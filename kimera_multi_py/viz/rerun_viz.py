"""Rerun logging of a simulation run, headless into an ``.rrd`` file; ``NullViz`` when off."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from kimera_multi_py.core.geometry import rot_to_quat, transform_points
from kimera_multi_py.core.semantics import CLASS_COLORS, CLASS_NAMES

_ROBOT_COLORS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40],
                          [148, 103, 189], [140, 86, 75], [227, 119, 194], [127, 127, 127]], dtype=np.uint8)


Closures = list[tuple[np.ndarray, np.ndarray, bool]]  # (end a, end b, accepted)
Voxels = list[tuple[np.ndarray, np.ndarray]]  # per robot: (centres, class ids)
Boxes = tuple[np.ndarray, np.ndarray, np.ndarray]  # centres, sizes, class ids
People = list[tuple[int, np.ndarray]]  # (person id, track positions (n, 3) in time order)


class Viz(Protocol):
    def log_world(self, world: object) -> None: ...
    def log_keyframe(self, robot: int, stamp: float, est_pose: np.ndarray, true_pose: np.ndarray,
                     points_sensor: np.ndarray, labels: np.ndarray) -> None: ...
    def log_team(self, stamp: float, trajectories: list[np.ndarray], closures: Closures, voxels: Voxels,
                 objects: Boxes) -> None: ...
    def log_people(self, stamp: float, people: People) -> None: ...
    def log_scalar(self, path: str, stamp: float, value: float) -> None: ...
    def log_voxels(self, path: str, stamp: float, centers: np.ndarray, labels: np.ndarray) -> None: ...
    def close(self) -> None: ...


class NullViz:
    """Logs nothing."""

    def log_world(self, world: object) -> None:
        pass

    def log_keyframe(self, robot: int, stamp: float, est_pose: np.ndarray, true_pose: np.ndarray,
                     points_sensor: np.ndarray, labels: np.ndarray) -> None:
        pass

    def log_team(self, stamp: float, trajectories: list[np.ndarray], closures: Closures, voxels: Voxels,
                 objects: Boxes) -> None:
        pass

    def log_people(self, stamp: float, people: People) -> None:
        pass

    def log_scalar(self, path: str, stamp: float, value: float) -> None:
        pass

    def log_voxels(self, path: str, stamp: float, centers: np.ndarray, labels: np.ndarray) -> None:
        pass

    def close(self) -> None:
        pass


class RerunViz:
    """Writes a Rerun recording: world boxes, per-robot trajectories and labelled scans."""

    def __init__(self, path: str | Path, max_points: int = 1000) -> None:
        import rerun as rr

        self.rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("kimera-multi")
        self.rec.save(str(self.path))
        self.max_points = max_points
        self.est: dict[int, list[np.ndarray]] = {}
        self.true: dict[int, list[np.ndarray]] = {}

    def log_world(self, world: object) -> None:
        P = world.static  # type: ignore[attr-defined]
        rr = self.rr
        self.rec.log("world/primitives", rr.Boxes3D(
            centers=P.center, half_sizes=P.half, quaternions=rot_to_quat(P.rot),
            colors=CLASS_COLORS[P.label], labels=[CLASS_NAMES[i] for i in P.label],
        ), static=True)

    def log_keyframe(self, robot: int, stamp: float, est_pose: np.ndarray, true_pose: np.ndarray,
                     points_sensor: np.ndarray, labels: np.ndarray) -> None:
        rr = self.rr
        self.rec.set_time("sim", duration=float(stamp))
        color = _ROBOT_COLORS[robot % len(_ROBOT_COLORS)]
        self.est.setdefault(robot, []).append(est_pose[:3, 3])
        self.true.setdefault(robot, []).append(true_pose[:3, 3])
        self.rec.log(f"robots/r{robot}/estimate", rr.LineStrips3D([np.array(self.est[robot])], colors=[color]))
        self.rec.log(f"robots/r{robot}/truth", rr.LineStrips3D([np.array(self.true[robot])],
                                                                colors=[[200, 200, 200]]))
        step = max(1, len(points_sensor) // self.max_points)
        pts = transform_points(true_pose, points_sensor[::step])
        self.rec.log(f"robots/r{robot}/scan", rr.Points3D(pts, colors=CLASS_COLORS[labels[::step]], radii=0.02))

    def log_team(self, stamp: float, trajectories: list[np.ndarray], closures: Closures, voxels: Voxels,
                 objects: Boxes) -> None:
        """The team's estimate (world frame): optimised trajectories, loop closures (green accepted,
        red rejected), occupied voxels coloured by class and object boxes with labels."""
        rr = self.rr
        self.rec.set_time("sim", duration=float(stamp))
        for r, xyz in enumerate(trajectories):
            color = _ROBOT_COLORS[r % len(_ROBOT_COLORS)]
            self.rec.log(f"team/r{r}/trajectory", rr.LineStrips3D([xyz], colors=[color]))
        if closures:
            strips = [np.stack([a, b]) for a, b, _ in closures]
            colors = [[40, 200, 40] if ok else [220, 40, 40] for _, _, ok in closures]
            self.rec.log("team/loop_closures", rr.LineStrips3D(strips, colors=colors, radii=0.02))
        for r, (centers, labels) in enumerate(voxels):
            if len(centers):
                self.rec.log(f"team/r{r}/map", rr.Points3D(centers, colors=CLASS_COLORS[labels], radii=0.05))
        c, size, lab = objects
        if len(c):
            self.rec.log("team/objects", rr.Boxes3D(centers=c, sizes=size, colors=CLASS_COLORS[lab],
                                                    labels=[CLASS_NAMES[i] for i in lab]))

    def log_people(self, stamp: float, people: People) -> None:
        """Each tracked person (world frame, docs/algorithms/people.md): their track so far as a line and
        where they were last seen as a point labelled with their id."""
        rr = self.rr
        self.rec.set_time("sim", duration=float(stamp))
        for pid, xyz in people:
            if len(xyz):
                color = CLASS_COLORS[CLASS_NAMES.index("human")]
                self.rec.log(f"team/people/P{pid}/track", rr.LineStrips3D([xyz], colors=[color], radii=0.02))
                self.rec.log(f"team/people/P{pid}/now", rr.Points3D(xyz[-1:], colors=[color], radii=0.15,
                                                                   labels=[f"P({pid})"]))

    def log_scalar(self, path: str, stamp: float, value: float) -> None:
        """One point of a time series (a plot in the viewer), e.g. the team maps' disagreement φ."""
        self.rec.set_time("sim", duration=float(stamp))
        self.rec.log(path, self.rr.Scalars(float(value)))

    def log_voxels(self, path: str, stamp: float, centers: np.ndarray, labels: np.ndarray) -> None:
        """Occupied cells coloured by class, e.g. a robot's team map (world frame)."""
        self.rec.set_time("sim", duration=float(stamp))
        if len(centers):
            self.rec.log(path, self.rr.Points3D(centers, colors=CLASS_COLORS[labels], radii=0.05))

    def close(self) -> None:
        self.rec.flush()


def make_viz(path: str | Path | None) -> Viz:
    """A RerunViz writing ``path``, or a NullViz when ``path`` is None."""
    return NullViz() if path is None else RerunViz(path)
