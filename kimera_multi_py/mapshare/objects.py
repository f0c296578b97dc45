"""Object sharing: one robot's pure step towards the team's object map (docs/algorithms/map_consensus.md, objects).

Every robot publishes a versioned table of its confirmed object landmarks
(:class:`~kimera_multi_py.comms.messages.maps.ObjectUpdate`), each object anchored in one of its
submaps with its box in that submap's reference frame. Where a submap is comes from the map
consensus's pose tables (:class:`~kimera_multi_py.comms.messages.maps.SubmapPoses`), so a PGO
correction moves every robot's copy of the objects exactly, and only a changed table travels.

Tables spread by flooding: a robot publishes a table (its own, or a neighbour's newer one) once
per version, and every ``refresh_every`` periods all it holds again, which recovers lost messages
and partitions; but not a table that every neighbour (the source aside) said it holds: every
table a robot sends lists the newest version of each source it holds (``held_sources``,
``held_versions``). A table of another source that arrived since the robot's last step is
relayed only to neighbours that lag behind the version the robot held at that step: those that
hear the source get the new version from it, and say so in their next tables. So in a team
whose robots all hear each other a table travels once, from its source, while a neighbour that
hears the source only through this robot gets every version a step later. A table is small
(about 130 B per object), so this costs little beside the map.

The team object map (:meth:`ObjectExchange.team_objects`) fuses every held table whose source's
poses are in the robot's frame with :func:`~kimera_multi_py.mapping.object_fusion.fuse_objects`:
robots that hold the same tables and pose tables get the same objects with the same ids, which
is what makes their scene graphs agree. The robot's own objects enter through its own published
table, exactly as the others see them.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.maps import ObjectUpdate, SubmapPoses
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import inverse, transform_points
from kimera_multi_py.mapping.landmark import Landmark
from kimera_multi_py.mapping.object_fusion import fuse_objects, team_id
from kimera_multi_py.mapshare.table_delta import TableHistory, delta_rows, expand_rows

OBJECT_MESSAGES = (ObjectUpdate,)


def own_table(robot: int, version: int, frame: int, landmarks: Iterable[Landmark], num_classes: int,
              poses: SubmapPoses | None) -> ObjectUpdate:
    """The table of ``landmarks`` (confirmed ones), each box expressed in its submap's reference
    frame as the pose table ``poses`` has it (the landmark's own reference frame without one)."""
    rows = []
    where = {} if poses is None else {int(s): (poses.T_ref[k], poses.T[k]) for k, s in enumerate(poses.submaps)}
    for lm in landmarks:
        centre, size, R = lm.box()  # world now
        M = inverse(lm.T_world_ref)  # back into the landmark's reference frame
        if lm.submap in where:  # or into the submap's reference frame as the table has it
            T_ref, T = where[lm.submap]
            M = T_ref @ inverse(T)
        centre, half = transform_points(M, centre[None])[0], np.abs(M[:3, :3] @ R) @ (size / 2)
        counts = lm.class_counts[:num_classes]
        rows.append((lm.id, lm.submap, int(np.argmax(counts[1:])) + 1, counts / counts.sum(), centre, half,
                     lm.num_observations))
    rows.sort(key=lambda r: r[0])
    n = len(rows)
    return ObjectUpdate(robot=robot, source=robot, version=version, frame=frame,
                        ids=np.array([r[0] for r in rows], np.int64), submaps=np.array([r[1] for r in rows], np.int64),
                        classes=np.array([r[2] for r in rows], np.int32),
                        probs=np.array([r[3] for r in rows], np.float32).reshape(n, num_classes),
                        centroids=np.array([r[4] for r in rows], np.float64).reshape(n, 3),
                        extents=np.array([r[5] for r in rows], np.float64).reshape(n, 3),
                        sightings=np.array([r[6] for r in rows], np.int32))


class ObjectExchange:
    """One robot's object sharing (see the module docstring).

    ``landmarks`` gives the robot's confirmed landmarks; ``poses(source)`` the newest pose table
    the robot holds for ``source`` (its own included), or None. Subclasses share other tables
    (:class:`~kimera_multi_py.mapshare.people.PeopleExchange`) through ``MESSAGE``, ``ROWS`` (the
    row fields), ``_check`` and ``_own_table``.

    A table goes as a row delta (:mod:`.table_delta`) against the oldest version of it that a
    neighbour (its source aside) said it holds, when this robot still holds that version;
    refreshes go whole. A delta against a version the receiver no longer holds is ignored and
    counted (``ignored["objects_no_base"]``): a later version or the refresh brings the table.
    """

    MESSAGE: type[Message] = ObjectUpdate
    WHAT = "objects"
    ROWS: tuple[str, ...] = ("ids", "submaps", "classes", "probs", "centroids", "extents", "sightings")

    def __init__(self, robot: int, landmarks: Callable[[], Iterable[Landmark]],
                 poses: Callable[[int], SubmapPoses | None], num_classes: int, period: float = 5.0,
                 refresh_every: int = 4) -> None:
        if period <= 0 or refresh_every < 1:
            raise ValueError("object sharing: period must be positive and refresh_every at least 1")
        self.robot = int(robot)
        self.landmarks = landmarks
        self.poses = poses
        self.num_classes = int(num_classes)
        self.period = float(period)
        self.refresh_every = int(refresh_every)
        self.frame = self.robot
        self.neighbours: set[int] = set()
        self.tables: dict[int, Any] = {}  # source -> newest table
        self.ignored: Counter[str] = Counter()
        self.rounds = 0
        self._version = 0
        self._published: dict[int, int] = {}  # source -> version last published
        self._held_last: dict[int, int] = {}  # source -> the version held at the last step
        self.peer_holds: dict[int, dict[int, int]] = {}  # neighbour -> source -> newest version it holds
        self.history = TableHistory()  # the bases of deltas, sent and received
        self._next = -np.inf

    def set_neighbours(self, ids: Iterable[int]) -> None:
        self.neighbours = {int(i) for i in ids} - {self.robot}

    def set_frame(self, frame: int) -> None:
        self.frame = int(frame)

    def handle(self, message: Message) -> None:
        """Absorb one table; raises :class:`MessageError` on inconsistent content."""
        if not isinstance(message, self.MESSAGE):
            return
        msg: Any = message
        if msg.robot != self.robot:
            self.peer_holds[msg.robot] = dict(zip(msg.held_sources.tolist(), msg.held_versions.tolist(), strict=True))
            self._own_version_seen(max(self.peer_holds[msg.robot].get(self.robot, 0),
                                       msg.version if msg.source == self.robot else 0))
        if msg.robot == self.robot or msg.source == self.robot:
            return
        if msg.robot not in self.neighbours:
            self.ignored["not_neighbour"] += 1
            return
        old = self.tables.get(msg.source)
        if old is not None and msg.version <= old.version:
            self.ignored[f"{self.WHAT}_duplicate"] += 1
            return
        if msg.base:
            base = self.history.get(msg.source, msg.base)
            if base is None:
                self.ignored[f"{self.WHAT}_no_base"] += 1
                return
            msg = dataclasses.replace(msg, base=0, reuse=np.zeros(0, np.int32), **expand_rows(
                type(msg).__name__, {f: getattr(base, f) for f in self.ROWS},
                {f: getattr(msg, f) for f in self.ROWS}, msg.reuse))
        elif len(msg.reuse):
            raise MessageError(f"{type(msg).__name__}.reuse: a whole table (base 0) reuses no rows")
        self._check(msg)
        self.tables[msg.source] = msg
        self.history.add(msg.source, msg.version, msg)

    def _own_version_seen(self, version: int) -> None:
        """A neighbour holds this robot's own table at ``version``. A robot that restarted (the
        exchange is not checkpointed) counts its versions from 0 again, and its neighbours would
        ignore its new tables as duplicates of the old ones they hold: versions continue above
        every one a neighbour reports, and the current table goes out afresh."""
        if version > self._version:
            self._version = int(version)
            self.tables.pop(self.robot, None)

    def _check(self, msg: Any) -> None:
        if msg.probs.shape[1] != self.num_classes:
            raise MessageError(f"ObjectUpdate.probs: expected {self.num_classes} classes, got {msg.probs.shape[1]}")
        if len(np.unique(msg.ids)) != len(msg.ids):
            raise MessageError("ObjectUpdate.ids: duplicate object ids")

    def _own_table(self, version: int) -> Any:
        return own_table(self.robot, version, self.frame, self.landmarks(), self.num_classes, self.poses(self.robot))

    def _content(self, t: Any) -> bytes:
        return b"".join(getattr(t, f).tobytes() for f in self.ROWS)

    def _send(self, t: Any, refresh: bool, sources: np.ndarray, versions: np.ndarray) -> Message:
        """``t`` as this robot sends it: whole, or a row delta against the oldest version of it a
        neighbour (the source aside) holds, when that is older than ``t`` and still held here."""
        fields: dict[str, Any] = {}
        held = [self.peer_holds.get(nb, {}).get(t.source, -1) for nb in self.neighbours if nb != t.source]
        b = min(held, default=-1)
        base = None if refresh or not 0 < b < t.version else self.history.get(t.source, b)
        if base is not None:
            reuse, fresh = delta_rows([getattr(base, f) for f in self.ROWS], [getattr(t, f) for f in self.ROWS])
            fields = {f: getattr(t, f)[fresh] for f in self.ROWS}
            fields.update(base=b, reuse=reuse)
        return dataclasses.replace(t, robot=self.robot, frame=self.frame, held_sources=sources,
                                   held_versions=versions, **fields)

    def step(self, now: float) -> list[Message]:
        """Publish what is due at time ``now`` (seconds): nothing between periods."""
        if now < self._next:
            return []
        self._next = float(now) + self.period
        self.rounds += 1
        table = self._own_table(self._version + 1)
        old = self.tables.get(self.robot)
        if (old is None and self._content(table)) or (old is not None and self._content(old) != self._content(table)):
            self._version += 1
            self.tables[self.robot] = table
            self.history.add(self.robot, self._version, table)
        if not self.neighbours:
            return []
        refresh = self.rounds % self.refresh_every == 0
        held = sorted((src, t.version) for src, t in self.tables.items())
        sources, versions = np.array([s for s, _ in held], np.int32), np.array([v for _, v in held], np.int64)
        out: list[Message] = []
        for src, t in sorted(self.tables.items()):
            due = refresh or t.version > self._published.get(src, 0)
            bar = t.version if src == self.robot else min(t.version, self._held_last.get(src, 0))
            if due and self._lagging(src, bar):
                out.append(self._send(t, refresh, sources, versions))
                self._published[src] = t.version
            elif not self._lagging(src, t.version):  # every neighbour holds it
                self._published[src] = t.version
        self._held_last = {src: t.version for src, t in self.tables.items()}
        return out

    def _lagging(self, src: int, version: int) -> bool:
        """Some neighbour but the source said it holds ``src``'s table only older than ``version``."""
        return any(self.peer_holds.get(nb, {}).get(src, 0) < version for nb in self.neighbours if nb != src)

    def team_objects(self, min_sightings: int = 1) -> list[dict[str, Any]]:
        """The team object map in the robot's frame: every held table whose source's submap poses
        are in this frame, fused (``id``, ``class``, ``centroid``, ``lo``, ``hi``, ``sightings``,
        ``members``); objects seen fewer than ``min_sightings`` times are left out first."""
        ids, cls, lo, hi, sights, probs = [], [], [], [], [], []
        for src, t in sorted(self.tables.items()):
            poses = self.poses(src)
            if poses is None or poses.frame != self.frame:
                continue
            where = {int(s): k for k, s in enumerate(poses.submaps)}
            for k in range(len(t.ids)):
                j = where.get(int(t.submaps[k]))
                if j is None or t.sightings[k] < min_sightings:
                    continue
                C = poses.T[j] @ inverse(poses.T_ref[j])
                c = transform_points(C, t.centroids[k][None])[0]
                half = np.abs(C[:3, :3]) @ t.extents[k]
                ids.append(team_id(src, int(t.ids[k])))
                cls.append(int(t.classes[k]))
                lo.append(c - half)
                hi.append(c + half)
                sights.append(int(t.sightings[k]))
                probs.append(t.probs[k])
        if not ids:
            return []
        return fuse_objects(np.array(ids), np.array(cls), np.array(lo), np.array(hi), np.array(sights),
                            np.array(probs))
