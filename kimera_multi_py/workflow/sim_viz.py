"""What the simulation shows of the team in Rerun: its estimate, closures, maps, objects and people."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.mapping.object_fusion import team_id
from kimera_multi_py.viz.rerun_viz import Viz


def log_team(viz: Viz, agents: Sequence[Agent], T: np.ndarray, stamp: float) -> None:
    """Send the team's current estimate to the visualiser, placed in the world by ``T`` (the true
    start of robot 0: the team frame is robot 0's odometry frame)."""
    trajs = [transform_points(T, np.array(a.poses)[:, :3, 3]) if a.poses else np.zeros((0, 3))
             for a in agents]
    closures = []
    for a in agents:
        for peer, group in a.closures.items():
            for c in group:
                if c.own_kf < len(a.poses) and c.peer_kf < len(agents[peer].poses):
                    closures.append((transform_points(T, a.poses[c.own_kf][None, :3, 3])[0],
                                     transform_points(T, agents[peer].poses[c.peer_kf][None, :3, 3])[0],
                                     c.accepted))
    voxels = []
    for a in agents:
        lv, occ = a.map.octree.leaves(), a.map.octree.occupied_leaves()
        voxels.append((transform_points(T, lv.centers[occ]), np.argmax(lv.logodds[occ], axis=1)))
    lms = [lm for a in agents for lm in a.objects.confirmed()]
    objects = (transform_points(T, np.array([lm.position for lm in lms]).reshape(-1, 3)),
               np.array([lm.box()[1] for lm in lms]).reshape(-1, 3), np.array([lm.label for lm in lms], dtype=int))
    viz.log_team(stamp, trajs, closures, voxels, objects)
    # every robot's confirmed people tracks, with their team ids (docs/algorithms/people.md)
    viz.log_people(stamp, [(team_id(a.robot, t.id), transform_points(T, a.people.positions(t)))
                           for a in agents for t in a.people.confirmed()])
