"""Places and rooms on hand-made maps: two rooms and a door, an L-shaped room."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.scene_graph import SceneGraphError, SceneGraphParams, build_scene_graph
from kimera_multi_py.scene_graph.grid import distance_field, occupancy_grid
from kimera_multi_py.scene_graph.places import extract_places
from tests.scene_graph.helpers import L_ROOM, TWO_ROOMS, add_box, box_world, octree_of


@pytest.fixture(scope="module")
def two_rooms():
    c, free = box_world(*TWO_ROOMS)
    free = add_box(c, free, (0.5, 0.5, 0.0), (1.7, 1.3, 0.75))  # a table in the west room
    tree = octree_of(c, free)
    objects = [(7, "table", (1.1, 0.9, 0.4), (0.5, 0.5, 0.0), (1.7, 1.3, 0.75)),
               (8, "cabinet", (7.7, 3.6, 0.9), (7.45, 3.2, 0.0), (7.95, 3.95, 1.8))]
    stamps = np.arange(5) * 10.0
    poses = np.repeat(np.eye(4)[None], 5, axis=0)
    poses[:, :3, 3] = [[1.0, 2.0, 1.0], [3.0, 2.0, 1.0], [4.0, 2.0, 1.0], [5.0, 2.0, 1.0], [7.0, 2.0, 1.0]]
    return build_scene_graph(tree, objects, {0: (stamps, poses)})


def _room_at(g, x: float, y: float) -> int:
    """Room of the places in a 1 m square around (x, y)."""
    near = np.all(np.abs(g.place_pos[:, :2] - [x, y]) < 0.5, axis=1) & (g.place_room >= 0)
    rooms = np.unique(g.place_room[near])
    assert len(rooms) == 1, f"places around ({x}, {y}) are in rooms {rooms}"
    return int(rooms[0])


def test_places_lie_in_free_space_with_their_clearance(two_rooms) -> None:
    c, free = box_world(*TWO_ROOMS)
    field = distance_field(occupancy_grid(octree_of(c, free)))
    places = extract_places(field, SceneGraphParams())
    assert len(places) > 50
    assert places.clearance.min() >= 0.4 - 1e-6
    np.testing.assert_allclose(field.clearance_at(places.positions), places.clearance, atol=1e-5)
    # edges are short and keep their clearance
    e = places.edges
    assert np.all(places.edge_clearance >= 0.25)
    assert np.linalg.norm(places.positions[e[:, 0]] - places.positions[e[:, 1]], axis=1).max() < 1.5


def test_two_rooms_joined_by_a_door_stay_two(two_rooms) -> None:
    g = two_rooms
    assert g.num_rooms == 2
    west, east = _room_at(g, 2.0, 2.0), _room_at(g, 6.0, 2.0)
    assert west != east
    # no place of one room lies inside the other room (the wall is at x = 4)
    assert np.all(g.place_pos[g.place_room == west, 0] < 4.3)
    assert np.all(g.place_pos[g.place_room == east, 0] > 3.7)
    assert g.room_edges.tolist() == [[0, 1]]  # the door joins them
    assert g.room_pos[west, 0] < 4.0 < g.room_pos[east, 0]


def test_l_shaped_room_stays_one_room() -> None:
    c, free = box_world(*L_ROOM)
    g = build_scene_graph(octree_of(c, free))
    assert g.num_rooms == 1
    assert np.mean(g.place_room == 0) > 0.95
    # both arms' far ends belong to it
    assert _room_at(g, 5.0, 1.25) == _room_at(g, 1.25, 5.0) == 0


def test_objects_and_agents_hang_below_places(two_rooms) -> None:
    g = two_rooms
    rooms = g.object_room()
    assert rooms[0] == _room_at(g, 2.0, 2.0) and rooms[1] == _room_at(g, 6.0, 2.0)
    assert np.all(g.agent_place >= 0)
    assert g.place_room[g.agent_place[0]] == rooms[0] and g.place_room[g.agent_place[-1]] == rooms[1]
    assert g.nodes_per_layer() == {"objects": 2, "agents": 5, "places": len(g.place_ids), "rooms": 2, "building": 1}


def test_identical_maps_give_identical_graphs(two_rooms) -> None:
    c, free = box_world(*TWO_ROOMS)
    free = add_box(c, free, (0.5, 0.5, 0.0), (1.7, 1.3, 0.75))
    a = build_scene_graph(octree_of(c, free))
    np.testing.assert_array_equal(a.place_ids, two_rooms.place_ids)
    np.testing.assert_array_equal(a.place_room, two_rooms.place_room)
    assert len(np.unique(a.place_ids)) == len(a.place_ids)


def test_bad_input_is_named(two_rooms) -> None:
    c, free = box_world(*TWO_ROOMS)
    tree = octree_of(c, free)
    with pytest.raises(SceneGraphError, match="unknown object class"):
        build_scene_graph(tree, [(1, "spaceship", (1, 1, 1), (0, 0, 0), (2, 2, 2))])
    with pytest.raises(SceneGraphError, match="unique"):
        build_scene_graph(tree, [(1, "chair", (1, 1, 1), (0, 0, 0), (2, 2, 2))] * 2)
    with pytest.raises(SceneGraphError, match="3 stamps for 2 poses"):
        build_scene_graph(tree, [], {0: (np.arange(3.0), np.repeat(np.eye(4)[None], 2, 0))})
    with pytest.raises(SceneGraphError, match="must not decrease"):
        build_scene_graph(tree, [], {0: (np.array([1.0, 0.0]), np.repeat(np.eye(4)[None], 2, 0))})
    with pytest.raises(SceneGraphError, match="letter 'p'"):
        build_scene_graph(tree, [], {15: (np.arange(1.0), np.eye(4)[None])})


def test_ceiling_cut_needs_clearance_above_the_doors_half_width() -> None:
    c, free = box_world(*TWO_ROOMS)  # the door is 1 m wide and full height
    tree = octree_of(c, free)
    assert build_scene_graph(tree, params=SceneGraphParams(room_method="ceiling")).num_rooms == 1
    two = build_scene_graph(tree, params=SceneGraphParams(room_method="ceiling", ceiling_clearance=0.6))
    assert two.num_rooms == 2
    with pytest.raises(Exception, match="room_method"):
        SceneGraphParams(room_method="magic")


def _holed(c: np.ndarray, free: np.ndarray, fraction: float, seed: int) -> object:
    """The map with a random ``fraction`` of its free cells never observed (holes between rays)."""
    from kimera_multi_py.mapping import morton
    from kimera_multi_py.mapping.observation import SCALE
    from kimera_multi_py.mapping.semantic_octree import SemanticOctree
    from tests.scene_graph.helpers import RES, WALL, K

    rng = np.random.default_rng(seed)
    seen = ~free | (rng.random(len(free)) >= fraction)
    tree = SemanticOctree(RES, K)
    codes = morton.points_to_codes(c[seen], RES)
    order = np.argsort(codes)
    rows = np.zeros((len(codes), K + 1), dtype=np.int16)
    rows[:, 1:] = -3 * SCALE
    rows[~free[seen], WALL] = 6 * SCALE
    tree.add(codes[order], rows[order])
    return tree


def test_holes_between_rays_do_not_break_rooms() -> None:
    """3 % of the free cells unobserved, scattered: filled, the two rooms keep their places and
    stay two; counted as obstacles, the clearance collapses and the rooms are lost."""
    c, free = box_world(*TWO_ROOMS)
    tree = _holed(c, free, 0.03, 4)
    clean = build_scene_graph(octree_of(c, free))
    g = build_scene_graph(tree)
    assert g.num_rooms == 2
    assert len(g.place_ids) > 0.8 * len(clean.place_ids)
    bare = build_scene_graph(tree, params=SceneGraphParams(hole_min_free=0))
    assert bare.num_rooms < 2 or len(bare.place_ids) < 0.5 * len(clean.place_ids)


def test_freespace_edges_join_components_through_free_space_only() -> None:
    from kimera_multi_py.scene_graph.places import _freespace_edges

    c, free = box_world(*TWO_ROOMS)
    field = distance_field(occupancy_grid(octree_of(c, free)))
    # components {0, 1} and {2} in the west room 1.2 m apart; {3} in the east room behind the wall
    pos = np.array([[1.0, 2.0, 1.2], [1.5, 2.0, 1.2], [2.7, 2.0, 1.2], [4.6, 3.5, 1.2]])
    e, w = np.array([[0, 1]]), np.array([0.9])
    ne, nw = _freespace_edges(field, pos, e, w, SceneGraphParams())
    assert ne.tolist() == [[0, 1], [1, 2]]  # the shorter of the two clear candidates to {2}
    assert nw[1] == pytest.approx(field.clearance_at(np.linspace(pos[1], pos[2], 30)).min(), abs=1e-6)
    # nothing through the wall at x = 4 (the door is at y in [1.5, 2.5]), none when disabled
    off = _freespace_edges(field, pos, e, w, SceneGraphParams(freespace_edge_max_length=0.0))
    assert off[0].tolist() == [[0, 1]]


def _tilted(c: np.ndarray, free: np.ndarray, R: np.ndarray, t: np.ndarray) -> object:
    """The floor plan seen in a tilted frame ``p_map = R p + t`` (floor, ceiling and walls labelled),
    binned into the map's grid (occupied wins where two cells land in one)."""
    from kimera_multi_py.core.semantics import CLASS_IDS
    from kimera_multi_py.mapping import morton
    from kimera_multi_py.mapping.observation import SCALE
    from kimera_multi_py.mapping.semantic_octree import SemanticOctree
    from tests.scene_graph.helpers import HEIGHT, RES, WALL, K

    cls = np.where(c[:, 2] < 0.0, CLASS_IDS["floor"], np.where(c[:, 2] > HEIGHT, CLASS_IDS["ceiling"], WALL))
    codes = morton.points_to_codes(c @ R.T + t, RES)
    order = np.lexsort((free, codes))  # per code, occupied (free = False) first
    codes, keep = np.unique(codes[order], return_index=True)
    sel = order[keep]
    rows = np.zeros((len(codes), K + 1), dtype=np.int16)
    rows[:, 1:] = -3 * SCALE
    occ = ~free[sel]
    rows[np.flatnonzero(occ), cls[sel][occ]] = 6 * SCALE
    tree = SemanticOctree(RES, K)
    tree.add(codes, rows)
    return tree


def test_a_tilted_map_is_built_level_and_answers_in_its_own_frame() -> None:
    from kimera_multi_py.core.geometry import so3_exp

    c, free = box_world(*TWO_ROOMS)
    R = so3_exp(np.array([np.radians(25.0), np.radians(-10.0), np.radians(40.0)]))
    t = np.array([1.0, -2.0, 0.5])
    g = build_scene_graph(_tilted(c, free, R, t))
    assert g.num_rooms == 2
    L = np.array(g.metadata["level_rotation"])
    assert np.degrees(np.arccos(np.clip((L @ R)[2, 2], -1, 1))) < 2.0  # level: the plan's z is up again
    plan = (g.place_pos - t) @ R  # places back in the floor plan's frame
    inside = (plan[:, 2] > 0.0) & (plan[:, 2] < 2.5) & (plan[:, 0] > -0.2) & (plan[:, 0] < 8.2)
    assert inside.mean() > 0.98
    west = g.place_room[plan[:, 0] < 3.5]
    east = g.place_room[plan[:, 0] > 4.5]
    assert len(set(west.tolist()) - {-1}) == 1 and len(set(east.tolist()) - {-1}) == 1
    assert set(west.tolist()) != set(east.tolist())
    # a level map is built as it stands
    assert build_scene_graph(octree_of(c, free)).metadata["level_rotation"] is None
