"""Map consensus: exact equals the centralised fusion bit for bit; ROAM double counts; laplacian converges."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.comms.comm_range import neighbours_within
from kimera_multi_py.comms.messages.maps import SubmapEvidence, SubmapPoses
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp, transform_points
from kimera_multi_py.eval.map_metrics import agreement, occupancy_logodds, phi
from kimera_multi_py.mapping import SemanticOctree, SubmapMap
from kimera_multi_py.mapping.observation import SCALE
from kimera_multi_py.mapshare.consensus import MapConsensus, MapConsensusParams
from kimera_multi_py.mapshare.exchange import MapExchange, full_links
from kimera_multi_py.mapshare.fusion import centralised_team_map, octree_cells
from kimera_multi_py.mapshare.wire import pack_cells, unpack_cells

from ..mapping.helpers import K, room_scan

RES = 0.1


def add_scan(m: SubmapMap, sid: int, origin: np.ndarray, seed: int, rays: int = 300) -> None:
    T = m.submaps[sid].T
    T_w_sensor = make_pose(so3_exp([0.0, 0.0, 0.3 * seed]), origin)
    p, lab = room_scan(origin, rays, seed=seed, noise=0.1)
    m.integrate(sid, inverse(T) @ T_w_sensor, transform_points(inverse(T_w_sensor), p), lab)


def robot_map(r: int, submaps: int = 2) -> SubmapMap:
    """Robot ``r``'s map of the test room: a few submaps of one scan each (hand-made evidence)."""
    m = SubmapMap(RES, K)
    for s in range(submaps):
        m.new_submap(s, make_pose(so3_exp([0.0, 0.0, 0.2 * r + 0.1 * s]), [0.4 * r - 1.0, 0.3 * s - 0.5, 0.0]))
        add_scan(m, s, np.array([0.6 * r - 1.2, 0.5 * s - 0.6, 1.0 + 0.1 * s]), seed=10 * r + s)
    return m


def team(n: int, mode: str = "exact", **params: float) -> tuple[dict[int, SubmapMap], dict[int, MapConsensus]]:
    """``n`` robots; the growing submap gets a version every period unless ``hold`` is given."""
    params = {"hold": 0.0, **params}
    maps = {r: robot_map(r) for r in range(n)}
    nodes = {r: MapConsensus(r, maps[r], MapConsensusParams(mode=mode, **params), team_size=n) for r in maps}
    for node in nodes.values():
        node.set_frame(0)
    return maps, nodes


def snapshot(tree: SemanticOctree) -> tuple[np.ndarray, ...]:
    return tree.codes.copy(), tree.levels.copy(), tree.values.copy()


def same(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def run(net: MapExchange, t0: float, rounds: int) -> float:
    for k in range(rounds):
        net.round(t0 + k)
    return t0 + rounds


def assert_exact(maps: dict[int, SubmapMap], nodes: dict[int, MapConsensus]) -> None:
    ref = centralised_team_map(maps)
    ref_cells = octree_cells(ref)
    for r, node in nodes.items():
        assert same(snapshot(node.team_map), snapshot(ref)), f"robot {r}'s team map differs"
        codes, rows = node.team_cells()
        assert np.array_equal(codes, ref_cells[0]) and np.array_equal(rows, ref_cells[1])
        assert agreement(node.team_cells(), ref_cells)["identical"] == 1.0


def test_exact_equals_the_centralised_fusion_bit_for_bit() -> None:
    maps, nodes = team(3)
    run(MapExchange(nodes), 0.0, 4)
    assert_exact(maps, nodes)
    ref = centralised_team_map(maps)
    assert len(ref) > max(len(m.octree) for m in maps.values())  # the team sees more than anyone
    # the team map is not any one robot's map, and not a sum of clamped maps
    assert not same(snapshot(ref), snapshot(maps[0].octree))


def test_exact_follows_new_scans_and_moved_submaps_with_poses_only() -> None:
    maps, nodes = team(3)
    net = MapExchange(nodes)
    t = run(net, 0.0, 4)
    add_scan(maps[1], 1, np.array([0.5, 0.2, 1.1]), seed=77)  # a new version of a submap
    t = run(net, t, 3)
    assert_exact(maps, nodes)
    before = net.total_bytes()
    evidence_before = sum(c[SubmapEvidence.TOPIC] for c in net.bytes.values())
    assert maps[2].move_submap(0, make_pose(so3_exp([0.0, 0.0, 0.15]), [0.35, -0.2, 0.05]) @ maps[2].submaps[0].T)
    run(net, t, 3)
    assert_exact(maps, nodes)
    assert sum(c[SubmapEvidence.TOPIC] for c in net.bytes.values()) == evidence_before  # only poses travelled
    assert net.total_bytes() > before


def test_exact_survives_duplicated_reordered_and_dropped_messages() -> None:
    maps, nodes = team(3)
    net = MapExchange(nodes, drop=0.2, duplicate=0.2, reorder=True, seed=3)
    t = run(net, 0.0, 3)
    for k in range(4):  # evidence keeps arriving while messages are lost
        add_scan(maps[k % 3], 0, np.array([0.3 * k - 0.5, 0.1, 1.2]), seed=100 + k)
        t = run(net, t, 2)
    maps[0].move_submap(1, make_pose(None, [0.0, 0.4, 0.0]) @ maps[0].submaps[1].T)
    run(net, t, 40)
    assert net.dropped > 0
    assert sum(n.ignored["evidence_duplicate"] for n in nodes.values()) > 0
    assert_exact(maps, nodes)


def test_exact_recovers_after_a_partition_heals() -> None:
    maps, nodes = team(3)
    split = {0: {1}, 1: {0}, 2: set()}
    net = MapExchange(nodes, links=lambda now: split if now < 10 else full_links([0, 1, 2]))
    t = run(net, 0.0, 5)
    add_scan(maps[2], 0, np.array([0.2, -0.3, 1.0]), seed=55)
    add_scan(maps[0], 1, np.array([-0.4, 0.6, 1.3]), seed=56)
    t = run(net, t, 4)
    assert not same(snapshot(nodes[2].team_map), snapshot(centralised_team_map(maps)))
    run(net, max(t, 10.0), 12)
    assert_exact(maps, nodes)


def test_exact_reaches_robots_that_are_never_neighbours() -> None:
    maps, nodes = team(4)
    line = {0: {1}, 1: {0, 2}, 2: {1, 3}, 3: {2}}
    net = MapExchange(nodes, links=line)
    run(net, 0.0, 12)
    assert_exact(maps, nodes)
    assert nodes[0].held.keys() >= {(3, 0), (3, 1)}  # robot 3's evidence came over two relays


def test_a_peer_is_applied_only_once_aligned_and_kept_until_then() -> None:
    maps, nodes = team(2)
    nodes[1].set_frame(1)  # robot 1 is not aligned yet
    net = MapExchange(nodes)
    t = run(net, 0.0, 4)
    assert (1, 0) in nodes[0].held  # kept ...
    assert same(snapshot(nodes[0].team_map), snapshot(centralised_team_map(maps, robots=[0])))  # ... not applied
    nodes[1].set_frame(0)
    run(net, t, 3)
    assert_exact(maps, nodes)


def test_messages_from_non_neighbours_and_bad_content_are_refused() -> None:
    maps, nodes = team(2)
    node = nodes[0]
    node.set_neighbours({1})
    cells = pack_cells(np.array([3, 9], np.int64), np.ones((2, K), np.int16))
    bad = SubmapEvidence(robot=1, source=1, submap=0, base=2, version=2, cells=2, classes=K, payload=cells)
    with pytest.raises(MessageError, match="base"):
        node.handle(bad)
    wrong_k = SubmapEvidence(robot=1, source=1, submap=0, base=0, version=1, cells=2, classes=K - 1, payload=cells)
    with pytest.raises(MessageError, match="classes"):
        node.handle(wrong_k)
    huge = SubmapEvidence(robot=1, source=1, submap=0, base=0, version=2**40, cells=2, classes=K, payload=cells)
    with pytest.raises(MessageError, match="out of range"):
        node.handle(huge)
    short = SubmapEvidence(robot=1, source=1, submap=0, base=0, version=1, cells=3, classes=K, payload=cells)
    with pytest.raises(MessageError, match="payload"):
        node.handle(short)
    garbage = SubmapEvidence(robot=1, source=1, submap=0, base=0, version=1, cells=2, classes=K,
                             payload=np.arange(40, dtype=np.uint8))
    with pytest.raises(MessageError, match="payload"):
        node.handle(garbage)
    unsorted = pack_cells(np.array([3, 9], np.int64), np.ones((2, K), np.int16))
    assert unpack_cells(unsorted, 2, K, "x")[0].tolist() == [3, 9]
    stranger = SubmapPoses(robot=5, source=5, version=1, frame=0, submaps=np.zeros(1, np.int64),
                           T_ref=np.eye(4)[None], T=np.eye(4)[None])
    node.handle(stranger)
    assert node.ignored["not_neighbour"] == 1 and 5 not in node.poses


def test_roam_reproduces_double_counting_up_to_the_clamp() -> None:
    maps = {0: robot_map(0, submaps=1), 1: SubmapMap(RES, K)}
    params = MapConsensusParams(mode="roam", period=1.0, roam_period=1.0)
    nodes = {r: MapConsensus(r, maps[r], params) for r in maps}
    for n in nodes.values():
        n.set_frame(0)
    net = MapExchange(nodes)
    codes, rows = octree_cells(maps[0].octree)
    occ = np.flatnonzero(occupancy_logodds(rows.astype(np.float64) / SCALE) > 0)
    probe = codes[occ[:1]]
    history = []
    for k in range(40):
        net.round(float(k))
        history.append(int(nodes[0].team_map.cell_values(probe)[0][0].max()))
    hi = nodes[0].team_map.model.hi
    first = history.index(hi)
    assert first > 3
    assert all(b > a for a, b in zip(history[1:first], history[2:first + 1], strict=True))  # grows every exchange
    assert history[-1] == hi  # ... until the clamp
    single = int(maps[0].octree.cell_values(probe)[0][0].max())
    assert single < hi  # the evidence itself was weak: the agreement is by saturation
    assert nodes[0].roam_bytes > 0 and nodes[0].roam_bytes % 36 == 0


def test_roam_fuses_at_most_one_peer_per_period() -> None:
    maps, nodes = team(3, mode="roam", roam_period=5.0)
    net = MapExchange(nodes)
    run(net, 0.0, 5)
    assert all(n.roam.fused == 1 for n in nodes.values() if n.roam is not None)
    assert all(n.ignored["roam_dropped"] == 1 for n in nodes.values())


def test_laplacian_phi_falls_monotonically_on_a_static_map() -> None:
    maps, nodes = team(4, mode="laplacian")
    line = {0: {1}, 1: {0, 2}, 2: {1, 3}, 3: {2}}
    net = MapExchange(nodes, links=line)
    pairs = [(0, 1), (1, 2), (2, 3)]
    prior = maps[0].octree.model.prior_row
    values = []
    for k in range(25):
        net.round(float(k))
        values.append(phi({r: n.team_cells() for r, n in nodes.items()}, pairs, prior)["phi"])
    assert values[-1] < 1e-3 * values[1]
    assert all(b <= a * (1 + 1e-9) for a, b in zip(values[1:], values[2:], strict=False))
    ref = octree_cells(centralised_team_map(maps))
    assert min(agreement(n.team_cells(), ref)["label"] for n in nodes.values()) > 0.99


def test_neighbours_within_comm_range() -> None:
    pos = {0: np.zeros(3), 1: np.array([6.0, 0, 0]), 2: make_pose(None, [12.0, 0, 0])}
    assert neighbours_within(pos, 10.0) == {0: {1}, 1: {0, 2}, 2: {1}}
    assert neighbours_within(pos, None) == {0: {1, 2}, 1: {0, 2}, 2: {0, 1}}
    with pytest.raises(ValueError, match="comm_range"):
        neighbours_within(pos, -1.0)


def test_a_server_without_a_map_fuses_centrally_and_serves_the_team_map_back() -> None:
    maps, nodes = team(3)
    server = MapConsensus(9, SubmapMap(RES, K), team_size=3)
    server.set_frame(0)
    star = {9: {0, 1, 2}, 0: {9}, 1: {9}, 2: {9}}
    run(MapExchange({**nodes, 9: server}, links=star), 0.0, 8)
    assert same(snapshot(server.team_map), snapshot(centralised_team_map(maps)))
    assert_exact(maps, nodes)


def test_a_delta_on_top_of_a_lost_one_waits_until_the_lost_cells_are_resent() -> None:
    maps, nodes = team(2)
    a, b = nodes[0], nodes[1]
    for n in nodes.values():
        n.set_neighbours({0, 1})

    def deliver(out, drop_evidence=False):
        for m in out:
            if not (drop_evidence and isinstance(m, SubmapEvidence)):
                b.handle(m)

    b.step(0.0)
    deliver(a.step(0.0))
    for n in nodes.values():  # summaries after round 0
        for m in n.step(1.0):
            (b if n is a else a).handle(m)
    add_scan(maps[0], 1, np.array([0.3, 0.4, 1.2]), seed=91)
    deliver(a.step(2.0), drop_evidence=True)  # version 2 of submap 1 is lost
    add_scan(maps[0], 1, np.array([-0.3, 0.1, 1.1]), seed=92)
    deliver(a.step(3.0))  # version 3 sent on top of version 2, which b does not have
    run(MapExchange(nodes), 4.0, 6)
    assert_exact(maps, nodes)
    assert b.ignored["evidence_gap"] == 1


def test_gaps_say_what_stands_between_a_robot_and_a_whole_team_map() -> None:
    """``MapConsensus.gaps``: what an agent checks before it exits (team/process.py). Empty
    exactly when every robot's summary matches what the robot holds."""
    maps, nodes = team(3)
    assert nodes[0].gaps({0, 1, 2}) == {1: {"summary": "none received"}, 2: {"summary": "none received"}}
    split = {0: {1}, 1: {0}, 2: set()}
    net = MapExchange(nodes, links=lambda now: split if now < 10 else full_links([0, 1, 2]))
    t = run(net, 0.0, 5)
    assert nodes[0].gaps({1}) == {}  # robots 0 and 1 hold the same, robot 2 is cut off
    assert nodes[0].gaps({2}) == {2: {"summary": "none received"}}
    add_scan(maps[1], 0, np.array([0.2, -0.3, 1.0]), seed=57)  # robot 1's submap 0 changes
    nodes[1].step(t)  # robot 1 takes it in (what it sends is lost): ahead of robot 0's summary
    assert nodes[1].gaps({0}) == {0: {"submaps_ahead": [[1, 0]]}}
    assert nodes[0].gaps({1}) == {}  # robot 0 cannot know yet: robot 1's last summary is older
    run(net, max(t + 1, 10.0), 12)  # healed; the periodic summaries recover the lost messages
    assert all(node.gaps({0, 1, 2}) == {} for node in nodes.values())
    assert_exact(maps, nodes)
    nodes[2].set_frame(2)  # a robot in another frame holds other maps, whatever its versions
    nodes[2].step(100.0)
    nodes[0]._on_versions(nodes[2]._versions())
    assert nodes[0].gaps({2})[2]["frame"] == {"mine": 0, "theirs": 2}


def test_a_restarted_robot_continues_its_pose_table_versions_above_what_its_neighbours_hold() -> None:
    """The map consensus is not checkpointed: a robot that restarts counts its pose table's
    versions from 0 again, while its neighbours hold its old table at higher versions and would
    ignore the new ones as duplicates (a killed and resumed agent's PGO moves then never reached
    the team's maps). Hearing their summaries, it continues above them, and the maps end exact."""
    maps, nodes = team(2)
    net = MapExchange(nodes, links=lambda now: full_links([0, 1]))
    t = run(net, 0.0, 3)
    for k in range(4):  # robot 1's PGO moves its submaps: its pose table goes through versions
        maps[1].move_submap(0, make_pose(so3_exp([0.0, 0.0, 0.02 * (k + 1)]), [0.1 * (k + 1), 0.0, 0.0]))
        t = run(net, t, 2)
    held = nodes[0].poses[1][0].version
    assert held >= 4
    assert_exact(maps, nodes)
    # robot 1 restarts: a fresh map consensus over its map, which its PGO then moves once more
    nodes[1] = MapConsensus(1, maps[1], MapConsensusParams(mode="exact", hold=0.0), team_size=2)
    nodes[1].set_frame(0)
    maps[1].move_submap(1, make_pose(so3_exp([0.0, 0.0, -0.05]), [0.0, 0.25, 0.0]))
    net = MapExchange(nodes, links=lambda now: full_links([0, 1]))
    run(net, t, 12)
    assert nodes[0].poses[1][0].version > held
    assert all(node.gaps({0, 1}) == {} for node in nodes.values())
    assert_exact(maps, nodes)


def test_version_marks_are_held_in_the_narrowest_dtype_that_holds_them() -> None:
    """Marks count scans, so a byte holds most; a larger version widens them without changing any."""
    from kimera_multi_py.mapshare.held import marks_for

    marks = np.array([3, 200], np.uint8)
    assert marks_for(marks, 255) is marks
    wide = marks_for(marks, 256)
    assert wide.dtype == np.uint16 and wide.tolist() == [3, 200]
    wider = marks_for(wide, 70_000)
    assert wider.dtype == np.int32 and wider.tolist() == [3, 200]
