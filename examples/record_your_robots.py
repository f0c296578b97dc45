"""Record your own robots' keyframes into a folder the agents can replay, then read it back.

Each keyframe is plain numpy: the odometry step ``T_{k-1,k}`` (4x4, identity at k = 0) and one
labelled scan (end points in the sensor frame, a class id per ray, a hit flag). Here the robots
drive straight lines through a box-shaped room and the scan is a ring of rays hitting its walls;
swap in your own arrays. The folder format is described in docs/outputs.md.

    python examples/record_your_robots.py --out runs/my_robots --robots 2 --keyframes 40

Replay one robot of it with ``kimera-multi agent --robot 0 --source runs/my_robots ...``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.io.recording import RecordingWriter, read_ground_truth
from kimera_multi_py.io.sources import RecordedSource

WALL = CLASS_IDS["wall"]
ROOM = np.array([10.0, 6.0, 3.0])  # a closed box from (0, 0, 0) to ROOM


def ring_scan(position: np.ndarray, rays: int, max_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A horizontal ring of rays from ``position`` to the room's walls: (points, labels, hit)."""
    angles = np.linspace(0, 2 * np.pi, rays, endpoint=False)
    d = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(rays)])
    with np.errstate(divide="ignore"):  # distance to the wall each ray meets first
        t = np.min(np.where(d[:, :2] > 0, (ROOM[:2] - position[:2]) / d[:, :2],
                            np.where(d[:, :2] < 0, -position[:2] / d[:, :2], np.inf)), axis=1)
    hit = t <= max_range
    points = d * np.minimum(t, max_range)[:, None]  # sensor frame (the robots never turn here)
    labels = np.where(hit, WALL, 0).astype(np.int16)
    return points, labels, hit


def main(out: Path, robots: int = 2, keyframes: int = 40, step: float = 0.2, rays: int = 720,
         max_range: float = 8.0, seed: int = 0) -> dict[str, object]:
    """Write ``robots`` x ``keyframes`` keyframes to ``out``, read robot 1 back from keyframe 10."""
    rng = np.random.default_rng(seed)
    sensor = {"model": "ring lidar", "max_range": max_range, "keyframe_distance": step,
              "odometry": {"rot_sigma_deg": 0.2, "trans_sigma": 0.01}}
    with RecordingWriter(out, sensor=sensor, truth_info={"site": "example room"}) as rec:
        for robot in range(robots):
            pose = np.eye(4)
            pose[:3, 3] = [1.0, 1.0 + 4.0 * robot / max(robots - 1, 1), 0.5]
            for k in range(keyframes):
                odom = np.eye(4)
                if k:
                    odom[0, 3] = step + rng.normal(0, 0.01)  # measured step, noise included
                    pose = pose.copy()
                    pose[0, 3] += step  # the true motion
                points, labels, hit = ring_scan(pose[:3, 3], rays, max_range)
                rec.add_keyframe(robot, k, stamp=0.5 * k, odometry=odom, points=points, labels=labels,
                                 hit=hit, max_range=max_range, true_pose=pose)  # true_pose: optional

    replay = list(RecordedSource(out, robot=min(1, robots - 1), start=10))  # restart anywhere
    truth = read_ground_truth(out)  # for an evaluator; agents never open it
    return {"folder": str(out), "replayed": len(replay), "first_index": replay[0].index,
            "rays_per_keyframe": len(replay[0].points), "true_poses": {r: len(p) for r, p in truth.poses.items()}}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("runs/my_robots"), help="recording folder to write")
    ap.add_argument("--robots", type=int, default=2)
    ap.add_argument("--keyframes", type=int, default=40, help="keyframes per robot")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    print(main(a.out, a.robots, a.keyframes, seed=a.seed))
