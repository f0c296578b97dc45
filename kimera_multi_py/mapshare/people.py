"""People sharing: one robot's pure step towards the team's people (docs/algorithms/people.md).

Exactly as objects travel (:mod:`.objects`): every robot publishes a versioned table of its
confirmed people tracks (:class:`~kimera_multi_py.comms.messages.maps.PeopleUpdate`), each sample
anchored in the submap it was seen from, in that submap's reference frame as the map consensus's
pose tables have it; tables flood hop by hop and are refreshed every ``refresh_every`` periods.
:meth:`PeopleExchange.team_people` places every held table whose source's poses are in this robot's
frame and fuses them (:func:`~kimera_multi_py.people.fusion.fuse_people`): robots holding the same
tables and pose tables hold the same people with the same ids.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from kimera_multi_py.comms.messages.maps import PeopleUpdate, SubmapPoses
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import inverse, transform_points
from kimera_multi_py.mapping.object_fusion import team_id
from kimera_multi_py.mapshare.objects import ObjectExchange
from kimera_multi_py.people.fusion import TeamTrack, fuse_people
from kimera_multi_py.people.tracking import PeopleTracker

PEOPLE_MESSAGES = (PeopleUpdate,)


def _cat(parts: list[np.ndarray], dtype: type, *shape: int) -> np.ndarray:
    return np.concatenate(parts).astype(dtype) if parts else np.zeros((0, *shape), dtype)


def people_table(robot: int, version: int, frame: int, tracker: PeopleTracker,
                 poses: SubmapPoses | None) -> PeopleUpdate:
    """The table of ``tracker``'s confirmed tracks, each sample in its submap's reference frame as
    the pose table ``poses`` has it (the tracker's own reference frame without one)."""
    where = {} if poses is None else {int(s): (poses.T_ref[k], poses.T[k]) for k, s in enumerate(poses.submaps)}
    ids, stamps, subs, pos = [], [], [], []
    for t in tracker.confirmed():
        world = tracker.positions(t)
        for s in sorted(set(t.submaps)):
            m = np.asarray(t.submaps) == s
            M = where[s][0] @ inverse(where[s][1]) if s in where else inverse(tracker.correction(s))
            ids.append(np.full(int(m.sum()), t.id, np.int64))
            stamps.append(np.asarray(t.stamps, np.float64)[m])
            subs.append(np.full(int(m.sum()), s, np.int64))
            pos.append(transform_points(M, world[m]))
    return PeopleUpdate(robot=robot, source=robot, version=version, frame=frame, tracks=_cat(ids, np.int64),
                        stamps=_cat(stamps, np.float64), submaps=_cat(subs, np.int64),
                        positions=_cat(pos, np.float64, 3).reshape(-1, 3))


class PeopleExchange(ObjectExchange):
    """One robot's people sharing (see the module docstring)."""

    MESSAGE = PeopleUpdate
    WHAT = "people"
    ROWS = ("tracks", "stamps", "submaps", "positions")

    def __init__(self, robot: int, tracker: Callable[[], PeopleTracker],
                 poses: Callable[[int], SubmapPoses | None], period: float = 5.0, refresh_every: int = 4) -> None:
        super().__init__(robot, lambda: (), poses, 1, period, refresh_every)
        self.tracker = tracker

    def _check(self, msg: Any) -> None:
        """Decoding already refused non-finite samples and negative ids; the rows must be whole."""
        if len(np.unique(np.column_stack([msg.tracks, msg.stamps]), axis=0)) != len(msg.tracks):
            raise MessageError("PeopleUpdate: a track has two samples at one stamp")

    def _own_table(self, version: int) -> Any:
        return people_table(self.robot, version, self.frame, self.tracker(), self.poses(self.robot))

    def team_tracks(self) -> dict[int, TeamTrack]:
        """Every held track placed in this robot's frame, by team id (tables whose source's submap
        poses are in another frame, and samples of submaps without a pose, are left out)."""
        out: dict[int, TeamTrack] = {}
        for src, t in sorted(self.tables.items()):
            poses = self.poses(src)
            if poses is None or poses.frame != self.frame:
                continue
            where = {int(s): k for k, s in enumerate(poses.submaps)}
            world = np.full((len(t.stamps), 3), np.nan)
            for s in np.unique(t.submaps).tolist():
                j = where.get(int(s))
                if j is not None:
                    m = t.submaps == s
                    world[m] = transform_points(poses.T[j] @ inverse(poses.T_ref[j]), t.positions[m])
            ok = np.all(np.isfinite(world), axis=1)
            for tid in np.unique(t.tracks[ok]).tolist():
                m = ok & (t.tracks == tid)
                order = np.argsort(t.stamps[m], kind="stable")
                out[team_id(src, int(tid))] = TeamTrack(src, np.asarray(t.stamps[m])[order], world[m][order])
        return out

    def team_people(self) -> list[dict[str, Any]]:
        """The team's people in this robot's frame (:func:`~kimera_multi_py.people.fusion.fuse_people`)."""
        return fuse_people(self.team_tracks())
