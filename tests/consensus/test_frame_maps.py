"""Frame decisions against the maps: an alias that rests on more places than the truth is refuted
by the robots' occupancy maps, and the robot aligns to the truth, or stays out of the team frame;
the centralised server's frame screen decides alike.

Two robots loop a corridor ring with two identical rooms 6 m apart (:mod:`.test_alignment_switch`).
Robot 0's room A matches robot 1's room B, and two corridor places match the places 6 m further
on: the frame shifted by 6 m rests on three places, the truth (the corner only) on one. The
closures alone take the alias. The maps do not: shifted 6 m, robot 1's map puts the ring's walls
into robot 0's corridors (maps from :mod:`tests.alignment.world`, what each robot saw near its
path, in its own frame).
"""

from __future__ import annotations

import asyncio

import numpy as np

from kimera_multi_py.alignment.map_check import CellStates, MapAgreement, refined_agreement
from kimera_multi_py.alignment.server_frames import MapRule, screen_frames
from kimera_multi_py.core.geometry import inverse, transform_points
from kimera_multi_py.pgo.agent import PgoAgent
from kimera_multi_py.pgo.local_graph import split_local
from kimera_multi_py.pgo.params import team_params
from tests.alignment.world import Floor, seen
from tests.consensus.test_alignment_switch import (
    CORNER,
    _closures,
    _frame_error,
    _graph,
    _odometry_start,
    _run_agents,
    _team,
)
from tests.consensus.test_pgo_aliased import OFFSET, ROOM_A, ROOM_B

# the ring's corridors (2 m wide around its sides) and the twin rooms south of its first side
RING_FLOOR = Floor(spaces=[(-1.0, -1.0, 17.0, 1.0), (15.0, -1.0, 17.0, 9.0), (-1.0, 7.0, 17.0, 9.0),
                           (-1.0, -1.0, 1.0, 9.0), (ROOM_A - 1.5, -4.0, ROOM_A + 1.5, -1.1),
                           (ROOM_B - 1.5, -4.0, ROOM_B + 1.5, -1.1), (ROOM_A - 0.5, -1.2, ROOM_A + 0.5, -0.9),
                           (ROOM_B - 0.5, -1.2, ROOM_B + 0.5, -0.9)],
                   boxes=[(ROOM_A - 1.2, -3.6, ROOM_A, -3.0), (ROOM_B - 1.2, -3.6, ROOM_B, -3.0)])


def _run(edges_at: list, map_check: bool, seed: int = 3, alias_per_place: int = 2,
         true_per_place: int = 4, blind_to_alias: bool = False, **params: object) -> tuple[float, dict]:
    """Robot 1's error and report; ``blind_to_alias``: the maps judge only frames near the truth
    (as where they do not overlap under the alias)."""
    trajs, odo, first = _team()
    rng = np.random.default_rng(seed)
    edges = _closures(trajs, first, [p for p in edges_at if p[2]], rng, per_place=alias_per_place)
    edges += _closures(trajs, first, [p for p in edges_at if not p[2]], rng, per_place=true_per_place)
    graph = _graph(trajs, odo + edges, _odometry_start(trajs, odo))
    agents = [PgoAgent(local, team_params(max_rounds=300, map_check=map_check, **params))
              for local in split_local(graph, frames="given")]
    maps = [seen(RING_FLOOR, T[:, :2, 3], T_world_own=T[0]) for T in trajs]
    truth = inverse(trajs[0][0]) @ trajs[1][0]  # robot 1's frame in robot 0's

    def view(T: np.ndarray) -> MapAgreement | None:
        if blind_to_alias and np.linalg.norm(T[:3, 3] - truth[:3, 3]) > 2.0:
            return None
        return refined_agreement(maps[1], maps[0], T)

    agents[1].frame.set_map_view(view)

    poses = asyncio.run(_run_agents(agents, graph))
    return _frame_error(trajs, poses, first), agents[1].frame.alignment


ALIAS_PLACES = [(np.array([ROOM_A, 0.0]), np.array([ROOM_B, 0.0]), True),
                (np.array([2.0, 8.0]), np.array([8.0, 8.0]), True),
                (np.array([6.0, 8.0]), np.array([12.0, 8.0]), True)]


def test_an_alias_on_more_places_than_the_truth_is_refuted_and_the_robot_aligns_to_the_truth() -> None:
    places = [*ALIAS_PLACES, (CORNER, CORNER, False)]  # alias: 3 places, 1 edge each; truth: 1 place, 4 edges
    error, report = _run(places, map_check=False, alias_per_place=1)
    assert abs(error - OFFSET) < 1.5, report  # the closures alone take the alias
    error, report = _run(places, map_check=True, alias_per_place=1)
    assert report["status"] == "aligned" and error < 1.0, report
    assert report["map_refuted"] and all(r["conflicts"] >= 20 for r in report["map_refuted"])
    assert report["map"]["conflicts"] < 20
    # the report gives every hypothesis weighed, with its evidence and verdict
    verdicts = {e["verdict"]: e for e in report["evidence"]}
    assert verdicts["adopted"]["map"]["conflicts"] < 20
    assert verdicts["refuted by the maps"]["map"]["conflicts"] >= 20


def test_without_true_closures_the_refuted_alias_keeps_the_robot_out() -> None:
    error, report = _run(ALIAS_PLACES, map_check=True)
    assert report["status"] == "excluded", report
    assert report["map_refuted"]
    assert all(e["verdict"] != "adopted" for e in report["evidence"])
    assert error > 1.0  # in its own frame, not the alias's: nothing was adopted


TRUE_PLACES = [(np.array([ROOM_A, 0.0]),) * 2 + (False,), (CORNER, CORNER, False),
               (np.array([4.0, 8.0]),) * 2 + (False,), (np.array([0.0, 8.0]),) * 2 + (False,)]


def test_a_lead_in_places_adopts_a_frame_only_once_the_maps_refute_every_rival() -> None:
    """The truth rests on four places, the alias one room over on two: a clear lead in places.
    While the maps cannot judge the alias, it stands as a rival and robot 1 stays out of the team
    frame, saying why; once the maps refute it, robot 1 aligns to the truth. The lead alone
    (``align_rivals="lead"``) aligns it without the maps' word."""
    places = [*ALIAS_PLACES[:2], *TRUE_PLACES]
    error, report = _run(places, map_check=True, alias_per_place=3, true_per_place=2, blind_to_alias=True)
    assert report["status"] == "excluded" and "rival" in report["reason"], report
    assert report["support"] >= 4 and not report.get("map_refuted")
    assert error > 1.0  # its own frame: nothing was adopted
    error, report = _run(places, map_check=True, alias_per_place=3, true_per_place=2)
    assert report["status"] == "aligned" and error < 1.0, report
    assert report["map_refuted"] and report["hypotheses"] == 1
    error, report = _run(places, map_check=True, alias_per_place=3, true_per_place=2, blind_to_alias=True,
                         align_rivals="lead")
    assert report["status"] == "aligned" and error < 1.0, report
    assert report["hypotheses"] == 2 and not report.get("map_refuted")
    # a rival on one place is what one twin room looks like: the four places refute it already
    error, report = _run([ALIAS_PLACES[0], *TRUE_PLACES], map_check=True, alias_per_place=3, true_per_place=2,
                         blind_to_alias=True)
    assert report["status"] == "aligned" and error < 1.0, report


def _server_maps(trajs: list[np.ndarray]) -> MapRule:
    """The server's view of the robots' maps: what each saw near its path, in its own frame (first
    pose at the identity, as its odometry starts), placed where the screen puts its first pose."""
    own = [seen(RING_FLOOR, T[:, :2, 3], T_world_own=T[0]) for T in trajs]

    def cells(robot: int, poses: np.ndarray) -> CellStates:
        c = own[robot]
        return CellStates(transform_points(poses[0], c.centres), c.state)

    return MapRule(cells)


def test_the_servers_frame_screen_faces_the_maps_as_the_agents_do() -> None:
    """The server's screen on the same evidence: the closures alone put robot 1 in the alias (three
    places against the truth's one); facing the maps, the alias is refuted and listed, and robot 1
    joins on the truth."""
    rng = np.random.default_rng(3)
    trajs, odo, first = _team()
    edges = _closures(trajs, first, ALIAS_PLACES, rng, per_place=1)
    edges += _closures(trajs, first, [(CORNER, CORNER, False)], rng, per_place=4)
    graph = _graph(trajs, odo + edges, _odometry_start(trajs, odo))
    blind = screen_frames(graph)
    assert blind.report[1]["status"] == "aligned" and abs(_frame_error(trajs, blind.poses, first) - OFFSET) < 1.5
    screen = screen_frames(graph, maps=_server_maps(trajs))
    assert screen.report[1]["status"] == "aligned", screen.report[1]
    assert _frame_error(trajs, screen.poses, first) < 1.0
    assert screen.report[1]["map_refuted"] and all(r["conflicts"] >= 20 for r in screen.report[1]["map_refuted"])
    assert not np.any(screen.keep & graph.outlier)  # no aliased closure reaches GNC
    verdicts = [e["verdict"] for e in screen.report[1]["evidence"]]
    assert verdicts.count("adopted") == 1 and "refuted by the maps" in verdicts


def test_the_servers_frame_screen_also_waits_while_a_rival_stands() -> None:
    """The server's screen on a lead in places (the truth on four places, the alias on two) with no
    map of robot 1 to judge either frame: robot 1 stays out, the rival named as the reason; with
    ``every_rival=False`` the lead decides and robot 1 joins on the truth."""
    rng = np.random.default_rng(3)
    trajs, odo, first = _team()
    edges = _closures(trajs, first, ALIAS_PLACES[:2], rng, per_place=3)
    edges += _closures(trajs, first, TRUE_PLACES, rng, per_place=2)
    graph = _graph(trajs, odo + edges, _odometry_start(trajs, odo))
    seen_by = _server_maps(trajs).cells

    def cells(robot: int, poses: np.ndarray) -> CellStates | None:
        return None if robot == 1 else seen_by(robot, poses)

    screen = screen_frames(graph, maps=MapRule(cells))
    assert screen.report[1]["status"] == "excluded" and "rival" in str(screen.report[1]["reason"]), screen.report[1]
    lead = screen_frames(graph, maps=MapRule(cells, every_rival=False))
    assert lead.report[1]["status"] == "aligned" and _frame_error(trajs, lead.poses, first) < 1.0
