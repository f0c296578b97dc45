"""The team's people: every robot's confirmed tracks fused into one set of people
(docs/algorithms/people.md).

Two tracks of different robots follow the same person when they were seen at the same time in the
same place: at the stamps of one track that the other covers (a sample of it within ``max_gap``
seconds on either side, positions interpolated), the median horizontal distance is at most
``link_distance`` over at least ``min_common`` stamps. Pairs are joined in order of that distance,
never joining two tracks of one robot that overlap in time (that robot saw two people). A fused
person's id is the smallest team id of its tracks (``source << 24 | track id``), so robots that hold
the same tables give the same people the same ids.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.cluster.hierarchy import DisjointSet

from kimera_multi_py.mapping.object_fusion import TEAM_ID_SHIFT


@dataclass
class TeamTrack:
    source: int
    stamps: np.ndarray  # (n,) increasing
    positions: np.ndarray  # (n, 3)


def _distance(a: TeamTrack, b: TeamTrack, max_gap: float, min_common: int) -> float:
    """Median horizontal distance of ``b`` to ``a`` at the stamps of ``a`` that ``b`` covers (inf: too few)."""
    t = a.stamps[(a.stamps >= b.stamps[0] - max_gap) & (a.stamps <= b.stamps[-1] + max_gap)]
    if len(t) < min_common:
        return np.inf
    i = np.clip(np.searchsorted(b.stamps, t), 1, max(len(b.stamps) - 1, 1))
    near = np.minimum(np.abs(b.stamps[i - 1] - t), np.abs(b.stamps[np.minimum(i, len(b.stamps) - 1)] - t))
    ok = near <= max_gap
    if ok.sum() < min_common:
        return np.inf
    bx = np.interp(t[ok], b.stamps, b.positions[:, 0])
    by = np.interp(t[ok], b.stamps, b.positions[:, 1])
    pa = a.positions[(a.stamps >= b.stamps[0] - max_gap) & (a.stamps <= b.stamps[-1] + max_gap)][ok]
    return float(np.median(np.hypot(pa[:, 0] - bx, pa[:, 1] - by)))


def _overlap(a: TeamTrack, b: TeamTrack) -> bool:
    return bool(a.stamps[0] <= b.stamps[-1] and b.stamps[0] <= a.stamps[-1])


def fuse_people(tracks: Mapping[int, TeamTrack], link_distance: float = 0.6, max_gap: float = 1.5,
                min_common: int = 2) -> list[dict[str, Any]]:
    """Fuse tracks keyed by team id into people: ``id``, ``stamps``, ``positions`` (sorted by stamp),
    ``members`` (team ids of the tracks fused), ``sources``."""
    ids = sorted(int(k) for k in tracks if len(tracks[k].stamps))
    pairs = []
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            ta, tb = tracks[a], tracks[b]
            if ta.source == tb.source or not _overlap(ta, tb):
                continue
            d = min(_distance(ta, tb, max_gap, min_common), _distance(tb, ta, max_gap, min_common))
            if d <= link_distance:
                pairs.append((d, a, b))
    groups = DisjointSet(ids)
    for _, a, b in sorted(pairs):
        if groups.connected(a, b):
            continue
        ga, gb = groups.subset(a), groups.subset(b)
        if any(tracks[x].source == tracks[y].source and _overlap(tracks[x], tracks[y]) for x in ga for y in gb):
            continue
        groups.merge(a, b)
    out = []
    for members in sorted((sorted(s) for s in groups.subsets()), key=lambda m: m[0]):
        stamps = np.concatenate([tracks[m].stamps for m in members])
        pos = np.concatenate([tracks[m].positions for m in members]).reshape(-1, 3)
        order = np.argsort(stamps, kind="stable")
        out.append({"id": members[0], "stamps": stamps[order].tolist(), "positions": pos[order].tolist(),
                    "members": members, "sources": sorted({m >> TEAM_ID_SHIFT for m in members})})
    return out
