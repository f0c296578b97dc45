"""The centralised server decides every robot's frame before GNC, as the agents do.

Robots loop the corridor with the twin rooms of :mod:`tests.consensus.test_pgo_aliased` (see
:mod:`tests.consensus.test_alignment_switch` for the helpers); each robot's odometry starts at
the identity, as the server receives it.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.alignment.server_frames import screen_frames
from kimera_multi_py.comms.messages.closures import KeyframeOdometry, LoopClosures
from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.core.posegraph import robot_key
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.server.node import Server
from tests.consensus.test_alignment_switch import CORNER, _closures, _graph, _odometry_start, _team
from tests.consensus.test_pgo_aliased import ROOM_A, ROOM_B

A, B = np.array([ROOM_A, 0.0]), np.array([ROOM_B, 0.0])
FAR = [np.array([0.0, 8.0]), np.array([4.5, 8.0]), np.array([9.0, 8.0])]


def _team_error(trajs: list[np.ndarray], poses: np.ndarray, first: np.ndarray, robot: int) -> float:
    """Mean position error of ``robot`` in robot 0's frame."""
    end = first[robot] + len(trajs[robot])
    true = (inverse(trajs[0][0]) @ trajs[robot])[:, :3, 3]
    return float(np.linalg.norm(poses[first[robot]:end, :3, 3] - true, axis=1).mean())


def _server(trajs: list[np.ndarray], first: np.ndarray, edges: list, frame_params: PgoParams | None = None) -> Server:
    """A server holding two robots' odometry and robot 0's closures with robot 1 (``edges``)."""
    server = Server(999, (0, 1), closure_sigmas=(0.05, 0.15), odom_sigmas=(0.0026, 0.02), frame_params=frame_params)
    for r, T in enumerate(trajs):
        steps = [np.eye(4)] + [inverse(T[k - 1]) @ T[k] for k in range(1, len(T))]
        server.handle(KeyframeOdometry(robot=r, keyframes=np.arange(len(T)), odometry=np.array(steps)))
    i, j, Z = (np.array(v) for v in zip(*[(e[0], e[1], e[2]) for e in edges], strict=True))
    server.handle(LoopClosures(robot=0, peer=1, batch=0, keys_a=[robot_key(0, int(k)) for k in i],
                               keys_b=[robot_key(1, int(k - first[1])) for k in j], poses=Z,
                               sigmas=np.tile([0.05] * 3 + [0.15] * 3, (len(i), 1)), inliers=np.ones(len(i), int)))
    return server


def test_the_server_decides_with_the_agents_frame_parameters() -> None:
    """The truth on four places, an alias on two: with the defaults robot 1 joins on the truth;
    when the agents ask for five places before a frame is adopted (``align_min_places``), the
    server keeps it out as they would."""
    rng = np.random.default_rng(0)
    trajs, odo, first = _team(rng=rng)
    alias = _closures(trajs, first, [(A, B, True), (np.array([8.0, 8.0]), np.array([14.0, 8.0]), True)], rng)
    true = _closures(trajs, first, [(A, A, False), (CORNER, CORNER, False), (FAR[0], FAR[0], False),
                                    (FAR[2], FAR[2], False)], rng, per_place=2)
    edges = alias + true
    server = _server(trajs, first, edges)
    assert server.optimise()[1].settled and server.frames is not None
    assert server.frames.report[1]["status"] == "aligned"
    strict = _server(trajs, first, edges, PgoParams(align_min_places=5))
    assert not strict.optimise()[1].settled and strict.frames is not None
    assert strict.frames.report[1]["status"] == "excluded"


def test_the_alias_group_is_left_out_and_the_robot_joins_on_the_truth() -> None:
    """Robot 0's room A against robot 1's room B and a far place 6 m on (an alias of two places)
    against four true places: robot 1 joins on the truth, settled, and exactly the aliased
    closures leave the graph GNC sees."""
    rng = np.random.default_rng(0)
    trajs, odo, first = _team(rng=rng)
    alias = _closures(trajs, first, [(A, B, True), (np.array([8.0, 8.0]), np.array([14.0, 8.0]), True)], rng)
    true = _closures(trajs, first, [(A, A, False), (CORNER, CORNER, False), (FAR[0], FAR[0], False),
                                    (FAR[2], FAR[2], False)], rng, per_place=2)
    graph = _graph(trajs, odo + alias + true, _odometry_start(trajs, odo))
    screen = screen_frames(graph)
    assert screen.report[1]["status"] == "aligned" and screen.report[1]["settled"]
    assert screen.report[1]["support"] == 4
    assert np.array_equal(screen.keep, ~graph.outlier)  # odometry and the true closures
    assert _team_error(trajs, screen.poses, first, 1) < 0.5


def test_an_alias_one_corridor_stretch_away_is_left_out_though_it_counts_with_the_truth() -> None:
    """An alias group 2 m from the truth (a repeated corridor stretch) sits within the distance at
    which drift-split groups count as one frame (``SAME_FRAME_M``), so the old screen kept it with
    the truth. It is not at the identity once the robot has joined, so it leaves the graph GNC
    sees (aliased_wing, 5 robots, seed 6: kept, GNC accepted 18 such closures)."""
    rng = np.random.default_rng(3)
    trajs, odo, first = _team(rng=rng)
    # robot 1 seen one stretch (2 m) on
    alias = _closures(trajs, first, [(FAR[1], FAR[1], True)], rng, per_place=3, alias_offset=-2.0)
    true = _closures(trajs, first, [(A, A, False), (CORNER, CORNER, False), (FAR[0], FAR[0], False),
                                    (FAR[2], FAR[2], False)], rng, per_place=2)
    graph = _graph(trajs, odo + alias + true, _odometry_start(trajs, odo))
    assert graph.outlier.sum() == 3
    screen = screen_frames(graph)
    assert screen.report[1]["status"] == "aligned" and screen.report[1]["settled"]
    assert np.array_equal(screen.keep, ~graph.outlier)  # odometry and the true closures
    assert _team_error(trajs, screen.poses, first, 1) < 0.5


def test_a_robot_joins_through_a_settled_robot_before_an_unsettled_one() -> None:
    """Robot 2's only closures with the root are a lone alias group (room A against room B);
    with robot 1, which shares two true places with the root, it shares three true places.
    Robot 1 joins first (a clear lead), then robot 2 on the truth through robot 1; its closures
    with the root are left out."""
    rng = np.random.default_rng(5)
    trajs, odo, first = _team(starts=((0.5, 0.0), (20.5, 0.3), (34.5, -0.3)), rng=rng)
    edges = _closures(trajs, first, [(A, A, False), (CORNER, CORNER, False)], rng, per_place=3)
    edges += _closures(trajs, first, [(A, B, True)], rng, pair=(0, 2), per_place=4)
    edges += _closures(trajs, first, [(c, c, False) for c in FAR], rng, pair=(1, 2), per_place=3)
    graph = _graph(trajs, odo + edges, _odometry_start(trajs, odo))
    screen = screen_frames(graph)
    assert [screen.report[r]["status"] for r in (0, 1, 2)] == ["root", "aligned", "aligned"]
    assert screen.report[2]["peers"] == [1] and screen.report[2]["settled"]
    assert np.array_equal(screen.keep, ~graph.outlier)
    assert _team_error(trajs, screen.poses, first, 2) < 0.5
    # the lone alias decides nothing once robot 1 is not there to settle robot 2's frame
    alone = _graph(trajs, [e for e in odo + edges if not (first[1] <= e[0] < first[2] and e[1] >= first[2])],
                   _odometry_start(trajs, odo))
    lone = screen_frames(alone).report[2]
    assert lone["status"] == "aligned" and not lone["settled"] and lone["support"] == 1


def test_a_tie_keeps_the_robot_out_and_the_server_says_so() -> None:
    """Twin rooms only: the alias and the truth each rest on one place. The server keeps robot 1
    out of the team frame: no closure of it reaches GNC, its poses come back in its own frame
    and the message says they are not settled."""
    rng = np.random.default_rng(2)
    trajs, odo, first = _team(rng=rng)
    edges = _closures(trajs, first, [(A, B, True), (A, A, False)], rng)
    graph = _graph(trajs, odo + edges, _odometry_start(trajs, odo))
    assert screen_frames(graph).report[1]["status"] == "excluded"
    server = _server(trajs, first, edges)
    out = server.optimise()  # one message per robot, by id
    assert not out[1].settled and out[0].settled
    assert np.allclose(out[1].poses[0], np.eye(4), atol=1e-6)  # its own frame
    assert server.stats.weights and all(w == 0.0 for w in server.stats.weights.values())
