"""Queries on a scene graph: the room of an object, the objects in a room, a shortest route over
places, where a robot was at a time (docs/algorithms/scene_graph.md), and the people: who is in a
room at a time, which rooms are occupied, where a person was, the rooms a person visited
(docs/algorithms/people.md).

Nodes are named as Spark-DSG prints them (``O(3)``, ``R(1)``, ``p(…)``, ``a(12)``); ``O3`` and
``R1`` are accepted too, and plain integers mean object ids for objects and room indices for
rooms; people are ``P(12)`` (their id). Answers are plain dicts of JSON types (the CLI prints
them as tables or JSON).
"""

from __future__ import annotations

import re
from typing import Any

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

from kimera_multi_py.core.semantics import CLASS_IDS, CLASS_NAMES
from kimera_multi_py.scene_graph.dsg_io import agent_symbol, object_symbol, place_symbol, room_symbol
from kimera_multi_py.scene_graph.graph import SceneGraph, SceneGraphError

_NAME = re.compile(r"^\s*([A-Za-z])\s*\(?\s*(\d+)\s*\)?\s*$")


def _parse(name: str | int, category: str) -> int:
    """The index in ``O(3)`` / ``O3`` / ``3`` for the given category."""
    if isinstance(name, int | np.integer):
        return int(name)
    m = _NAME.match(str(name))
    if m and m.group(1) == category:
        return int(m.group(2))
    if str(name).strip().isdigit():
        return int(str(name).strip())
    raise SceneGraphError(f"{name!r} is not a {category} node name (e.g. {category}(3))")


def _room_name(g: SceneGraph, r: int) -> str | None:
    return str(room_symbol(r)) if r >= 0 else None


def _object_index(g: SceneGraph, obj: str | int) -> int:
    oid = _parse(obj, "O")
    hit = np.flatnonzero(g.object_ids == oid)
    if len(hit) == 0:
        raise SceneGraphError(f"no object O({oid}) in the scene graph ({len(g.object_ids)} objects)")
    return int(hit[0])


def room_of(g: SceneGraph, obj: str | int) -> dict[str, Any]:
    """The room (through its place) of object ``obj``."""
    k = _object_index(g, obj)
    p = int(g.object_place[k])
    r = int(g.place_room[p]) if p >= 0 else -1
    return {"object": str(object_symbol(int(g.object_ids[k]))), "class": CLASS_NAMES[int(g.object_class[k])],
            "position": g.object_pos[k].round(3).tolist(),
            "place": str(place_symbol(int(g.place_ids[p]))) if p >= 0 else None, "room": _room_name(g, r)}


def objects_in(g: SceneGraph, room: str | int, cls: str | int | None = None) -> list[dict[str, Any]]:
    """Objects whose place lies in ``room`` (a room or a kind of room), optionally of one class (name or id)."""
    rooms = g.object_room()
    keep = np.isin(rooms, room_indices(g, room))
    if cls is not None:
        c = CLASS_IDS.get(str(cls)) if not str(cls).isdigit() else int(cls)
        if c is None or not 0 < c < len(CLASS_NAMES):
            raise SceneGraphError(f"unknown class {cls!r} (known: {', '.join(CLASS_NAMES[1:])})")
        keep &= g.object_class == c
    return [{"object": str(object_symbol(int(g.object_ids[k]))), "class": CLASS_NAMES[int(g.object_class[k])],
             "position": g.object_pos[k].round(3).tolist()} for k in np.flatnonzero(keep)]


def place_graph(g: SceneGraph) -> nx.Graph:
    """Places as a networkx graph (node = place index) with Euclidean edge ``length``."""
    G = nx.Graph()
    G.add_nodes_from(range(len(g.place_ids)))
    e = g.place_edges
    length = np.linalg.norm(g.place_pos[e[:, 0]] - g.place_pos[e[:, 1]], axis=1)
    G.add_weighted_edges_from(zip(e[:, 0].tolist(), e[:, 1].tolist(), length.tolist(), strict=True), weight="length")
    return G


def _endpoint(g: SceneGraph, a: Any) -> tuple[np.ndarray, int]:
    """A point (3 numbers) or an object / place name -> (position, place index)."""
    if isinstance(a, str) and _NAME.match(a):
        m = _NAME.match(a)
        assert m is not None
        if m.group(1) == "O":
            k = _object_index(g, a)
            return g.object_pos[k], int(g.object_place[k])
        if m.group(1) == "p":
            hit = np.flatnonzero(g.place_ids == int(m.group(2)))
            if len(hit):
                return g.place_pos[hit[0]], int(hit[0])
        raise SceneGraphError(f"{a!r}: a path end must be a point, an object O(k) or a place p(k)")
    p = np.asarray(a, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise SceneGraphError(f"{a!r}: a path end must be three finite coordinates")
    return p, int(cKDTree(g.place_pos).query(p)[1])


def path(g: SceneGraph, a: Any, b: Any) -> dict[str, Any]:
    """Shortest route over places (Euclidean edge lengths) between two points or nodes; each end
    is joined to its place (the nearest one for a point)."""
    if len(g.place_ids) == 0:
        raise SceneGraphError("the scene graph has no places")
    pa, ia = _endpoint(g, a)
    pb, ib = _endpoint(g, b)
    if ia < 0 or ib < 0:
        raise SceneGraphError("a path end has no place")
    try:
        nodes = nx.shortest_path(place_graph(g), ia, ib, weight="length")
    except nx.NetworkXNoPath:
        raise SceneGraphError(f"no route over places from {pa.round(2).tolist()} to {pb.round(2).tolist()}") from None
    pts = np.vstack([pa, g.place_pos[nodes], pb])
    rooms = [int(g.place_room[n]) for n in nodes]
    through = [r for i, r in enumerate(rooms) if r >= 0 and (i == 0 or r != rooms[i - 1])]
    return {"places": [str(place_symbol(int(g.place_ids[n]))) for n in nodes],
            "rooms": [_room_name(g, r) for r in through],
            "waypoints": pts.round(3).tolist(),
            "length": float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())}


def where(g: SceneGraph, robot: int | str, t: float) -> dict[str, Any]:
    """Robot ``robot``'s last keyframe at or before time ``t`` (the first one if ``t`` is earlier)."""
    r = ord(robot) - ord("a") if isinstance(robot, str) and robot.isalpha() and len(robot) == 1 else int(robot)
    sel = np.flatnonzero(g.agent_robot == r)
    if len(sel) == 0:
        robots = sorted(set(g.agent_robot.tolist()))
        raise SceneGraphError(f"robot {robot} has no poses in the scene graph (robots: {robots})")
    stamps = g.agent_stamp[sel]
    i = int(np.searchsorted(stamps, float(t), side="right")) - 1
    k = int(sel[max(i, 0)])
    p = int(g.agent_place[k])
    room = int(g.place_room[p]) if p >= 0 else -1
    return {"robot": r, "t": float(t), "node": str(agent_symbol(r, int(g.agent_index[k]))),
            "stamp": float(g.agent_stamp[k]), "position": g.agent_pose[k, :3, 3].round(3).tolist(),
            "place": str(place_symbol(int(g.place_ids[p]))) if p >= 0 else None, "room": _room_name(g, room)}


# ---- people (docs/algorithms/people.md) ----------------------------------------------------------
def room_indices(g: SceneGraph, room: str | int) -> list[int]:
    """The rooms a name means: ``R(1)`` / ``R1`` / ``1``, or a kind (``meeting``: every room of
    that kind, :mod:`.kinds`)."""
    if isinstance(room, str) and room.strip() in g.room_kind:
        return [r for r, k in enumerate(g.room_kind) if k == room.strip()]
    if isinstance(room, str) and room.strip().isalpha() and len(room.strip()) > 1:
        kinds = ", ".join(sorted(set(g.room_kind))) or "none"
        raise SceneGraphError(f"no room of kind {room.strip()!r} in the scene graph (kinds: {kinds})")
    r = _parse(room, "R")
    if not 0 <= r < g.num_rooms:
        raise SceneGraphError(f"no room R({r}) in the scene graph ({g.num_rooms} rooms)")
    return [r]


def _person(g: SceneGraph, person: str | int) -> np.ndarray:
    """Sample rows of a person named ``P(12)`` / ``P12`` / ``12``."""
    pid = _parse(person, "P")
    rows = np.flatnonzero(g.person_id == pid)
    if len(rows) == 0:
        known = ", ".join(f"P({i})" for i in np.unique(g.person_id).tolist()) or "none"
        raise SceneGraphError(f"no person P({pid}) in the scene graph (people: {known})")
    return rows


def _sample(g: SceneGraph, k: int, rooms: np.ndarray) -> dict[str, Any]:
    p = int(g.person_place[k])
    return {"person": f"P({int(g.person_id[k])})", "stamp": round(float(g.person_stamp[k]), 3),
            "position": g.person_pos[k].round(3).tolist(),
            "place": str(place_symbol(int(g.place_ids[p]))) if p >= 0 else None, "room": _room_name(g, int(rooms[k]))}


def _at(g: SceneGraph, t: float, within: float) -> np.ndarray:
    """Per person seen within ``within`` s of ``t``: the row of their sample nearest to ``t``."""
    dt = np.abs(g.person_stamp - float(t))
    near = np.flatnonzero(dt <= within)
    if len(near) == 0:
        return near
    order = near[np.lexsort((dt[near], g.person_id[near]))]
    first = np.concatenate([[True], g.person_id[order][1:] != g.person_id[order][:-1]])
    return order[first]


def people_in(g: SceneGraph, room: str | int, t: float, within: float = 1.0) -> list[dict[str, Any]]:
    """The people in ``room`` at time ``t``: each person seen within ``within`` s of ``t``, by the
    room of their sample nearest in time."""
    rooms = g.person_room()
    wanted = set(room_indices(g, room))
    return [_sample(g, int(k), rooms) for k in _at(g, t, within) if int(rooms[k]) in wanted]


def occupied_rooms(g: SceneGraph, t: float, within: float = 1.0) -> list[dict[str, Any]]:
    """The rooms with people in them at time ``t`` (as :func:`people_in`), with who is there."""
    rooms = g.person_room()
    out: dict[int, list[str]] = {}
    for k in _at(g, t, within).tolist():
        if rooms[k] >= 0:
            out.setdefault(int(rooms[k]), []).append(f"P({int(g.person_id[k])})")
    return [{"room": _room_name(g, r), "people": people} for r, people in sorted(out.items())]


def where_was(g: SceneGraph, person: str | int, t: float) -> dict[str, Any]:
    """Where ``person`` was at time ``t``: between two samples, the position interpolated and the room
    of the nearer one; before the first or after the last sample, that sample (``seen`` says whether
    ``t`` lies within the person's track)."""
    rows = _person(g, person)
    stamps = g.person_stamp[rows]
    rooms = g.person_room()
    k = int(rows[int(np.argmin(np.abs(stamps - float(t))))])
    out = _sample(g, k, rooms)
    seen = bool(stamps[0] <= t <= stamps[-1])
    if seen and len(rows) > 1:
        out["position"] = [round(float(np.interp(t, stamps, g.person_pos[rows, a])), 3) for a in range(3)]
    out.update(t=float(t), seen=seen)
    return out


def rooms_visited(g: SceneGraph, person: str | int) -> list[dict[str, Any]]:
    """The rooms ``person`` was seen in, visit by visit in time order (samples outside every room
    are skipped): room, first and last stamp, samples."""
    rows = _person(g, person)
    rooms = g.person_room()[rows]
    keep = rooms >= 0
    rows, rooms = rows[keep], rooms[keep]
    if len(rows) == 0:
        return []
    start = np.flatnonzero(np.concatenate([[True], rooms[1:] != rooms[:-1]]))
    end = np.concatenate([start[1:], [len(rows)]])
    return [{"room": _room_name(g, int(rooms[a])), "first": round(float(g.person_stamp[rows[a]]), 3),
             "last": round(float(g.person_stamp[rows[b - 1]]), 3), "samples": int(b - a)}
            for a, b in zip(start.tolist(), end.tolist(), strict=True)]
