"""The safety net on real maps: two robots map the simulator's twin rooms (``sims/tiny.toml``) from
their true poses; robot 1's submaps are then moved one room over while it still claims the team
frame. Its map contradicts the root's there, so :func:`frame_check` refutes the frame; when it
leaves (its pose table names its own frame), its evidence leaves the root's team map exactly."""

from __future__ import annotations

import itertools

import numpy as np

from kimera_multi_py.alignment.map_check import cell_states
from kimera_multi_py.core.geometry import inverse, make_pose
from kimera_multi_py.mapping import SubmapMap
from kimera_multi_py.mapshare.agreement import frame_check, source_states
from kimera_multi_py.mapshare.consensus import MapConsensus, MapConsensusParams
from kimera_multi_py.mapshare.exchange import MapExchange
from kimera_multi_py.mapshare.fusion import centralised_team_map, octree_cells
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.sim import Simulation, load_scenario
from tests.sim.helpers import TINY

P = PgoParams()
LIMITS = (P.map_min_conflicts, P.map_conflict_ratio)
ROOM = 4.0  # the twin rooms' pitch in sims/tiny.toml


def _maps(keyframes: int = 60, per_submap: int = 10) -> dict[int, SubmapMap]:
    cfg = load_scenario(TINY)
    sim = Simulation(cfg, 0)
    maps = {}
    for r in range(2):
        m = SubmapMap(0.1, 20)
        for k, kf in enumerate(itertools.islice(sim.keyframes(r), keyframes)):
            sid = k // per_submap
            if sid not in m.submaps:
                m.new_submap(sid, kf.true_pose)
            m.integrate(sid, inverse(m.submaps[sid].T) @ kf.true_pose, kf.scan.points(), kf.scan.labels,
                        kf.scan.max_range)
        maps[r] = m
    return maps


def _exchanged(maps: dict[int, SubmapMap]) -> tuple[dict[int, MapConsensus], MapExchange]:
    """Both robots' map consensus in the team frame, after a few exchange rounds."""
    nodes = {r: MapConsensus(r, maps[r], MapConsensusParams(mode="exact"), team_size=2) for r in maps}
    for node in nodes.values():
        node.set_frame(0)
    net = MapExchange(nodes)
    for k in range(4):
        net.round(float(k))
    return nodes, net


def test_a_robot_one_room_off_is_refuted_and_its_evidence_leaves_the_team_map() -> None:
    maps = _maps()
    nodes, net = _exchanged(maps)
    truth = frame_check(nodes[1], maps[1], 0, *LIMITS)
    assert truth is not None and not truth.refuted and truth.conflicting == [], truth.as_dict()
    # robot 1 moved into the frame one room over, still claiming the team frame
    shift = make_pose(np.eye(3), np.array([ROOM, 0.0, 0.0]))
    for sid, s in maps[1].submaps.items():
        maps[1].move_submap(sid, shift @ s.T, force=True)
    for k in range(4, 8):
        net.round(float(k))
    off = frame_check(nodes[1], maps[1], 0, *LIMITS)
    assert off is not None and off.refuted and off.conflicting == [0], off.as_dict()
    # it leaves: its evidence leaves the root's team map, exactly
    nodes[1].set_frame(1)
    for k in range(8, 12):
        net.round(float(k))
    alone = octree_cells(centralised_team_map({0: maps[0]}))
    codes, rows = nodes[0].team_cells()
    assert np.array_equal(codes, alone[0]) and np.array_equal(rows, alone[1])


def test_source_states_place_a_robots_held_evidence_at_any_keyframe_poses() -> None:
    """The server's view of a robot's map (:func:`source_states`): at the poses its table holds it
    is the evidence as held; at poses one room over, the same cells one room over."""
    maps = _maps()
    nodes, net = _exchanged(maps)
    per = 10
    poses = np.tile(np.eye(4), (60, 1, 1))
    for sid, s in maps[1].submaps.items():
        poses[sid * per] = s.T
    held = source_states(nodes[0], 1, poses, per)
    codes, rows = nodes[0].frame_cells(0, [1])
    expected = cell_states(codes, rows, maps[1].resolution)
    assert held is not None and np.allclose(held.centres, expected.centres) and np.array_equal(held.state,
                                                                                               expected.state)
    shift = make_pose(np.eye(3), np.array([ROOM, 0.0, 0.0]))
    moved = source_states(nodes[0], 1, shift @ poses, per)
    assert moved is not None

    def by_place(c: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        order = np.lexsort(np.round(c, 3).T)
        return c[order], state[order]

    (a, sa), (b, sb) = by_place(moved.centres, moved.state), by_place(held.centres + [ROOM, 0.0, 0.0], held.state)
    assert np.allclose(a, b, atol=1e-6) and np.array_equal(sa, sb)
    assert source_states(nodes[0], 5, poses, per) is None  # nothing held of robot 5
