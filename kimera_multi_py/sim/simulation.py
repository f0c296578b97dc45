"""The deterministic multi-robot simulation: robot paths, keyframes, scans, odometry, humans.

Each robot draws its noise from its own generator seeded by ``(seed, robot)``, so a robot's
keyframes do not depend on how many robots run or in which order they are consumed.
Robots know only their own odometry frame (identity at their first keyframe); the true
poses are carried on each :class:`Keyframe` for evaluation only.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.geometry import relative, yaw_pose
from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.sensors import OdometryModel, RangeCategorySensor, Scan, flip_confusion, ray_pattern
from kimera_multi_py.sim.world import DOOR_APPROACH, ELLIPSOID, Primitives, World


@dataclass
class Keyframe:
    """What robot ``robot`` produces at keyframe ``index``; ``true_*`` fields are ground truth."""

    robot: int
    index: int
    stamp: float
    odometry: np.ndarray  # noisy T_{k-1,k} (identity at k = 0)
    scan: Scan
    true_pose: np.ndarray  # T_world_sensor
    true_scan: Scan


@dataclass
class RobotPlan:
    waypoints: np.ndarray  # (w, 2)
    stamps: np.ndarray  # (n,)
    poses: np.ndarray  # (n, 4, 4) true T_world_sensor at keyframes

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.poses[:, :3, 3], axis=0), axis=1).sum())


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def keyframe_poses(waypoints: np.ndarray, z: float, speed: float, turn_rate: float,
                   kf_distance: float, kf_angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe stamps and poses along a polyline: turn in place at corners, then drive straight."""
    seg = np.diff(waypoints, axis=0)
    yaw = float(np.arctan2(seg[0, 1], seg[0, 0]))
    stamps, xs, ys, yaws = [0.0], [waypoints[0, 0]], [waypoints[0, 1]], [yaw]
    t = 0.0
    for a, d in zip(waypoints[:-1], seg, strict=True):
        dyaw = _wrap(float(np.arctan2(d[1], d[0])) - yaw)
        if abs(dyaw) > 1e-9:
            n = int(np.ceil(abs(dyaw) / kf_angle))
            f = np.arange(1, n + 1) / n
            stamps += list(t + f * abs(dyaw) / turn_rate)
            xs += [a[0]] * n
            ys += [a[1]] * n
            yaws += list(yaw + f * dyaw)
            t += abs(dyaw) / turn_rate
            yaw += dyaw
        L = float(np.linalg.norm(d))
        n = int(np.ceil(L / kf_distance))
        f = np.arange(1, n + 1) / n
        stamps += list(t + f * L / speed)
        xs += list(a[0] + f * d[0])
        ys += list(a[1] + f * d[1])
        yaws += [yaw] * n
        t += L / speed
    poses = np.stack([yaw_pose(x, y, z, w) for x, y, w in zip(xs, ys, yaws, strict=True)])
    return np.array(stamps), poses


class Human:
    """A walking person: an upright ellipsoid along its waypoints at ``speed``, standing ``pauses[i]``
    seconds at waypoint ``i``, still at the first one until ``start``; back and forth along the
    path, or round it when ``loop``."""

    def __init__(self, waypoints: np.ndarray, speed: float, radius: float, height: float, floor_z: float,
                 pauses: np.ndarray | None = None, start: float = 0.0, loop: bool = False) -> None:
        self.waypoints = np.asarray(waypoints, dtype=float)
        self.speed, self.radius, self.height, self.floor_z = speed, radius, height, floor_z
        self.start = float(start)
        pause = np.zeros(len(self.waypoints)) if pauses is None else np.asarray(pauses, dtype=float)
        idx = np.arange(len(self.waypoints))
        idx = np.concatenate([idx, [0]]) if loop else np.concatenate([idx, idx[-2::-1]])
        pts, waits = self.waypoints[idx], pause[idx]
        legs = np.linalg.norm(np.diff(pts, axis=0), axis=1) / speed
        # key times: arrive at each waypoint, leave it after its pause
        arrive = np.concatenate([[0.0], np.cumsum(waits[:-1] + legs)])
        self.times = np.stack([arrive, arrive + waits], axis=1).reshape(-1)[:-1]  # the last pause is the first's
        self.points = np.repeat(pts, 2, axis=0)[:-1]
        self.period = float(self.times[-1])

    def position(self, t: float) -> np.ndarray:
        tau = max(float(t) - self.start, 0.0)
        tau = tau % self.period if self.period > 0 else 0.0
        xy = [np.interp(tau, self.times, self.points[:, a]) for a in (0, 1)]
        return np.array([xy[0], xy[1], self.floor_z + self.height / 2])


class Simulation:
    """The world, the team's plans and the sensor models for one scenario and seed."""

    def __init__(self, cfg: ScenarioConfig, seed: int | None = None, world: World | None = None) -> None:
        self.cfg = cfg
        self.seed = cfg.seed if seed is None else int(seed)
        self.world = world or World(cfg)
        s = cfg.sensor
        confusion = np.asarray(s.confusion) if s.confusion is not None else flip_confusion(s.label_flip)
        self.sensor = RangeCategorySensor(ray_pattern(s.model, s.h_fov_deg, s.v_fov_deg, s.rows, s.cols),
                                          s.max_range, s.range_sigma, confusion)
        self.odometry = OdometryModel(np.deg2rad(cfg.odometry.rot_sigma_deg), cfg.odometry.trans_sigma)
        self.humans = [self._human(i) for i in range(len(cfg.humans))]
        self.plans = [self._plan(i) for i in range(len(cfg.robots))]

    def _human(self, i: int) -> Human:
        h = self.cfg.humans[i]
        if h.waypoints is not None:
            wp, fname = np.asarray(h.waypoints, dtype=float), f"humans[{i}].waypoints"
            pauses = np.full(len(wp), h.pause)
        else:
            fname = f"humans[{i}].route"
            wp = self.world.plan_route(list(h.route or []), fname)
            doors = np.array([d.center for d in self.world.doors]).reshape(-1, 2)
            at_door = (np.linalg.norm(wp[:, None] - doors[None], axis=2) <= DOOR_APPROACH + 1e-6).any(axis=1) \
                if len(doors) else np.zeros(len(wp), dtype=bool)
            pauses = np.where(at_door, 0.0, h.pause)
        self.world.check_path(wp, fname)
        return Human(wp, h.speed, h.radius, h.height, self.world.floor_z, pauses, h.start, h.loop)

    @property
    def num_robots(self) -> int:
        return len(self.plans)

    @property
    def num_keyframes(self) -> int:
        return sum(len(p.stamps) for p in self.plans)

    @property
    def duration(self) -> float:
        return float(max(p.stamps[-1] for p in self.plans))

    def _plan(self, i: int) -> RobotPlan:
        rc = self.cfg.robots[i]
        if rc.waypoints is not None:
            wp, fname = np.asarray(rc.waypoints, dtype=float), f"robots[{i}].waypoints"
        else:
            fname = f"robots[{i}].route"
            wp = self.world.plan_route(list(rc.route or []), fname)
        if len(wp) < 2:
            raise ConfigError(fname, "the path has fewer than two distinct points")
        self.world.check_path(wp, fname)
        kf = self.cfg.keyframes
        z = self.world.floor_z + self.cfg.sensor.height
        stamps, poses = keyframe_poses(wp, z, rc.speed, np.deg2rad(rc.turn_rate_deg), kf.distance,
                                       np.deg2rad(kf.angle_deg))
        return RobotPlan(wp, stamps, poses)

    def humans_at(self, t: float) -> Primitives:
        """The walking humans at time ``t`` as dynamic primitives."""
        label = CLASS_IDS["human"]
        return Primitives.build([
            (ELLIPSOID, h.position(t), np.array([h.radius, h.radius, h.height / 2]), 0.0, label, f"human{j}")
            for j, h in enumerate(self.humans)
        ])

    def rng(self, robot: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, robot])

    def keyframes(self, robot: int) -> Iterator[Keyframe]:
        """Robot ``robot``'s keyframes in order."""
        rng = self.rng(robot)
        for k in range(len(self.plans[robot].stamps)):
            yield self.keyframe(robot, k, rng)

    def keyframe(self, robot: int, k: int, rng: np.random.Generator) -> Keyframe:
        """Keyframe ``k`` of ``robot``, drawing its noise from ``rng``: the robot's generator
        (:meth:`rng`) after keyframes ``0..k-1`` were drawn from it."""
        plan = self.plans[robot]
        stamp, pose = plan.stamps[k], plan.poses[k]
        odom = np.eye(4) if k == 0 else self.odometry.measure(relative(plan.poses[k - 1], pose), rng)
        scan, truth = self.sensor.measure(self.world, pose, rng, self.humans_at(float(stamp)))
        return Keyframe(robot, k, float(stamp), odom, scan, pose, truth)

    def stream(self) -> Iterator[Keyframe]:
        """All robots' keyframes merged by time (ties by robot id)."""
        return heapq.merge(*(self.keyframes(r) for r in range(self.num_robots)),
                           key=lambda kf: (kf.stamp, kf.robot))
