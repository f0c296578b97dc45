"""The layered scene graph as flat arrays, and :func:`build_scene_graph` (docs/algorithms/scene_graph.md).

Layers and ids follow Spark-DSG: 2 objects (``O``) and agents (the robot's letter, one
partition per robot), 3 places (``p``), 4 rooms (``R``), 5 building (``B``). Parents: object and
agent -> nearest place in sight -> room -> building. Everything is in the map frame of the
octree it was built from; the graph is pure data, with no file or network access.

Inputs
    ``objects``: object landmarks (:class:`~kimera_multi_py.mapping.landmark.Landmark`, using
    ``id``, the most likely non-free class, ``position`` (the box centre) and ``aabb()``), or
    tuples ``(id, class, centroid, box_lo, box_hi)`` with ``class`` an id or a name, or dicts with
    those keys (``id``, ``class``, ``centroid``, ``lo``, ``hi``: a ``RobotOutcome``'s objects). Ids must
    be unique.
    ``trajectories``: ``{robot index: (stamps (n,), poses (n, 4, 4))}``, keyframe poses in the
    map frame; robot ``i`` has the letter ``chr(ord('a') + i)``.
    ``people``: dicts with ``id``, ``stamps`` (n,) and ``positions`` (n, 3) in the map frame (a
    robot's tracks or the team's fused people, docs/algorithms/people.md): dynamic agents of
    layer 2, one sample per node, each attached to the place it is in (and so to a room).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from kimera_multi_py.core.errors import KimeraMultiError
from kimera_multi_py.core.ids import MAX_AGENT_ID
from kimera_multi_py.core.semantics import CLASS_IDS, CLASS_NAMES
from kimera_multi_py.mapping.object_fusion import team_id
from kimera_multi_py.mapping.semantic_octree import SemanticOctree
from kimera_multi_py.scene_graph.grid import DistanceField, distance_field, fill_holes, occupancy_grid
from kimera_multi_py.scene_graph.kinds import load_kind_table
from kimera_multi_py.scene_graph.level import level_frame, levelled_grid
from kimera_multi_py.scene_graph.params import SceneGraphParams
from kimera_multi_py.scene_graph.places import Places, extract_places
from kimera_multi_py.scene_graph.rooms import find_rooms, find_rooms_ceiling, room_edges

OBJECTS_LAYER, AGENTS_LAYER, PLACES_LAYER, ROOMS_LAYER, BUILDING_LAYER = 2, 2, 3, 4, 5
RESERVED_LETTERS = frozenset("OpRB")


class SceneGraphError(KimeraMultiError):
    """Bad scene-graph input, an unknown node in a query, or an unreadable ``dsg.json``."""


def robot_letter(robot: int) -> str:
    """The NodeSymbol category of robot ``robot``'s agent nodes (``a``, ``b``, ...)."""
    if not 0 <= robot <= MAX_AGENT_ID:
        raise SceneGraphError(f"robot {robot}: agent letters exist for robots 0..{MAX_AGENT_ID} only")
    letter = chr(ord("a") + robot)
    if letter in RESERVED_LETTERS:
        raise SceneGraphError(f"robot {robot}: its letter {letter!r} is the places' category")
    return letter


@dataclass
class SceneGraph:
    """All layers as arrays; indices link the layers (-1 = no parent)."""

    place_ids: np.ndarray  # (n,) int64
    place_pos: np.ndarray  # (n, 3)
    place_clearance: np.ndarray  # (n,)
    place_room: np.ndarray  # (n,) room index
    place_edges: np.ndarray  # (m, 2) place indices
    place_edge_clearance: np.ndarray  # (m,)
    room_pos: np.ndarray  # (r, 3)
    room_edges: np.ndarray  # (q, 2) room indices
    object_ids: np.ndarray  # (o,) int64
    object_class: np.ndarray  # (o,) class ids
    object_pos: np.ndarray  # (o, 3) centroids
    object_lo: np.ndarray  # (o, 3) axis-aligned box
    object_hi: np.ndarray
    object_place: np.ndarray  # (o,) place index
    agent_robot: np.ndarray  # (a,) robot index
    agent_index: np.ndarray  # (a,) keyframe index
    agent_stamp: np.ndarray  # (a,) s
    agent_pose: np.ndarray  # (a, 4, 4)
    agent_place: np.ndarray  # (a,)
    building_pos: np.ndarray  # (3,)
    metadata: dict[str, Any] = field(default_factory=dict)
    # people: one row per sample, grouped by person and in time order within a person
    person_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (s,)
    person_stamp: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (s,)
    person_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (s, 3)
    person_place: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (s,) place index
    # rooms by kind (:mod:`.kinds`): per room, its kind and the kind's confidence
    room_kind: list[str] = field(default_factory=list)
    room_kind_confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def num_rooms(self) -> int:
        return len(self.room_pos)

    def object_room(self) -> np.ndarray:
        """Room index of each object through its place (-1 when none)."""
        return np.where(self.object_place >= 0, self.place_room[np.maximum(self.object_place, 0)], -1) \
            if len(self.place_room) else np.full(len(self.object_ids), -1, dtype=np.int64)

    def person_room(self) -> np.ndarray:
        """Room index of each person sample through its place (-1 when none)."""
        return np.where(self.person_place >= 0, self.place_room[np.maximum(self.person_place, 0)], -1) \
            if len(self.place_room) else np.full(len(self.person_id), -1, dtype=np.int64)

    def nodes_per_layer(self) -> dict[str, int]:
        out = {"objects": len(self.object_ids), "agents": len(self.agent_robot), "places": len(self.place_ids),
               "rooms": self.num_rooms, "building": 1}
        if len(self.person_id):
            out["people"] = len(np.unique(self.person_id))
            out["people_samples"] = len(self.person_id)
        return out


def as_people(people: Iterable[Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ids, stamps, positions)`` of person dicts, one row per sample, sorted by id then stamp."""
    ids, stamps, pos = [], [], []
    for i, p in enumerate(people):
        try:
            st = np.asarray(p["stamps"], dtype=np.float64).reshape(-1)
            xyz = np.asarray(p["positions"], dtype=np.float64).reshape(-1, 3)
            pid = int(p["id"])
        except (KeyError, TypeError, ValueError) as exc:
            raise SceneGraphError(f"people[{i}]: expected id, stamps and positions ({exc})") from None
        if len(st) != len(xyz):
            raise SceneGraphError(f"people[{i}]: {len(st)} stamps for {len(xyz)} positions")
        ids.append(np.full(len(st), pid, np.int64))
        stamps.append(st)
        pos.append(xyz)
    if not ids:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
    I, S, P = np.concatenate(ids), np.concatenate(stamps), np.concatenate(pos)
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(P))):
        raise SceneGraphError("people: stamps and positions must be finite")
    order = np.lexsort((S, I))
    return I[order], S[order], P[order]


@dataclass
class _Objects:
    ids: np.ndarray
    labels: np.ndarray
    centroids: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def rows(self) -> list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]:
        return [(int(self.ids[k]), int(self.labels[k]), self.centroids[k], self.lo[k], self.hi[k])
                for k in range(len(self.ids))]


def _class_id(c: object) -> int:
    if isinstance(c, str):
        if c not in CLASS_IDS or c == "free":
            raise SceneGraphError(f"unknown object class {c!r}")
        return CLASS_IDS[c]
    k = int(c)  # type: ignore[call-overload]
    if not 0 < k < len(CLASS_NAMES):
        raise SceneGraphError(f"object class id {k} outside 1..{len(CLASS_NAMES) - 1}")
    return k


def as_objects(objects: Iterable[Any]) -> _Objects:
    """Normalise landmarks or ``(id, class, centroid, box_lo, box_hi)`` tuples."""
    rows = []
    for i, ob in enumerate(objects):
        if isinstance(ob, Mapping):  # a RobotOutcome's object: {"id", "class", "centroid", "lo", "hi", ...}
            try:
                rows.append((int(ob["id"]), _class_id(ob["class"]), ob["centroid"], ob["lo"], ob["hi"]))
            except KeyError as exc:
                raise SceneGraphError(f"objects[{i}]: missing key {exc}") from None
        elif hasattr(ob, "aabb") and hasattr(ob, "position"):  # a Landmark: its box centre is its position
            lo, hi = ob.aabb()
            counts = getattr(ob, "class_counts", None)
            label = int(np.argmax(counts[1:])) + 1 if counts is not None else ob.label  # never "free"
            rows.append((int(ob.id), _class_id(label), ob.position, lo, hi))
        else:
            try:
                oid, cls, c, lo, hi = ob
            except (TypeError, ValueError):
                raise SceneGraphError(f"objects[{i}]: expected (id, class, centroid, box_lo, box_hi)") from None
            rows.append((int(oid), _class_id(cls), c, lo, hi))
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    if len(np.unique(ids)) != len(ids):
        raise SceneGraphError("object ids must be unique")
    arr = [np.array([r[k] for r in rows], dtype=np.float64).reshape(-1, 3) for k in (2, 3, 4)]
    if not all(np.all(np.isfinite(a)) for a in arr):
        raise SceneGraphError("object centroids and boxes must be finite")
    return _Objects(ids, np.array([r[1] for r in rows], dtype=np.int64), *arr)


def team_objects(landmarks_by_robot: Mapping[int, Iterable[Any]]) -> list[tuple[int, int, Any, Any, Any]]:
    """Object tuples for a graph over several robots' landmarks, unfused, with ids made unique and
    deterministic as team ids (:func:`~kimera_multi_py.mapping.object_fusion.team_id`: each robot
    numbers its landmarks from 0). :func:`~kimera_multi_py.mapping.object_fusion.fuse_team` fuses."""
    out = []
    for robot in sorted(landmarks_by_robot):
        for ob in as_objects(landmarks_by_robot[robot]).rows():
            try:
                out.append((team_id(robot, ob[0]), *ob[1:]))
            except ValueError as exc:
                raise SceneGraphError(str(exc)) from None
    return out


def _attach(field: DistanceField, places: Places, usable: np.ndarray, points: np.ndarray, lo: np.ndarray,
            hi: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """Nearest place in sight of each point: the segment may cross only free or unknown cells, or cells
    of the point's own class (``labels``) inside its own box (``lo``, ``hi``): an object's box often holds
    some wall, which must still block. Only places in ``usable`` are tried; falls back to the nearest."""
    pool = np.flatnonzero(usable)
    if len(points) == 0 or len(pool) == 0:
        return np.full(len(points), -1, dtype=np.int64)
    k = min(k, len(pool))
    _, near = cKDTree(places.positions[pool]).query(points, k=k)
    idx = pool[np.asarray(near).reshape(len(points), k)]
    target = places.positions[idx]  # (q, k, 3)
    seen = np.concatenate([_in_sight(field, points[c:c + _CHUNK], target[c:c + _CHUNK], lo[c:c + _CHUNK],
                                     hi[c:c + _CHUNK], labels[c:c + _CHUNK]) for c in range(0, len(points), _CHUNK)])
    first = np.where(seen.any(axis=1), np.argmax(seen, axis=1), 0)
    return idx[np.arange(len(points)), first].astype(np.int64)


_CHUNK = 256  # points per line-of-sight batch (bounds memory when a point is far from every place)


def _in_sight(field: DistanceField, points: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray,
              labels: np.ndarray) -> np.ndarray:
    """``(q, k)``: whether each segment ``points[i] -> target[i, j]`` is clear (see :func:`_attach`)."""
    length = np.linalg.norm(target - points[:, None], axis=2)
    res = field.grid.resolution
    s = np.linspace(0.0, 1.0, int(np.ceil(length.max() / (0.5 * res))) + 2)
    pts = points[:, None, None, :] + s[None, None, :, None] * (target - points[:, None])[:, :, None, :]
    cells = field.grid.index(pts)
    ok = field.grid.inside(cells)
    occ = np.zeros(ok.shape, dtype=np.bool_)
    cls = np.zeros(ok.shape, dtype=np.int64)
    c = cells[ok]
    occ[ok] = field.grid.occupied[c[:, 0], c[:, 1], c[:, 2]]
    cls[ok] = field.grid.labels[c[:, 0], c[:, 1], c[:, 2]]
    own = np.all((pts >= lo[:, None, None]) & (pts <= hi[:, None, None]), axis=-1)
    own &= cls == labels[:, None, None]
    return ~np.any(occ & ~own, axis=2)


def _level_boxes(R: np.ndarray, c: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, ...]:
    """Centres and the axis-aligned bounds of boxes (map frame) in the level frame."""
    centre, half = (lo + hi) / 2 @ R.T, np.abs(R) @ ((hi - lo) / 2).T
    return c @ R.T, centre - half.T, centre + half.T


def build_scene_graph(octree: SemanticOctree, objects: Iterable[Any] = (),
                      trajectories: Mapping[int, tuple[np.ndarray, np.ndarray]] | None = None,
                      params: SceneGraphParams | None = None, people: Iterable[Any] = ()) -> SceneGraph:
    """Places, rooms and building from the octree; objects, agents and people attached (see module docs)."""
    p = params or SceneGraphParams()
    t0 = time.perf_counter()
    # a tilted map is built in its level frame (p_level = R p_map) and the results turned back
    R = level_frame(octree) if p.level else None
    try:
        grid = occupancy_grid(octree, p.esdf_resolution) if R is None else levelled_grid(octree, R, p.esdf_resolution)
    except ValueError as exc:
        raise SceneGraphError(f"scene_graph.esdf_resolution: {exc}") from None
    field = distance_field(fill_holes(grid, p.hole_min_free))
    places = extract_places(field, p)
    rooms = find_rooms(places, p) if p.room_method == "dilation" else find_rooms_ceiling(places, field, p)
    # rooms: mean of their places; building: mean of the rooms
    nr = rooms.num_rooms
    m = rooms.place_room >= 0
    counts = np.bincount(rooms.place_room[m], minlength=nr)
    room_pos = np.stack([np.bincount(rooms.place_room[m], weights=places.positions[m, a], minlength=nr)
                         for a in range(3)], 1) / np.maximum(counts, 1)[:, None]
    building = room_pos.mean(0) if nr else (places.positions.mean(0) if len(places) else np.zeros(3))
    obs = as_objects(objects)
    usable = m if m.any() else np.ones(len(places), dtype=np.bool_)  # attach to places that have a room
    c, lo, hi = (obs.centroids, obs.lo, obs.hi) if R is None else _level_boxes(R, obs.centroids, obs.lo, obs.hi)
    object_place = _attach(field, places, usable, c, lo, hi, obs.labels, p.attach_candidates)
    robots, index, stamps, poses = [], [], [], []
    for r in sorted(trajectories or {}):
        robot_letter(int(r))
        st, P = trajectories[r]  # type: ignore[index]
        st, P = np.asarray(st, dtype=np.float64).reshape(-1), np.asarray(P, dtype=np.float64).reshape(-1, 4, 4)
        if len(st) != len(P):
            raise SceneGraphError(f"trajectories[{r}]: {len(st)} stamps for {len(P)} poses")
        if not (np.all(np.isfinite(st)) and np.all(np.isfinite(P))):
            raise SceneGraphError(f"trajectories[{r}]: stamps and poses must be finite")
        if np.any(np.diff(st) < 0):
            raise SceneGraphError(f"trajectories[{r}]: stamps must not decrease")
        robots.append(np.full(len(st), int(r), dtype=np.int64))
        index.append(np.arange(len(st), dtype=np.int64))
        stamps.append(st)
        poses.append(P)
    agent_pose = np.concatenate(poses) if poses else np.zeros((0, 4, 4))
    xyz = agent_pose[:, :3, 3] if R is None else agent_pose[:, :3, 3] @ R.T
    agent_place = _attach(field, places, usable, xyz, xyz, xyz, np.zeros(len(xyz), np.int64), p.attach_candidates)
    person_id, person_stamp, person_pos = as_people(people)
    pxyz = person_pos if R is None else person_pos @ R.T
    person_place = _attach(field, places, usable, pxyz, pxyz, pxyz, np.zeros(len(pxyz), np.int64),
                           p.attach_candidates)
    place_pos = places.positions if R is None else places.positions @ R
    if R is not None:
        room_pos, building = room_pos @ R, building @ R
    build_s = time.perf_counter() - t0
    meta = {"delta": rooms.delta, "sweep": {"deltas": rooms.deltas.tolist(), "counts": rooms.counts.tolist()},
            "params": p.to_dict(), "build_s": build_s, "resolution": grid.resolution,
            "level_rotation": None if R is None else R.tolist()}
    kind_rooms = np.where(object_place >= 0, rooms.place_room[np.maximum(object_place, 0)], -1) \
        if len(rooms.place_room) else np.full(len(obs.ids), -1, dtype=np.int64)
    kinds, confidence = load_kind_table().kinds(kind_rooms, obs.labels, nr)
    return SceneGraph(
        places.ids, place_pos, places.clearance, rooms.place_room, places.edges, places.edge_clearance,
        room_pos, room_edges(places, rooms.place_room), obs.ids, obs.labels, obs.centroids, obs.lo, obs.hi,
        object_place, np.concatenate(robots) if robots else np.zeros(0, np.int64),
        np.concatenate(index) if index else np.zeros(0, np.int64),
        np.concatenate(stamps) if stamps else np.zeros(0), agent_pose, agent_place, building, meta,
        person_id, person_stamp, person_pos, person_place, kinds, confidence)
