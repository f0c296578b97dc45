"""Three identical rooms in a row, on generated floors: an alias that rests on more places than
the truth is refuted by the robots' maps, and the robot aligns to the truth, or stays out of the
team frame when no true closure is left (docs/algorithms/pgo.md, frame decisions).

Each floor comes from the building generator (:func:`kimera_multi_py.sim.generate.generate_building`)
with one row of three identical rooms side by side along the corridor, and distinct rooms across
it. Robot 0 walks from one distinct room through the three twins to the other; robot 1 walks the
same rooms the other way. The closures between them are chosen: in two twin rooms robot 1 is
matched to robot 0 one room further on (the alias, two places), and in the last distinct room
they are matched truly (one place). Closures alone take the alias; shifted by one room, robot 1's
map puts the walls of the distinct rooms it saw into robot 0's free space, and the alias is
refuted. Maps are what each robot could see near its path (the world's true voxel grid).
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from kimera_multi_py.alignment.map_check import FREE, OCCUPIED, CellStates, refined_agreement
from kimera_multi_py.core.geometry import inverse, make_pose
from kimera_multi_py.pgo.agent import PgoAgent
from kimera_multi_py.pgo.local_graph import split_local
from kimera_multi_py.pgo.params import team_params
from kimera_multi_py.sim.generate import generate_building, repeated_layouts
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.simulation import keyframe_poses
from kimera_multi_py.sim.world import World
from tests.consensus.test_alignment_switch import _frame_error, _graph, _odometry, _odometry_start, _run_agents
from tests.consensus.test_pgo_aliased import CLOSURE_SIGMA, _noisy

SEEDS = (1, 2, 3)  # generated floors with a row of three twins and two distinct rooms

pytestmark = pytest.mark.slow  # about 15 s per epoch (the map checks register whole floors)


def _floor(seed: int) -> tuple[ScenarioConfig, list[str], list[str]]:
    """The generated floor, its twin rooms west to east, and its distinct rooms."""
    cfg = generate_building(seed=seed, rooms=5, repeat=3, groups=1, halls=0, corridors=1, robots=2, scatter=False)
    (twins,) = repeated_layouts(cfg).values()
    centre = {s.name: (np.array(s.min) + np.array(s.max)) / 2 for s in cfg.spaces}
    twins = sorted(twins, key=lambda n: float(centre[n][0]))
    distinct = sorted((s.name for s in cfg.spaces if s.layout is not None and s.name not in twins),
                      key=lambda n: float(centre[n][0]))
    return cfg, twins, distinct


def _trajectories(cfg: ScenarioConfig, routes: list[list[str]]) -> list[np.ndarray]:
    world = World(cfg)
    out = []
    for route in routes:
        wp = world.plan_route(route, "route")
        _, poses = keyframe_poses(wp, world.floor_z + cfg.sensor.height, 1.0, np.deg2rad(45.0), 1.0,
                                  np.deg2rad(45.0))
        out.append(poses)
    return out


def _seen(grid_xy: np.ndarray, states: np.ndarray, z: np.ndarray, path: np.ndarray, estimate: np.ndarray,
          radius: float = 2.5) -> CellStates:
    """The known cells within ``radius`` of the true ``path``, where the robot's map holds them:
    each cell moves with its nearest keyframe's ``estimate`` (drift and all), as a submap does."""
    from scipy.spatial import cKDTree

    dist, nearest = cKDTree(path[:, :2, 3]).query(grid_xy)
    keep = (dist < radius)[:, None] & (states != 0)
    ij, k = np.nonzero(keep)
    pts = np.column_stack([grid_xy[ij], z[k]])
    move = estimate @ inverse(path)  # world -> the robot's estimate, per keyframe
    kf = nearest[ij]
    return CellStates(np.einsum("nij,nj->ni", move[kf, :3, :3], pts) + move[kf, :3, 3], states[ij, k])


def _maps(cfg: ScenarioConfig, trajs: list[np.ndarray], estimates: list[np.ndarray]) -> list[CellStates]:
    grid = World(cfg).gt_voxel_grid(0.2)
    c = grid.centers()
    labels = grid.labels.reshape(-1, grid.labels.shape[2])
    states = np.where(labels > 0, OCCUPIED, np.where(labels == 0, FREE, np.int8(0))).astype(np.int8)
    return [_seen(c[:, :, 0, :2].reshape(-1, 2), states, c[0, 0, :, 2], T, E)
            for T, E in zip(trajs, estimates, strict=True)]


def _inside(cfg: ScenarioConfig, T: np.ndarray, space: str) -> np.ndarray:
    (s,) = [s for s in cfg.spaces if s.name == space]
    xy = T[:, :2, 3]
    return np.flatnonzero(np.all((xy > np.array(s.min) + 0.5) & (xy < np.array(s.max) - 0.5), axis=1))


def _closures(cfg: ScenarioConfig, trajs: list[np.ndarray], first: np.ndarray,
              places: list[tuple[str, str]], rng: np.random.Generator, per_place: int
              ) -> list[tuple[int, int, np.ndarray, np.ndarray, bool]]:
    """Closures between robot 0 in the first space and robot 1 in the second of each place, robot 1
    seen as if it stood in robot 0's space (the same space: a true closure; a twin: an alias)."""
    centre = {s.name: (np.array(s.min) + np.array(s.max)) / 2 for s in cfg.spaces}
    out = []
    for s0, s1 in places:
        shift = make_pose(np.eye(3), np.array([*(centre[s0] - centre[s1]), 0.0]))
        for ka, kb in list(zip(_inside(cfg, trajs[0], s0), _inside(cfg, trajs[1], s1), strict=False))[:per_place]:
            Z = inverse(trajs[0][ka]) @ shift @ trajs[1][kb]
            out.append((first[0] + ka, first[1] + kb, _noisy(Z, CLOSURE_SIGMA, rng),
                        np.diag(1.0 / CLOSURE_SIGMA**2), s0 != s1))
    return out


def _decide(seed: int, map_check: bool, with_truth: bool) -> tuple[float, int, dict]:
    """Robot 1's frame error (m) after one epoch, the aliased closures it kept, and its report."""
    cfg, twins, distinct = _floor(seed)
    trajs = _trajectories(cfg, [[distinct[0], *twins, distinct[-1]], [distinct[-1], *twins[::-1], distinct[0]]])
    rng = np.random.default_rng(seed)
    odo, first = _odometry(trajs, rng)
    alias = [(twins[1], twins[0]), (twins[2], twins[1])]  # robot 1 one room west of where robot 0 is
    edges = _closures(cfg, trajs, first, alias, rng, per_place=2)
    if with_truth:
        edges += _closures(cfg, trajs, first, [(distinct[-1], distinct[-1])], rng, per_place=4)
    assert sum(e[4] for e in edges) == 4 and len(edges) == (8 if with_truth else 4)
    start = _odometry_start(trajs, odo)
    graph = _graph(trajs, odo + edges, start)
    params = team_params(max_rounds=300, map_check=map_check)
    agents = [PgoAgent(local, params) for local in split_local(graph, frames="given")]
    maps = _maps(cfg, trajs, [start[graph.robot_indices(r)] for r in range(len(trajs))])
    agents[1].frame.set_map_view(lambda T: refined_agreement(maps[1], maps[0], T))

    poses = asyncio.run(_run_agents(agents, graph))
    # aliased closures either end still weighs (the owner of an edge decides its weight)
    kept_aliases = max(int(np.sum(graph.outlier[a.local.inter_edge] & (a.state.inter_weights > 0.5))) for a in agents)
    return _frame_error(trajs, poses, first), kept_aliases, agents[1].frame.alignment


@pytest.mark.parametrize("seed", SEEDS)
def test_closures_alone_take_the_alias_one_room_off(seed: int) -> None:
    """The rule without the maps (places counted): two aliased places outvote one true place."""
    _, _, report = _decide(seed, map_check=False, with_truth=True)
    verdicts = {e["verdict"]: e for e in report["evidence"]}
    assert report["status"] == "aligned" and verdicts["adopted"]["places"] == 2, report
    assert verdicts["outvoted"]["places"] == 1


@pytest.mark.parametrize("seed", SEEDS)
def test_the_maps_refute_the_alias_and_the_robot_aligns_to_the_truth(seed: int) -> None:
    """Refuted by the maps, the alias's closures stay out at both ends for the whole epoch, even
    where GNC alone would take them back (as many aliased closures as true ones)."""
    error, kept_aliases, report = _decide(seed, map_check=True, with_truth=True)
    assert report["status"] == "aligned" and error < 1.0, (error, report)  # one true place: drift remains
    assert kept_aliases == 0
    assert report["map_refuted"], report
    verdicts = [e["verdict"] for e in report["evidence"]]
    assert verdicts.count("adopted") == 1 and "refuted by the maps" in verdicts


@pytest.mark.parametrize("seed", SEEDS)
def test_with_only_the_alias_left_the_robot_stays_out(seed: int) -> None:
    error, kept_aliases, report = _decide(seed, map_check=True, with_truth=False)
    assert report["status"] == "excluded", report
    assert all(e["verdict"] != "adopted" for e in report["evidence"])
    assert kept_aliases == 0 and error > 2.0  # in its own frame: nothing was adopted
