"""The deterministic multi-robot simulator (world, sensors, scenarios, keyframe source).

Typical use::

    from kimera_multi_py.sim import load_scenario, Simulation

    cfg = load_scenario("sims/office.toml", robots=3)      # ConfigError names bad fields
    sim = Simulation(cfg, seed=0)                            # plans paths, checks walls
    for kf in sim.stream():                                  # all robots, merged by time
        kf.robot, kf.index, kf.stamp                         # who and when
        kf.odometry                                          # noisy T_{k-1,k} (4x4)
        kf.scan.directions, kf.scan.ranges, kf.scan.labels   # sensor frame; inf / 0 on misses
        kf.scan.points()                                     # (n, 3) end points, misses at max_range
        kf.true_pose, kf.true_scan                           # ground truth, for evaluation only

    sim.world.gt_voxel_grid(0.1)   # VoxelGrid: labels -1 unknown / 0 free / class id
    sim.world.objects              # [GroundTruthObject(id, cls, centroid, size, yaw, ...)]
    sim.world.raycast(origin, dirs, max_range)   # vectorised (ranges, labels)
    sim.humans_at(t)               # walking humans (class ``human``) as dynamic primitives

Class ids and names are in :mod:`kimera_multi_py.core.semantics`.
"""

from kimera_multi_py.sim.scenario import ScenarioConfig, load_scenario
from kimera_multi_py.sim.sensors import RangeCategorySensor, Scan
from kimera_multi_py.sim.simulation import Keyframe, Simulation
from kimera_multi_py.sim.world import GroundTruthObject, VoxelGrid, World

__all__ = [
    "GroundTruthObject", "Keyframe", "RangeCategorySensor", "Scan", "ScenarioConfig", "Simulation",
    "VoxelGrid", "World", "load_scenario",
]
