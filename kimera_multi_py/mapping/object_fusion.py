"""Fusing several robots' object landmarks into one team object map.

:func:`object_groups` decides which same-class boxes are one object; :func:`fuse_objects` fuses a
team's object rows into one list with deterministic ids, the same on every robot that holds the
same rows (the ids of the scene graph's object layer).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from kimera_multi_py.mapping.objects import _max_extent

TEAM_ID_SHIFT = 24  # a team object id: source robot << 24 | the source's landmark id


def object_groups(classes: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float = -0.2,
                  min_iou: float = 0.2) -> np.ndarray:
    """The group of every box: two same-class axis-aligned boxes are one object when they overlap
    by more than ``-margin`` along every axis and their union stays within the class's plausible
    size (:data:`~kimera_multi_py.core.semantics.MAX_OBJECT_EXTENT`: fragments of a long table seen from
    either end merge, two cabinets side by side do not), or when their IoU is at least ``min_iou``
    (two robots' views of one object). Groups are numbered by their first box."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    classes = np.asarray(classes).reshape(-1)
    lo = np.asarray(lo, dtype=float).reshape(-1, 3)
    hi = np.asarray(hi, dtype=float).reshape(-1, 3)
    n = len(classes)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    overlap = np.all((lo[:, None] - margin <= hi[None]) & (hi[:, None] + margin >= lo[None]), axis=2)
    union = np.maximum(hi[:, None], hi[None]) - np.minimum(lo[:, None], lo[None])
    inter = np.clip(np.minimum(hi[:, None], hi[None]) - np.maximum(lo[:, None], lo[None]), 0, None).prod(axis=2)
    vol = (hi - lo).prod(axis=1)
    iou = inter / np.maximum(vol[:, None] + vol[None] - inter, 1e-12)
    fits = union[..., :2].max(axis=2) <= _max_extent(classes)[:, None]
    same = (classes[:, None] == classes[None, :]) & ((overlap & fits) | (iou >= min_iou))
    i, j = np.nonzero(same)
    _, comp = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)), directed=False)
    # renumber by first appearance, so the numbering does not depend on scipy's traversal
    _, first = np.unique(comp, return_index=True)
    order = np.argsort(np.argsort(first))
    return order[comp].astype(np.int64)


def fuse_objects(ids: np.ndarray, classes: np.ndarray, lo: np.ndarray, hi: np.ndarray, sightings: np.ndarray,
                 probs: np.ndarray | None = None) -> list[dict[str, Any]]:
    """One object per :func:`object_groups` group of the rows (team ids ``ids``, in any order):
    id = the group's smallest team id, box = the union, class = the most probable over the summed
    posteriors (``probs``; else the smallest id's class), sightings summed, and ``members`` (the
    team ids fused). Rows are sorted by id first, so equal inputs give equal outputs everywhere."""
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    order = np.argsort(ids, kind="stable")
    ids, classes = ids[order], np.asarray(classes, dtype=np.int64).reshape(-1)[order]
    lo, hi = np.asarray(lo, float).reshape(-1, 3)[order], np.asarray(hi, float).reshape(-1, 3)[order]
    sightings = np.asarray(sightings, dtype=np.int64).reshape(-1)[order]
    P = None if probs is None else np.asarray(probs, dtype=np.float64).reshape(len(ids), -1)[order]
    comp = object_groups(classes, lo, hi)
    out: list[dict[str, Any]] = []
    for g in range(int(comp.max(initial=-1)) + 1):
        sel = np.flatnonzero(comp == g)
        cls = int(classes[sel[0]]) if P is None else int(np.argmax(P[sel, 1:].sum(axis=0))) + 1
        glo, ghi = lo[sel].min(axis=0), hi[sel].max(axis=0)
        out.append({"id": int(ids[sel[0]]), "class": cls, "centroid": ((glo + ghi) / 2).tolist(),
                    "lo": glo.tolist(), "hi": ghi.tolist(), "sightings": int(sightings[sel].sum()),
                    "members": ids[sel].tolist()})
    return out


def team_id(source: int, landmark: int) -> int:
    """The team-wide id of ``source``'s landmark ``landmark``."""
    if not 0 <= landmark < 1 << TEAM_ID_SHIFT:
        raise ValueError(f"landmark id {landmark} of robot {source} does not fit in {TEAM_ID_SHIFT} bits")
    return (int(source) << TEAM_ID_SHIFT) | int(landmark)


def rows_of(objects: Sequence[dict[str, Any]]) -> tuple[np.ndarray, ...]:
    """``(classes, lo, hi, sightings)`` arrays of object dicts (a RobotOutcome's objects)."""
    return (np.array([o["class"] for o in objects], dtype=np.int64),
            np.array([o["lo"] for o in objects], dtype=float).reshape(-1, 3),
            np.array([o["hi"] for o in objects], dtype=float).reshape(-1, 3),
            np.array([o.get("sightings", 1) for o in objects], dtype=np.int64))


def fuse_team(objects_by_robot: dict[int, Sequence[dict[str, Any]]]) -> list[dict[str, Any]]:
    """The centralised team object map of every robot's object dicts (all in one frame), with the
    same team ids and fusion rule as each robot's :meth:`ObjectExchange.team_objects`."""
    ids = [team_id(r, int(o["id"])) for r in sorted(objects_by_robot) for o in objects_by_robot[r]]
    rows = [o for r in sorted(objects_by_robot) for o in objects_by_robot[r]]
    if not rows:
        return []
    classes, lo, hi, sightings = rows_of(rows)
    return fuse_objects(np.array(ids), classes, lo, hi, sightings)
