"""Spark-DSG files (``dsg.json``, which Hydra's tools open) and a networkx view of a scene graph.

Node ids are ``spark_dsg.NodeSymbol`` values: ``O`` + object id, ``p`` + place id (geometric,
see :func:`~.places.place_ids`), ``R`` + room index, ``B0`` the building and the robot's letter +
keyframe index for agents (layer 2, partition = the letter's code), and ``H`` + a running sample
index for people: dynamic agents of layer 2, one partition per person (``PEOPLE_PARTITION`` + the
person's rank by id), one node per sample with its stamp, position and person id, chained in time,
with edges to the sample's place and room (docs/algorithms/people.md). Hierarchy edges run child ->
parent (object/agent -> place -> room -> building); place-place edges carry the clearance as
their weight; room-room edges join rooms a place edge crosses; agent poses are chained in order.
What Spark-DSG has no field for (exact stamps and poses, the build's parameters) goes in metadata.
"""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np
import spark_dsg as dsg

from kimera_multi_py.core.geometry import rot_to_quat
from kimera_multi_py.core.semantics import CLASS_COLORS, CLASS_NAMES
from kimera_multi_py.scene_graph.graph import (
    AGENTS_LAYER,
    BUILDING_LAYER,
    OBJECTS_LAYER,
    PLACES_LAYER,
    ROOMS_LAYER,
    SceneGraph,
    SceneGraphError,
    robot_letter,
)

_ROOM_COLORS = np.array([[228, 26, 28], [55, 126, 184], [77, 175, 74], [152, 78, 163], [255, 127, 0],
                         [166, 86, 40], [247, 129, 191], [153, 153, 153], [255, 255, 51], [0, 128, 128]], np.uint8)


def place_symbol(pid: int) -> dsg.NodeSymbol:
    return dsg.NodeSymbol("p", int(pid))


def room_symbol(r: int) -> dsg.NodeSymbol:
    return dsg.NodeSymbol("R", int(r))


def object_symbol(oid: int) -> dsg.NodeSymbol:
    return dsg.NodeSymbol("O", int(oid))


def agent_symbol(robot: int, k: int) -> dsg.NodeSymbol:
    return dsg.NodeSymbol(robot_letter(robot), int(k))


BUILDING = dsg.NodeSymbol("B", 0)
PERSON = "H"
PEOPLE_PARTITION = 1000  # people's partitions start here (robots' are their letters' codes)


def person_symbol(sample: int) -> dsg.NodeSymbol:
    return dsg.NodeSymbol(PERSON, int(sample))


def room_color(r: int) -> np.ndarray:
    return _ROOM_COLORS[r % len(_ROOM_COLORS)]


def _color(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, dtype=np.uint8).reshape(3)


def _box(lo: np.ndarray, hi: np.ndarray) -> dsg.BoundingBox:
    return dsg.BoundingBox(np.asarray(hi - lo, np.float32), np.asarray((lo + hi) / 2, np.float32))


def _edge(weight: float) -> dsg.EdgeAttributes:
    e = dsg.EdgeAttributes()
    e.weight, e.weighted = float(weight), True
    return e


def to_spark(g: SceneGraph) -> dsg.DynamicSceneGraph:
    """A Spark-DSG graph holding every layer of ``g``."""
    G = dsg.DynamicSceneGraph()
    b = dsg.SemanticNodeAttributes()  # what Hydra gives its building node
    b.position, b.name = np.asarray(g.building_pos, np.float64), "building"
    G.add_node(BUILDING_LAYER, BUILDING, b)
    for r in range(g.num_rooms):
        a = dsg.RoomNodeAttributes()
        a.position, a.name, a.color = g.room_pos[r], f"room {r}", _color(room_color(r))
        if r < len(g.room_kind):
            a.metadata.set({"kind": g.room_kind[r], "kind_confidence": float(g.room_kind_confidence[r])})
        inside = g.place_pos[g.place_room == r]
        if len(inside):
            a.bounding_box = _box(inside.min(0), inside.max(0))
        G.add_node(ROOMS_LAYER, room_symbol(r), a)
        G.insert_edge(room_symbol(r), BUILDING)
    for r, s in g.room_edges.tolist():
        G.insert_edge(room_symbol(r), room_symbol(s))
    for i, pid in enumerate(g.place_ids.tolist()):
        a = dsg.PlaceNodeAttributes()
        a.position, a.distance = g.place_pos[i], float(g.place_clearance[i])
        G.add_node(PLACES_LAYER, place_symbol(pid), a)
        if g.place_room[i] >= 0:
            G.insert_edge(place_symbol(pid), room_symbol(int(g.place_room[i])))
    for (i, j), w in zip(g.place_edges.tolist(), g.place_edge_clearance.tolist(), strict=True):
        G.insert_edge(place_symbol(g.place_ids[i]), place_symbol(g.place_ids[j]), _edge(w))
    for k, oid in enumerate(g.object_ids.tolist()):
        a = dsg.ObjectNodeAttributes()
        c = int(g.object_class[k])
        a.position, a.semantic_label, a.name = g.object_pos[k], c, CLASS_NAMES[c]
        a.color, a.bounding_box = _color(CLASS_COLORS[c]), _box(g.object_lo[k], g.object_hi[k])
        G.add_node(OBJECTS_LAYER, object_symbol(oid), a)
        if g.object_place[k] >= 0:
            G.insert_edge(object_symbol(oid), place_symbol(g.place_ids[g.object_place[k]]))
    quats = rot_to_quat(g.agent_pose[:, :3, :3]) if len(g.agent_pose) else np.zeros((0, 4))
    for k in range(len(g.agent_robot)):
        robot, idx = int(g.agent_robot[k]), int(g.agent_index[k])
        a = dsg.AgentNodeAttributes()
        qx, qy, qz, qw = quats[k].tolist()
        a.position, a.world_R_body = g.agent_pose[k, :3, 3], dsg.Quaternion(qw, qx, qy, qz)
        a.timestamp = datetime.timedelta(seconds=float(g.agent_stamp[k]))
        a.metadata.set({"stamp": float(g.agent_stamp[k]), "pose": g.agent_pose[k].tolist()})
        sym = agent_symbol(robot, idx)
        G.add_node(AGENTS_LAYER, sym, a, ord(robot_letter(robot)))
        if g.agent_place[k] >= 0:
            G.insert_edge(sym, place_symbol(g.place_ids[g.agent_place[k]]))
        if k and g.agent_robot[k - 1] == robot:
            G.insert_edge(agent_symbol(robot, int(g.agent_index[k - 1])), sym)
    _add_people(G, g)
    G.metadata.set({"kimera_multi": _jsonable(g.metadata)})
    return G


def _add_people(G: dsg.DynamicSceneGraph, g: SceneGraph) -> None:
    rank = {pid: i for i, pid in enumerate(np.unique(g.person_id).tolist())}
    rooms = g.person_room()
    for k in range(len(g.person_id)):
        pid = int(g.person_id[k])
        a = dsg.AgentNodeAttributes()
        a.position, a.world_R_body = g.person_pos[k], dsg.Quaternion(1.0, 0.0, 0.0, 0.0)
        a.timestamp = datetime.timedelta(seconds=float(g.person_stamp[k]))
        a.metadata.set({"person": pid, "stamp": float(g.person_stamp[k])})
        G.add_node(AGENTS_LAYER, person_symbol(k), a, PEOPLE_PARTITION + rank[pid])
        if g.person_place[k] >= 0:
            G.insert_edge(person_symbol(k), place_symbol(g.place_ids[g.person_place[k]]))
        if rooms[k] >= 0:
            G.insert_edge(person_symbol(k), room_symbol(int(rooms[k])))
        if k and g.person_id[k - 1] == pid:
            G.insert_edge(person_symbol(k - 1), person_symbol(k))


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _vec(node: Any, name: str) -> np.ndarray:
    """A copy of a vector attribute, taken while the attributes object is alive (the bindings return
    views into it)."""
    attrs = node.attributes
    return np.array(getattr(attrs, name), dtype=np.float64, copy=True)


def _box_min_max(node: Any) -> tuple[np.ndarray, np.ndarray]:
    attrs = node.attributes
    box = attrs.bounding_box
    return np.array(box.min, dtype=np.float64, copy=True), np.array(box.max, dtype=np.float64, copy=True)


def from_spark(G: dsg.DynamicSceneGraph) -> SceneGraph:
    """The arrays of a Spark-DSG graph written by :func:`to_spark`."""
    places, rooms, objects, agents, people = [], [], [], [], []
    building = np.zeros(3)
    for node in G.nodes:
        sym = node.id
        cat, layer = sym.category, node.layer.layer
        if layer == PLACES_LAYER and cat == "p":
            places.append(node)
        elif layer == ROOMS_LAYER and cat == "R":
            rooms.append(node)
        elif layer == BUILDING_LAYER and cat == "B":
            building = _vec(node, "position")
        elif layer == OBJECTS_LAYER and node.layer.partition == 0 and cat == "O":
            objects.append(node)
        elif layer == AGENTS_LAYER and cat == PERSON and node.layer.partition >= PEOPLE_PARTITION:
            people.append(node)
        elif layer == AGENTS_LAYER and node.layer.partition != 0:
            agents.append(node)
    places.sort(key=lambda n: n.id.category_id)
    rooms.sort(key=lambda n: n.id.category_id)
    objects.sort(key=lambda n: n.id.category_id)
    place_ids = np.array([n.id.category_id for n in places], dtype=np.int64)
    room_ids = [n.id.category_id for n in rooms]
    if room_ids != list(range(len(rooms))):
        raise SceneGraphError("rooms must be numbered R(0), R(1), ... without gaps")
    index_of = {n.id.value: i for i, n in enumerate(places)}

    def parent_place(n: Any) -> int:
        return next((index_of[int(q)] for q in n.parents() if int(q) in index_of), -1)

    def parent_room(n: Any) -> int:
        return next((dsg.NodeSymbol(q).category_id for q in n.parents() if dsg.NodeSymbol(q).category == "R"), -1)

    edges, weights, room_edges = [], [], []
    for e in G.edges:
        s, t = int(e.source), int(e.target)
        if s in index_of and t in index_of:
            edges.append(sorted((index_of[s], index_of[t])))
            weights.append(e.info.weight)
        elif dsg.NodeSymbol(s).category == "R" and dsg.NodeSymbol(t).category == "R":
            room_edges.append(sorted((dsg.NodeSymbol(s).category_id, dsg.NodeSymbol(t).category_id)))
    pe = np.array(edges, dtype=np.int64).reshape(-1, 2)
    order = np.lexsort((pe[:, 1], pe[:, 0]))
    re = np.array(room_edges, dtype=np.int64).reshape(-1, 2)
    re = re[np.lexsort((re[:, 1], re[:, 0]))]
    agents.sort(key=lambda n: (n.id.category, n.id.category_id))
    a_meta = [n.attributes.metadata.get() for n in agents]
    meta = G.metadata.get().get("kimera_multi", {})
    boxes = [_box_min_max(n) for n in objects]
    r_meta = [n.attributes.metadata.get() for n in rooms]
    people.sort(key=lambda n: n.id.category_id)
    p_meta = [n.attributes.metadata.get() for n in people]

    def arr(rows: list[Any], dim: int = 3) -> np.ndarray:
        return np.array(rows, dtype=np.float64).reshape(-1, dim)

    return SceneGraph(
        place_ids=place_ids,
        place_pos=arr([_vec(n, "position") for n in places]),
        place_clearance=np.array([n.attributes.distance for n in places], dtype=np.float64),
        place_room=np.array([parent_room(n) for n in places], dtype=np.int64),
        place_edges=pe[order],
        place_edge_clearance=np.array(weights, dtype=np.float64)[order],
        room_pos=arr([_vec(n, "position") for n in rooms]),
        room_edges=re,
        object_ids=np.array([n.id.category_id for n in objects], dtype=np.int64),
        object_class=np.array([n.attributes.semantic_label for n in objects], dtype=np.int64),
        object_pos=arr([_vec(n, "position") for n in objects]),
        object_lo=arr([b[0] for b in boxes]),
        object_hi=arr([b[1] for b in boxes]),
        object_place=np.array([parent_place(n) for n in objects], dtype=np.int64),
        agent_robot=np.array([ord(n.id.category) - ord("a") for n in agents], dtype=np.int64),
        agent_index=np.array([n.id.category_id for n in agents], dtype=np.int64),
        agent_stamp=np.array([m.get("stamp", n.attributes.timestamp.total_seconds())
                              for m, n in zip(a_meta, agents, strict=True)], dtype=np.float64),
        agent_pose=np.array([m.get("pose", np.eye(4).tolist()) for m in a_meta], dtype=np.float64).reshape(-1, 4, 4),
        agent_place=np.array([parent_place(n) for n in agents], dtype=np.int64),
        building_pos=building,
        metadata=meta,
        person_id=np.array([m.get("person", -1) for m in p_meta], dtype=np.int64),
        person_stamp=np.array([m.get("stamp", n.attributes.timestamp.total_seconds())
                               for m, n in zip(p_meta, people, strict=True)], dtype=np.float64),
        person_pos=arr([_vec(n, "position") for n in people]),
        person_place=np.array([parent_place(n) for n in people], dtype=np.int64),
        room_kind=[str(m.get("kind", "unknown")) for m in r_meta],
        room_kind_confidence=np.array([m.get("kind_confidence", 0.0) for m in r_meta], dtype=np.float64),
    )


def save_scene_graph(g: SceneGraph, path: str | Path) -> Path:
    """Write ``dsg.json`` (or ``.sparkdsg`` binary, by suffix) through Spark-DSG."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    to_spark(g).save(str(path), include_mesh=False)
    return path


def load_scene_graph(path: str | Path) -> SceneGraph:
    """Read a file written by :func:`save_scene_graph`; raises SceneGraphError if it is missing or bad."""
    path = Path(path)
    if not path.is_file():
        raise SceneGraphError(f"{path}: no such scene-graph file")
    try:
        G = dsg.DynamicSceneGraph.load(str(path))
    except Exception as exc:  # noqa: BLE001 -- the C++ loader raises assorted types on bad files
        raise SceneGraphError(f"{path}: not a Spark-DSG file ({type(exc).__name__}: {exc})") from None
    return from_spark(G)


def to_networkx(g: SceneGraph) -> nx.Graph:
    """An undirected networkx view: nodes keyed by their NodeSymbol string, with ``layer``,
    ``position`` and per-layer attributes; edges carry ``kind`` (``hierarchy``, ``place``,
    ``room``, ``agent``) and, between places, ``clearance`` and Euclidean ``length``."""
    G = nx.Graph()
    bs = str(BUILDING)
    G.add_node(bs, layer=BUILDING_LAYER, position=g.building_pos.copy())
    for r in range(g.num_rooms):
        G.add_node(str(room_symbol(r)), layer=ROOMS_LAYER, position=g.room_pos[r].copy(),
                   kind=g.room_kind[r] if r < len(g.room_kind) else None)
        G.add_edge(str(room_symbol(r)), bs, kind="hierarchy")
    for r, s in g.room_edges.tolist():
        G.add_edge(str(room_symbol(r)), str(room_symbol(s)), kind="room")
    pnames = [str(place_symbol(p)) for p in g.place_ids.tolist()]
    for i, name in enumerate(pnames):
        G.add_node(name, layer=PLACES_LAYER, position=g.place_pos[i].copy(), clearance=float(g.place_clearance[i]))
        if g.place_room[i] >= 0:
            G.add_edge(name, str(room_symbol(int(g.place_room[i]))), kind="hierarchy")
    for (i, j), w in zip(g.place_edges.tolist(), g.place_edge_clearance.tolist(), strict=True):
        G.add_edge(pnames[i], pnames[j], kind="place", clearance=w,
                   length=float(np.linalg.norm(g.place_pos[i] - g.place_pos[j])))
    for k, oid in enumerate(g.object_ids.tolist()):
        name = str(object_symbol(oid))
        G.add_node(name, layer=OBJECTS_LAYER, position=g.object_pos[k].copy(),
                   label=CLASS_NAMES[int(g.object_class[k])])
        if g.object_place[k] >= 0:
            G.add_edge(name, pnames[g.object_place[k]], kind="hierarchy")
    for k in range(len(g.agent_robot)):
        name = str(agent_symbol(int(g.agent_robot[k]), int(g.agent_index[k])))
        G.add_node(name, layer=AGENTS_LAYER, position=g.agent_pose[k, :3, 3].copy(), stamp=float(g.agent_stamp[k]),
                   robot=int(g.agent_robot[k]))
        if g.agent_place[k] >= 0:
            G.add_edge(name, pnames[g.agent_place[k]], kind="hierarchy")
        if k and g.agent_robot[k - 1] == g.agent_robot[k]:
            prev = str(agent_symbol(int(g.agent_robot[k]), int(g.agent_index[k - 1])))
            G.add_edge(prev, name, kind="agent")
    rooms = g.person_room()
    for k in range(len(g.person_id)):
        name = str(person_symbol(k))
        G.add_node(name, layer=AGENTS_LAYER, position=g.person_pos[k].copy(), stamp=float(g.person_stamp[k]),
                   person=int(g.person_id[k]))
        if g.person_place[k] >= 0:
            G.add_edge(name, pnames[g.person_place[k]], kind="hierarchy")
        if rooms[k] >= 0:
            G.add_edge(name, str(room_symbol(int(rooms[k]))), kind="hierarchy")
        if k and g.person_id[k - 1] == g.person_id[k]:
            G.add_edge(str(person_symbol(k - 1)), name, kind="person")
    return G
